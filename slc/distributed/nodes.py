"""Render nodes sharing one surface cache: the owner protocol and the strategies, in one process.

The cache's *directory* (which texels have entries, their slots) is the same on every node: it
is a deterministic function of the union of the viewers' requests, and an entry is named by its
key in every message. The entries' *values* live with their owner
(:func:`slc.distributed.owners.owners`): the owner updates each entry any node requests, once
per frame, with the payload's own update (random numbers keyed by the entry, so the value does
not depend on who asked), and holds it as the authoritative value. Every node shades its own
viewers from its own copy (:class:`slc.distributed.owners.NodeCopy`): its owned entries
directly, the others from the records their owners sent it.

Per frame, for each node ``n`` and strategy:

1. *requests*: the entries n's viewers touch that n does not own; a new one is a subscription
   (its key to the owner), one n stops needing a cancellation (its key); nothing is sent for
   an entry n keeps needing.
2. *records*: the owner sends n an entry's packed record when n subscribed to it (or it is new),
   or, ``sparse``, when it changed by more than ``threshold``
   (:meth:`~slc.osc.payload.PayloadMethod.record_change`) since the record n last got;
   ``full`` sends every record updated in the frame to every other node.
3. *delivery*: records arrive ``delay`` frames after they are sent; n shades from what it holds.

``independent`` (no traffic: every node its own cache, updating every entry it sees) is run by
:mod:`slc.distributed.run` with one method instance per node.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID
from slc.distributed.owners import KEY_BYTES, Message, NodeCopy, count, mask_of, owners
from slc.osc.payload import PayloadMethod
from slc.osc.protocol import FrameRequests


@dataclass(frozen=True)
class Strategy:
    """How owners share records: ``full`` (every updated record to every other node) or
    ``sparse`` (a record when asked for or changed by more than ``threshold``), arriving
    ``delay`` frames after it is sent."""
    kind: str
    delay: int = 0
    threshold: float = 0.0

    @property
    def label(self) -> str:
        return f"{self.kind}-d{self.delay}" + (f"-t{self.threshold:g}" if self.kind == "sparse" else "")


@dataclass
class Traffic:
    """One frame's bytes sent by all nodes under one strategy."""
    request_bytes: int = 0
    record_bytes: int = 0
    records: int = 0
    node_ms: dict = field(default_factory=dict)    # node -> ms of its exchange and shading

    @property
    def total(self) -> int:
        return self.request_bytes + self.record_bytes


def node_requests(fr: FrameRequests, viewers: list) -> FrameRequests:
    """The frame's requests restricted to the pixels of ``viewers`` (indices into the frame's
    viewers); the entry arrays are the frame's (an entry's index is the same on every node)."""
    return replace(fr, pixel_slot=[fr.pixel_slot[v] for v in viewers],
                   pixel_index=[fr.pixel_index[v] for v in viewers], layer_slot=None, layer_index=None)


