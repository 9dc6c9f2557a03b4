"""Render nodes as Ray actors: each node a process holding the scene and its copy of the cache.

Every node keeps the cache's directory (which texels have entries, their slots) as every other
node does: it renders the G-buffers of all viewers for it (the directory is a deterministic
function of all viewers' requests; docs/distributed.md names this cost) and shades only its own
viewers. Per frame (:class:`NodeCluster`):

1. ``update``: each node updates the requested entries it owns (rendezvous hashing of the
   entry keys over the live nodes, :func:`slc.distributed.owners.owners`) and returns, per
   other node, the packed records of its owned entries that node's viewers need and that are
   new to it or changed by more than the threshold since it last got them;
2. the driver hands every node the records addressed to it (``shade``); the node writes them
   into its copy, shades its viewers and returns their images.

A node that dies (its process killed, its machine lost) is dropped: its viewers stop, its
entries are re-owned by the survivors and start anew there.
"""
from __future__ import annotations

import os
from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np
import ray

from slc import methods
from slc.core import backend
from slc.core.keys import INVALID
from slc.distributed.owners import changed_records, count, mask_of, owners
from slc.distributed.run import gbuffers
from slc.methods import FrameContext
from slc.core.timing import NullTimer
from slc.reference.references import image_of
from slc.scene import gbuffer as gbuf
from slc.scene import scenes, views
from slc.scene.camera import Viewer


def rig_viewers(scene, rig: str, n: int, overlap: float, static: bool) -> list:
    """The viewers of a rig (:func:`slc.scene.views.make_rig`), held at frame 0 when ``static``."""
    vs = views.make_rig(scene, rig, n, overlap)
    return [Viewer(v.name, (lambda t, v=v: v.pose(0.0)), v.rig) for v in vs] if static else vs


