"""A render node of one shared surface cache: the owner protocol, with no transport in it.

A :class:`Node` renders the G-buffers of its own viewers only and keeps a cache of its own (its
own slots, a :class:`slc.osc.cache.OnSurfaceCache`): the entries its viewers need, and the
entries it *owns* that any node needs. Nodes name entries by address
(:meth:`~slc.osc.cache.OnSurfaceCache.entry_address`) and each maps addresses to its own slots.
Entries are grouped in regions (:class:`slc.distributed.owners.Regions`); a region's *home*
(rendezvous hashing, :func:`~slc.distributed.owners.owners`) gets every node's requests for its
entries and owns it, unless it *delegated* it (:mod:`slc.distributed.directory`) to a node that
needs it.

A frame is seven phases (:data:`PHASES`); each takes the messages addressed to it
(:mod:`slc.distributed.messages`) and returns those it sends. A transport carries them
(:class:`slc.distributed.cluster.Cluster`: in one process, or between Ray actors), ``delay``
frames late:

1. ``begin``: the viewers' G-buffers (and, with ``predict``, the G-buffers of their cameras
   extrapolated ``2 x delay + 2`` frames ahead from their last motion); the entries they need; per
   home, :class:`~slc.distributed.messages.Requests` (:class:`~slc.distributed.state.Subscriptions`:
   subscriptions, cancellations after ``lease`` frames unneeded, the need bits);
2. ``forward``: as a home, the other nodes' requests; a region no entry of which exists yet,
   needed by other nodes and not by the home, is delegated to one of them (for the region's
   life); requests for a delegated region are passed on to its owner;
3. ``serve``: delegations taken; the cache's frame with the viewers'
   pixels and the owned entries other nodes need (``extra``); with delay 0, a
   :class:`~slc.distributed.messages.SeedQuery` to the owners of coarser entries of each new owned
   entry outside its region (a payload that reads LOD seeds starts from the finest coarser entry
   that exists anywhere, as in one process);
4. ``answer``: the existing queried entries' records, from before this frame's update; queries
   of entries of delegated regions passed on to their owners;
5. ``relay``: as the owner of delegated regions, the queries their homes passed on, answered;
6. ``update``: new owned entries seeded; every owned entry any node needs updated once, with the
   payload's own update (random numbers keyed by the entry); per node, the
   :class:`~slc.distributed.messages.Records` of the entries it needs now: ``full``, every
   updated record to every node; ``sparse``, a record the node does not hold or one that changed
   by more than ``threshold`` since the record it holds (:func:`~slc.distributed.owners.changed_records`).
   With ``bootstrap`` rays (and a delay), the node updates with that many rays per frame an entry
   its viewers need and hold no record of, until the owner's record arrives;
7. ``shade``: the records that arrived, into the node's slots; its viewers shaded (an entry with
   no value yet shades black).

``single`` (one node, every viewer) and ``independent`` (each node updates every entry its viewers
see, no messages) run the method's own frame. A node that leaves (:meth:`Node.drop`) moves only
its own regions; their entries start anew at their new owners.
"""
from __future__ import annotations

import functools
import os
from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.core.timing import NullTimer
from slc.distributed.directory import Directory
from slc.distributed.messages import Delegate, Relayed, SeedQuery, SeedRelay, SeedReply
from slc.distributed.owners import Regions, count, owners
from slc.distributed.records import codec_for, unpack_into
from slc.distributed.rig import Clock, Strategy, extrapolated, make_method
from slc.distributed.seeds import records_of, seed_queries, seed_slots
from slc.distributed.sending import records_to
from slc.distributed.state import Client, Subscriptions, in_sorted
from slc.methods import FrameContext
from slc.methods.cache_method import EntryPolicy
from slc.scene import gbuffer as gbuf

PHASES = ("begin", "forward", "serve", "answer", "relay", "update", "shade")
# requests ahead of a camera: its pose this many frames beyond the round trip of a request and its
# record (2 x delay); measured on the quick preset's overlap rig at delay 2: FLIP 1.056x delay 0's
# ahead by the round trip alone, 1.006x two frames further (docs/distributed.md, "Latency")
PREDICT_MARGIN = 2
# bytes by kind: requests (subscriptions and cancellations), need bits, seed queries and replies,
# regions delegated, records of entries new at
# their owner, first records of an entry the node does not hold, and records sent again because
# the entry changed, by its state after the update (young: in its first ``new_updates`` updates;
# moving: in a motion phase; settled)
KINDS = ("requests", "needs", "seeds", "ownership", "new", "first", "resend_young", "resend_moving",
         "resend_settled")