class SharedCacheNodes:
    """``n_nodes`` render nodes, viewer ``v`` on node ``v % n_nodes`` (round-robin), sharing the
    cache of ``method`` (the owners' authoritative values) under each of ``strategies``.

    :meth:`step` runs one frame: the owners' update of every requested entry (the rays of the
    single-process shared cache, counted once), the single-process images, and per strategy
    every live node's requests, records, deliveries and images."""

    def __init__(self, method: PayloadMethod, n_nodes: int, n_viewers: int, strategies: list):
        self.method = method
        self.live = list(range(int(n_nodes)))
        self.viewers = {n: [v for v in range(n_viewers) if v % n_nodes == n] for n in self.live}
        self.strategies = list(strategies)
        self.copies = {}            # (strategy, node) -> NodeCopy
        self.lost = None            # slots whose owner left (their values start anew)

    # ------------------------------------------------------------------ membership
    def kill(self, node: int) -> None:
        """Node ``node`` leaves: its viewers stop, its entries are re-owned by the surviving
        nodes (rendezvous hashing moves only those) and start anew there; the survivors
        subscribe to them again."""
        cache = self.method.cache
        old = list(self.live)
        self.live.remove(node)
        self.viewers.pop(node, None)
        if cache is None or not self.live:
            return
        slots = dr.arange(mi.UInt32, max(int(cache.capacity), 1))
        gone = owners(cache.entry_keys(slots), old) == node
        dr.eval(gone)
        self.lost = gone if self.lost is None else self.lost | gone
        for (s, n), c in list(self.copies.items()):
            if n == node:
                del self.copies[(s, n)]
            else:
                c.forget(gone)

    # ------------------------------------------------------------------ frame
    def step(self, ctx, gbuffers, timer) -> dict:
        """One frame (see the class). Returns ``single`` (all viewers' images from the owners'
        values), ``rays`` (update rays of the frame, summed), ``owned_rays`` (per live node),
        ``update_ms`` and ``shade_ms`` (the owners' update and the single-process shading), and
        per strategy label ``images`` (viewer -> image of the live nodes' viewers) and
        ``traffic`` (:class:`Traffic`)."""
        m = self.method
        fr = m.begin(ctx, gbuffers, timer)
        n_active = fr.n_active
        if self.lost is not None and n_active:
            fr.is_new = fr.is_new | dr.gather(mi.Bool, self.lost, fr.active)
            dr.scatter(self.lost, False, fr.active)

        # ------------------------------- owners: every requested entry updated once
        rays = mi.UInt32()
        t0 = time.perf_counter()
        with timer.stage("update"):
            if n_active:
                m.update_requested(ctx, fr)
                rays = m.update_rays
                dr.eval(m.storage, m.policy_state)
                dr.sync_thread()
        update_ms = 1e3 * (time.perf_counter() - t0)
        owner = owners(fr.keys, self.live) if n_active else mi.UInt32()
        out = {"rays": int(dr.sum(rays)[0]) if n_active else 0, "update_ms": update_ms,
               "owned_rays": {n: int(dr.sum(dr.select(owner == n, rays, 0))[0]) if n_active else 0
                              for n in self.live}}

        # ------------------------------- the single-process shared cache's images
        t0 = time.perf_counter()
        with timer.stage("shade"):
            out["single"] = self._shade(ctx, fr, gbuffers, m.entry_state())
            dr.sync_thread()
        out["shade_ms"] = 1e3 * (time.perf_counter() - t0)
        if not n_active:
            return out
        rec = m.pack_records(fr.active)
        rec_bytes = m.record_bytes(rec)
        dr.eval(rec, rec_bytes, owner)
        owned_bytes = int(dr.sum(rec_bytes)[0]) + KEY_BYTES * n_active

        # ------------------------------- per strategy: requests, records, delivery, images
        auth = m.entry_state()
        for s in self.strategies:
            traffic, images = Traffic(), {}
            if s.kind == "full":      # every updated record to every other node
                traffic.record_bytes = owned_bytes * (len(self.live) - 1)
                traffic.records = n_active * (len(self.live) - 1)
            for n in self.live:
                t0 = time.perf_counter()
                c = self._copy(s, n, auth, len(rec))
                self._exchange(s, n, c, ctx.frame, fr, owner, rec, rec_bytes, traffic)
                nf = node_requests(fr, self.viewers[n])
                # traced, not replayed: a node's arrays give recordings whose widths coincide with
                # other inputs' differently from frame to frame, and Dr.Jit's replay can fail on them
                with dr.scoped_set_flag(dr.JitFlag.KernelFreezing, False):
                    imgs = self._shade(ctx, nf, [gbuffers[v] for v in self.viewers[n]], c.state)
                dr.sync_thread()
                traffic.node_ms[n] = 1e3 * (time.perf_counter() - t0)
                images.update(zip(self.viewers[n], imgs))
            m.set_entry_state(auth)
            out[s.label] = {"images": images, "traffic": traffic}
        return out

    def _copy(self, s: Strategy, n: int, auth: dict, words: int) -> NodeCopy:
        cap = int(self.method.cache.capacity)
        c = self.copies.get((s, n))
        if c is None:
            c = self.copies[(s, n)] = NodeCopy.blank(auth, cap, words)
        c.grow(auth, cap)
        return c

    def _exchange(self, s: Strategy, n: int, c: NodeCopy, frame: int, fr: FrameRequests, owner, rec, rec_bytes,
                  traffic: Traffic) -> None:
        """Node ``n``'s requests, the records its owners send it, its own entries and the records
        that arrive this frame, into ``c`` (see the module)."""
        m, cap = self.method, int(self.method.cache.capacity)
        need = mask_of(mi.UInt32(0), cap, False)
        for v in self.viewers[n]:
            slot = mi.UInt32(fr.pixel_slot[v])
            dr.scatter(need, True, slot, slot != INVALID)
        need_act = dr.gather(mi.Bool, need, fr.active)
        owned = owner == n
        remote = need_act & ~owned

        # ------------------------------- requests: subscriptions and cancellations (a key each)
        new_sub = remote & (~dr.gather(mi.Bool, c.sub, fr.active) | fr.is_new)
        remote_cap = mask_of(fr.active, cap, remote)
        cancel = c.sub & ~remote_cap
        traffic.request_bytes += KEY_BYTES * (count(new_sub) + count(cancel))
        c.sub = remote_cap

        # ------------------------------- records from the owners
        if s.kind == "full":
            send = remote
        else:
            fresh = new_sub | ~dr.gather(mi.Bool, c.have, fr.active)
            last = [dr.gather(mi.UInt32, w, fr.active) for w in c.sent]
            send = remote & (fresh | (m.record_change(last, rec) > s.threshold))
            traffic.records += count(send)
            traffic.record_bytes += int(dr.sum(dr.select(send, rec_bytes + KEY_BYTES, 0))[0])
        for w, r in zip(c.sent, rec):
            dr.scatter(w, r, fr.active, send)
        dr.scatter(c.have, True, fr.active, send)
        idx = dr.compress(send)
        if dr.width(idx):
            msg = Message(frame, frame + s.delay, dr.gather(mi.UInt32, fr.active, idx),
                          [dr.gather(mi.UInt32, r, idx) for r in rec])
            dr.eval(msg.slots, msg.words)
            c.queue.append(msg)

        # ------------------------------- own entries now, others as their records arrive
        m.unpack_records(c.state, fr.active, rec, need_act & owned)
        while c.queue and c.queue[0].arrive <= frame:
            msg = c.queue.pop(0)
            m.unpack_records(c.state, msg.slots, msg.words)
        dr.eval(c.state, c.have, c.sub, c.sent)

    def _shade(self, ctx, fr: FrameRequests, gbuffers, state: dict) -> list:
        """The viewers' images shaded from ``state`` (the owner's state is restored by the caller)."""
        m = self.method
        if not gbuffers:
            return []
        m.set_entry_state(state)
        if fr.n_active == 0:
            return [dr.zeros(mi.Color3f, gb.size) for gb in gbuffers]
        outs = list(m.shade_all(ctx, fr, gbuffers))
        dr.eval(outs)
        return outs