@ray.remote
class RenderNode:
    """One render node (see the module): ``node`` of the nodes, viewer ``v`` on node
    ``v % n_nodes``; ``rig``: (name, viewers, overlap, static)."""

    def __init__(self, node: int, n_nodes: int, scene: str, spec: str, rig: tuple, width: int, height: int,
                 threshold: float = 0.0, seed: int = 0):
        self.node, self.threshold = int(node), float(threshold)
        self.scene = scenes.load(scene)
        self.viewers = rig_viewers(self.scene, *rig)
        self.width, self.height = int(width), int(height)
        self.method = methods.create(spec, self.scene, seed=seed)
        self.home = {n: [v for v in range(len(self.viewers)) if v % n_nodes == n] for n in range(n_nodes)}
        self.sent = {}            # other node -> (have mask, last records sent) over slots
        self.have = None          # this node holds a value of the entry (owned and updated, or received)
        self.lost = None
        self.fr = self.gbs = None
        self.foreign = 0          # records received of entries this node owns (the protocol says never)

    def drop(self, dead: int, live_before: list) -> None:
        """Node ``dead`` left: its entries start anew at their new owners; no one holds them."""
        self.home.pop(dead, None)
        self.sent.pop(dead, None)
        cache = self.method.cache
        if cache is None:
            return
        gone = owners(cache.entry_keys(dr.arange(mi.UInt32, int(cache.capacity))), live_before) == dead
        dr.eval(gone)
        self.lost = gone if self.lost is None else self.lost | gone
        if self.have is not None:
            self.have &= ~gone
        for d, (have, last) in self.sent.items():
            self.sent[d] = (have & ~gone, last)

    def update(self, frame: int, live: list) -> dict:
        """Update the owned requested entries; the records for each other live node (numpy)."""
        m, ctx = self.method, FrameContext(frame=frame)
        self.scene.set_frame(frame)
        gbs = [gbuf.render_gbuffer(self.scene, v.camera(frame), self.width, self.height,
                                   v.camera(frame - 1) if frame > 0 else None, v.name) for v in self.viewers]
        gbuf.attach_layers(gbs)
        fr = self.fr = m.begin(ctx, gbs, NullTimer())
        self.gbs = gbs
        cap = int(m.cache.capacity)
        self.have = _fit(self.have, cap)
        self.lost = _fit(self.lost, cap)
        if fr.n_active == 0:
            return {}
        fr.is_new = fr.is_new | dr.gather(mi.Bool, self.lost, fr.active)
        dr.scatter(self.lost, False, fr.active)
        owner = owners(fr.keys, live)
        own = dr.compress(owner == self.node)
        if dr.width(own):
            sub = replace(fr, active=dr.gather(mi.UInt32, fr.active, own), si=dr.gather(type(fr.si), fr.si, own),
                          is_new=dr.gather(mi.Bool, fr.is_new, own),
                          seed_slot=dr.gather(mi.UInt32, fr.seed_slot, own), keys=dr.gather(mi.UInt32, fr.keys, own))
            m.update_requested(ctx, sub)
            dr.scatter(self.have, True, sub.active)
        rec = m.pack_records(fr.active)
        out = {}
        for d in live:
            if d == self.node:
                continue
            need = mask_of(mi.UInt32(0), cap, False)
            for v in self.home.get(d, []):
                s = mi.UInt32(fr.pixel_slot[v])
                dr.scatter(need, True, s, s != INVALID)
            have, last = self.sent.get(d, (None, None))
            have = _fit(have, cap)
            last = [_fit(w, cap, mi.UInt32) for w in last] if last else [dr.zeros(mi.UInt32, cap) for _ in rec]
            want = dr.gather(mi.Bool, need, fr.active) & (owner == self.node)
            old = [dr.gather(mi.UInt32, w, fr.active) for w in last]
            dr.scatter(have, False, fr.active, fr.is_new)   # a reallocated slot's record is not the entry's
            send = want & (~dr.gather(mi.Bool, have, fr.active) | changed_records(m, old, rec, self.threshold))
            for w, r in zip(last, rec):
                dr.scatter(w, r, fr.active, send)
            dr.scatter(have, True, fr.active, send)
            dr.eval(have, last)
            self.sent[d] = (have, last)
            idx = dr.compress(send)
            out[d] = (np.array(dr.gather(mi.UInt32, fr.active, idx)),
                      np.stack([np.array(dr.gather(mi.UInt32, r, idx)) for r in rec]) if dr.width(idx)
                      else np.zeros((len(rec), 0), np.uint32),
                      np.array(dr.gather(mi.UInt32, fr.keys, idx)))
        return out

    def shade(self, inbox: list, live: list) -> dict:
        """Write the records ``inbox`` (from :meth:`update` of the other nodes) into this node's
        copy and shade its viewers: viewer index -> image (numpy), and the node's counts."""
        m, fr = self.method, self.fr
        for slots, words, keys in inbox:
            if len(slots) == 0:
                continue
            self.foreign += count(owners(mi.UInt32(keys), live) == self.node)
            s = mi.UInt32(slots)
            m.unpack_records(m.entry_state(), s, [mi.UInt32(w) for w in words])
            dr.scatter(self.have, True, s)
        mine = self.home.get(self.node, [])
        missing = 0
        for v in mine:
            s = mi.UInt32(fr.pixel_slot[v])
            ok = s != INVALID
            missing += count(ok & ~dr.gather(mi.Bool, self.have, s, ok))
        nf = replace(fr, pixel_slot=[fr.pixel_slot[v] for v in mine],
                     pixel_index=[fr.pixel_index[v] for v in mine], layer_slot=None, layer_index=None)
        gbs = [self.gbs[v] for v in mine]
        imgs = m.shade_all(FrameContext(frame=fr.frame), nf, gbs) if fr.n_active and gbs else []
        return {"images": {v: np.array(i) for v, i in zip(mine, imgs)}, "missing": missing,
                "foreign": self.foreign}


def _fit(a, size: int, tp=mi.Bool):
    """``a`` grown to ``size`` lanes (new lanes zero/False); a new array when ``a`` is None."""
    if a is None:
        out = dr.zeros(tp, size)
        dr.make_opaque(out)
        return out
    if dr.width(a) >= size:
        return a
    out = dr.zeros(tp, size)
    dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)))
    dr.eval(out)
    return out