def _timed(phase):
    """A phase whose wall and CPU time count as the node's work in the frame."""
    @functools.wraps(phase)
    def run(self, *args):
        with self.clock.part("work"):
            return phase(self, *args)
    return run


class Node:
    """One render node (see the module): node ``node`` of the ``live`` nodes, rendering
    ``viewers`` ({viewer index: :class:`ViewerPoses`}) at ``width`` x ``height`` with the cache
    method ``method`` (a spec, or a :class:`~slc.methods.MethodSpec`: :func:`make_method`) under
    ``strategy`` (:class:`Strategy`)."""

    def __init__(self, node: int, live: list, scene, method, viewers: dict, width: int, height: int,
                 strategy: Strategy, seed: int = 0):
        self.id, self.live, self.scene = int(node), [int(n) for n in live], scene
        self.viewers = dict(sorted(viewers.items()))
        self.width, self.height, self.s = int(width), int(height), strategy
        self.m, self.cache = make_method(method, scene, seed)
        self.codec = codec_for(self.m)            # its entries as records (slc.distributed.records)
        self.regions = Regions(self.cache.layout, strategy.region_level)
        self.dir = Directory(self)
        self.subs: dict[int, Subscriptions] = {}       # home -> this node's subscriptions there
        self.clients: dict[tuple, Client] = {}         # (node, via) -> what it asked of this owner (via: itself,
        #                                                  or the home that passed its requests on)
        self.value = self.boot = self.lost = self.new_now = None    # per slot (see _grow)
        self.pid = os.getpid()
        self.fr = None
        self.missing = 0

    # ------------------------------------------------------------------ helpers
    def home(self, keys: np.ndarray, live=None) -> np.ndarray:
        """The home node of every entry address in ``keys``."""
        return owners(self.regions(keys), self.live if live is None else live)

    def owns(self, keys: np.ndarray) -> np.ndarray:
        """Mask over ``keys``: this node owns the entry (its home and it did not delegate it, or
        delegated to it)."""
        return self.dir.owns(self.regions(keys), self.home(keys))

    def owner(self, keys: np.ndarray) -> np.ndarray:
        """The node this one sends its requests for ``keys`` to: the owner when this node knows
        it (itself, or as the home the node it delegated the region to), else the home."""
        home = self.home(keys)
        return np.where(self.owns(keys), self.id,
                        np.where(home == self.id, self.dir.away_of(self.regions(keys)), home))

    def _grow(self) -> None:
        """The per-slot masks sized to the cache's capacity (old contents kept)."""
        cap = max(int(self.cache.capacity), 1)
        for name in ("value", "boot", "lost", "new_now"):
            a = getattr(self, name)
            if a is None or dr.width(a) < cap:
                out = dr.zeros(mi.Bool, cap)
                if a is not None:
                    dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)))
                dr.eval(out)
                setattr(self, name, out)

    def _pixel_keys(self, gbs: list) -> np.ndarray:
        """The addresses of the entries the pixels of ``gbs`` request (sorted, unique)."""
        if not gbs:
            return np.zeros(0, np.uint32)
        L = self.cache.layout
        valid, vb, within, _ = L.pixel_texels(gbuf.layered(gbs))
        key = np.array(vb * L.block_texels + within, np.uint32)
        return np.unique(key[np.array(valid, bool)])

    def slots_of(self, keys: np.ndarray) -> tuple:
        """(mask over ``keys``: mapped here, their slots (``mi.UInt32``, mapped ones only))."""
        if len(keys) == 0:
            return np.zeros(0, bool), mi.UInt32()
        s = self.cache.address_slots(mi.UInt32(keys))
        ok = np.array(s != INVALID, bool)
        return ok, dr.gather(mi.UInt32, s, mi.UInt32(np.nonzero(ok)[0]))

    # ------------------------------------------------------------------ 1. begin
    def begin(self, frame: int) -> list:
        """G-buffers, needed entries, requests (see the module)."""
        self.clock, self.frame = Clock(), int(frame)
        with self.clock.part("gbuffer"):
            self.gbs, self.pred = self._gbuffers(frame)
        with self.clock.part("work"):
            return self._requests()

    def _gbuffers(self, frame: int) -> tuple:
        """The viewers' G-buffers, and with ``predict`` those of their extrapolated cameras."""
        gbs = gbuf.frame_gbuffers(self.scene, list(self.viewers.values()), frame, self.width, self.height)
        ahead = 2 * self.s.delay + PREDICT_MARGIN
        pred = []
        if self.s.predict and self.s.delay > 0 and frame > 0:
            pred = [gbuf.render_gbuffer(self.scene, extrapolated(p.camera(frame - 1), p.camera(frame), ahead),
                                        self.width, self.height, None, p.name) for p in self.viewers.values()]
        return gbs, pred

    def _requests(self) -> list:
        if not self.s.sharing:
            return []
        self.need_pixels = self._pixel_keys(self.gbs)
        self.need_pred = np.setdiff1d(self._pixel_keys(self.pred), self.need_pixels).astype(np.uint32)
        self.need = np.union1d(self.need_pixels, self.need_pred).astype(np.uint32)
        to, out = self.owner(self.need), []
        for o in self.live:
            if o != self.id:
                msg = self.subs.setdefault(o, Subscriptions()).frame(self.id, o, self.frame, self.need[to == o],
                                                                      self.s.lease, self._holds)
                out += [msg] if msg is not None else []
        return out

    def _holds(self, keys: np.ndarray) -> np.ndarray:
        """Mask over ``keys``: this node holds an owner's record of the entry."""
        if self.value is None or len(keys) == 0:
            return np.zeros(len(keys), bool)
        s = self.cache.address_slots(mi.UInt32(keys))
        ok = s != INVALID
        return np.array(ok & dr.gather(mi.Bool, self.value, s, ok), bool)

    # ------------------------------------------------------------------ 2. forward
    @_timed
    def forward(self, inbox: list) -> list:
        """The other nodes' requests; new regions delegated, requests passed on to the owners of
        delegated regions (as their home)."""
        for msg in inbox:
            self.clients.setdefault((msg.src, msg.src), Client()).apply(msg)
        if not self.s.sharing:
            return []
        return self.dir.decide()

    # ------------------------------------------------------------------ 3. serve
    @_timed
    def serve(self, inbox: list) -> list:
        """Delegations and relayed requests, the cache's frame, seed queries (see the module)."""
        m, ctx = self.m, FrameContext(frame=self.frame)
        self.fr, out = None, []
        if not self.s.sharing:
            return out
        for msg in inbox:
            if isinstance(msg, Delegate):
                self.dir.take(msg)
            elif isinstance(msg, Relayed):
                self.clients.setdefault((msg.client, msg.src), Client()).apply(msg)
        wanted = [c.needed() for c in self.clients.values()]
        remote = np.unique(np.concatenate(wanted)).astype(np.uint32) if wanted else np.zeros(0, np.uint32)
        remote = remote[self.owns(remote)]
        self.needed = np.union1d(self.need, remote).astype(np.uint32)
        extra = np.union1d(remote, self.need_pred).astype(np.uint32)
        fr = m.begin(ctx, self.gbs, NullTimer(), extra=mi.UInt32(extra) if len(extra) else None)
        self._grow()
        self.new_now = dr.zeros(mi.Bool, dr.width(self.value))
        if fr.n_active:
            fr.is_new = fr.is_new | dr.gather(mi.Bool, self.lost, fr.active)
            dr.scatter(self.lost, False, fr.active)
            self.keys = np.array(self.cache.entry_address(fr.active), np.uint32)
            self.fr = fr
            self._new_entries()
            self.owned = self.owns(self.keys)
            if self.s.delay == 0 and self.s.seeds == "exact" and m.reads_seeds and len(self.live) > 1:
                out += seed_queries(self)
        return out

    def _new_entries(self) -> None:
        """A new entry holds nothing yet and nobody holds a record of it."""
        fr = self.fr
        dr.scatter(self.new_now, True, fr.active, fr.is_new)
        for name in ("value", "boot"):
            dr.scatter(getattr(self, name), False, fr.active, fr.is_new)
        new = np.sort(self.keys[np.array(fr.is_new, bool)])
        for c in self.clients.values():
            c.forget(new)

    # ------------------------------------------------------------------ 4. answer, 5. relay
    @_timed
    def answer(self, inbox: list) -> list:
        """Records of the queried entries that exist, before this frame's update; queries of
        entries of delegated regions passed on to their owners."""
        out = []
        for q in inbox:
            if isinstance(q, SeedQuery):
                out += self._reply(q.keys, q.src)
                away = self.dir.away_of(self.regions(q.keys))
                for n in np.unique(away[away >= 0]).tolist():
                    out.append(SeedRelay(self.id, n, self.frame, keys=q.keys[away == n], origin=q.src))
        return out

    @_timed
    def relay(self, inbox: list) -> list:
        """Seed queries passed on by the homes of regions delegated to this node."""
        out = []
        for q in inbox:
            out += self._reply(q.keys, q.origin)
        return out

    def _reply(self, keys: np.ndarray, to: int) -> list:
        keys, words, nbytes = records_of(self, keys)
        return [SeedReply(self.id, to, self.frame, keys=keys, words=words, record_kinds={"seeds": nbytes},
                          counts={"seeds": len(keys)})] if len(keys) else []

    # ------------------------------------------------------------------ 6. update
    @_timed
    def update(self, inbox: list) -> list:
        """Seeds, the owned entries' update, bootstrap, records to the other nodes."""
        m, fr = self.m, self.fr
        self.rays = self.boot_rays = 0
        if not self.s.sharing or fr is None:
            return []
        idx = np.nonzero(self.owned & in_sorted(self.keys, self.needed))[0]
        sub = _subset(fr, idx)
        sub.seed_slot = seed_slots(self, idx, inbox)
        if dr.width(sub.active):
            m.update_requested(FrameContext(frame=self.frame), sub)
            self.rays = int(dr.sum(m.update_rays)[0])
            dr.scatter(self.value, True, sub.active)
        if self.s.bootstrap > 0 and self.s.delay > 0:
            self._bootstrap()
        return records_to(self, sub, self.keys[idx], np.array(sub.is_new, bool))

    def _bootstrap(self) -> None:
        """``bootstrap`` rays on every entry this node's viewers need, owned elsewhere, of which
        it holds no record: the payload's update on its own copy (the record overwrites it)."""
        m, fr = self.m, self.fr
        wait = (~self.owned) & in_sorted(self.keys, self.need_pixels)
        wait &= ~np.array(dr.gather(mi.Bool, self.value, fr.active), bool)
        idx = np.nonzero(wait)[0]
        if len(idx) == 0:
            return
        sub = _subset(fr, idx)
        ok = sub.seed_slot != INVALID
        sub.seed_slot = dr.select(ok & dr.gather(mi.Bool, self.value, sub.seed_slot, ok), sub.seed_slot, INVALID)
        state = dr.select(sub.is_new, 0, dr.gather(mi.UInt32, m.policy_state, sub.active))
        pol = EntryPolicy.of(m.ray_policy(), state)
        pol = EntryPolicy(pol.policy, pol.state, dr.minimum(pol.rays, mi.UInt32(self.s.bootstrap)), pol.unsettled)
        motion = m.update(FrameContext(frame=self.frame), sub, pol)
        dr.scatter(m.policy_state, pol.policy.advance(state, motion), sub.active)
        dr.scatter(self.boot, True, sub.active)
        self.boot_rays = int(dr.sum(pol.rays)[0])

    # ------------------------------------------------------------------ 7. shade
    @_timed
    def shade(self, inbox: list, images: bool = False) -> dict:
        """The records that arrived; the viewers' images (numpy, when ``images``) and the
        frame's figures."""
        m, ctx = self.m, FrameContext(frame=self.frame)
        if not self.s.sharing:
            outs = m.render(ctx, self.gbs, NullTimer())
            self.rays = int(dr.sum(m.update_rays)[0]) if m.update_rays is not None and dr.width(m.update_rays) else 0
            self.boot_rays = 0
        else:
            for msg in inbox:
                ok, slots = self.slots_of(msg.keys)
                if np.any(ok):
                    unpack_into(self.codec, slots, msg.words[:, ok])
                    dr.scatter(self.value, True, slots)
                    dr.scatter(self.boot, False, slots)
            outs = self._shade()
            m.check_images(ctx, outs, self.gbs)       # check mode: as Method.render checks its images
        dr.eval(outs)
        res = {"node": self.id, "pid": self.pid, "rays": self.rays, "boot_rays": self.boot_rays,
               "missing": self.missing, "clock": self.clock, "memory": self.memory_bytes(),
               "delegated": self.dir.count()}
        if images:
            res["images"] = {v: np.array(o, np.float32) for v, o in zip(self.viewers, outs)}
        return res

    def _shade(self) -> list:
        """The viewers' images; a pixel whose entry holds no value yet (no record, no bootstrap)
        is black (``self.missing``: how many)."""
        m, fr = self.m, self.fr
        self.missing = 0
        if fr is None or fr.n_active == 0:
            return [dr.zeros(mi.Color3f, gb.size) for gb in self.gbs]
        usable = self.value | self.boot

        def mask(s):
            s = mi.UInt32(s)
            ok = s != INVALID
            return dr.select(ok & dr.gather(mi.Bool, usable, s, ok), s, INVALID)
        view = fr
        if count(~dr.gather(mi.Bool, usable, fr.active)):
            slots = [mi.UInt32(s) for s in fr.pixel_slot]
            view = replace(fr, pixel_slot=[mask(s) for s in slots],
                           layer_slot=mask(fr.layer_slot) if fr.layer_slot is not None else None)
            self.missing = sum(count((s != INVALID) & (v == INVALID)) for s, v in zip(slots, view.pixel_slot))
        return list(m.shade_all(FrameContext(frame=self.frame), view, self.gbs))

    # ------------------------------------------------------------------ membership
    def drop(self, dead: int, live_before: list) -> None:
        """Node ``dead`` left: the entries it owned start anew at their new owners (rendezvous
        hashing moves only its regions; regions delegated to it or by it are no one's); no node
        holds a record of them; nobody subscribes there."""
        self.live = [n for n in live_before if n != dead]
        self.subs.pop(dead, None)
        self.clients = {k: c for k, c in self.clients.items() if dead not in k}
        if self.value is None:
            return
        cap = dr.width(self.value)
        slots = dr.arange(mi.UInt32, cap)
        mapped = np.array(dr.gather(mi.UInt32, self.cache.pool.blk_vb, slots // self.cache.layout.block_texels)
                          != INVALID, bool)
        keys = np.array(self.cache.entry_address(dr.select(mi.Bool(mapped), slots, 0)), np.uint32)
        gone = mapped & ((self.home(keys, live_before) == dead) | self.dir.drop(dead, self.regions(keys)))
        self.lost |= mi.Bool(gone)
        self.value &= ~mi.Bool(gone)
        self.boot &= ~mi.Bool(gone)
        for c in self.clients.values():
            c.forget(np.sort(keys[gone]))

    def memory_bytes(self) -> int:
        """The method's cache and payload, and this node's protocol state."""
        proto = sum(c.nbytes() for c in self.clients.values())
        proto += sum(s.keys.nbytes + s.last.nbytes for s in self.subs.values()) + self.dir.nbytes()
        proto += sum(dr.width(a) for a in (self.value, self.boot, self.lost, self.new_now) if a is not None)
        return int(self.m.memory_bytes()) + int(proto)


def _subset(fr, idx: np.ndarray):
    """``fr`` restricted to its active entries ``idx`` (for the update; no pixels)."""
    i = mi.UInt32(idx)
    return replace(fr, active=dr.gather(mi.UInt32, fr.active, i), si=dr.gather(type(fr.si), fr.si, i),
                   is_new=dr.gather(mi.Bool, fr.is_new, i), seed_slot=dr.gather(mi.UInt32, fr.seed_slot, i),
                   keys=dr.gather(mi.UInt32, fr.keys, i), pixel_slot=[], pixel_index=[], layer_slot=None,
                   layer_index=None, extra_slot=None)