class NodeCluster:
    """``n_nodes`` :class:`RenderNode` actors on the running Ray instance, stepped frame by frame."""

    def __init__(self, n_nodes: int, scene: str, spec: str, rig: tuple, width: int, height: int,
                 threshold: float = 0.0, seed: int = 0, env: dict | None = None):
        opts = {"runtime_env": {"env_vars": env}} if env else {}
        self.actors = {n: RenderNode.options(**opts).remote(n, n_nodes, scene, spec, rig, width, height,
                                                            threshold, seed) for n in range(n_nodes)}
        self.live = list(range(n_nodes))
        self.bytes = []

    def kill(self, node: int) -> None:
        """End node ``node``'s process (a crash) and drop it."""
        ray.kill(self.actors[node])
        self._drop(node)

    def _drop(self, node: int) -> None:
        before = list(self.live)
        self.live.remove(node)
        self.actors.pop(node)
        ray.get([a.drop.remote(node, before) for a in self.actors.values()])

    def step(self, frame: int) -> dict:
        """One frame on every live node: viewer index -> image, and the nodes' counts."""
        outs = {}
        for n, a in list(self.actors.items()):
            try:
                outs[n] = ray.get(a.update.remote(frame, list(self.live)))
            except ray.exceptions.RayActorError:
                self._drop(n)
        inbox = {n: [] for n in self.live}
        sent = 0
        for src, msgs in outs.items():
            for d, msg in msgs.items():
                if d in inbox:
                    inbox[d].append(msg)
                    sent += 4 * len(msg[0]) * (1 + msg[1].shape[0])
        self.bytes.append(sent)
        res = ray.get([self.actors[n].shade.remote(inbox[n], list(self.live)) for n in self.live])
        images = {}
        for r in res:
            images.update(r["images"])
        return {"images": images, "missing": sum(r["missing"] for r in res),
                "foreign": sum(r["foreign"] for r in res)}


def render_on_nodes(scene: str, spec: str, n_nodes: int, rig: tuple, width: int, height: int, frames: int,
                    threshold: float, seed: int = 0, address: str | None = None, output: str = "direct") -> dict:
    """Render ``frames`` frames of ``rig`` ((name, viewers, overlap, static)) on ``n_nodes``
    :class:`RenderNode` actors with sparse owner updates at ``threshold`` (``slc render
    --nodes``): on a local Ray instance of ``n_nodes`` CPUs, or on the cluster at ``address``.
    Returns the last frame's images (viewer index -> HxWx3, composed as the pipeline composes
    the method's ``output``) and the bytes sent per frame.
    Ray is shut down afterwards if this call started it."""
    own = not ray.is_initialized()
    if own:
        if address:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        else:
            # a new local instance, never another process's cluster on this machine
            ray.init(address="local", num_cpus=n_nodes, include_dashboard=False, log_to_driver=False,
                     _system_config=backend.RAY_SYSTEM_CONFIG)
    try:
        env = {"SLC_VARIANT": backend.variant()}
        if "SLC_CACHE" in os.environ:
            env["SLC_CACHE"] = os.environ["SLC_CACHE"]
        nodes = NodeCluster(n_nodes, scene, spec, rig, width, height, threshold=threshold, seed=seed, env=env)
        out = {}
        for f in range(frames):
            out = nodes.step(f)
        # composed with the emission seen directly, as the pipeline's images (the driver's own
        # G-buffers of the last frame; the arrays Ray hands over are read-only, these are copies)
        s = scenes.load(scene)
        vs = rig_viewers(s, *rig)
        gbs = gbuffers(s, vs, frames - 1, width, height)
        images = {v: image_of(output, gbs[v], mi.Color3f(np.array(img, np.float32)))
                  for v, img in out.get("images", {}).items()}
        return {"images": images, "bytes_per_frame": nodes.bytes, "missing": out.get("missing", 0)}
    finally:
        if own:
            ray.shutdown()
