"""A render node of one shared surface cache: the owner protocol, with no transport in it.

A :class:`Node` renders the G-buffers of its own viewers only and keeps a cache of its own (its
own slots, a :class:`slc.osc.cache.OnSurfaceCache`): the entries its viewers need, and the
entries it *owns* (:func:`slc.distributed.owners.owners`: by block) that any node needs. The
directory is so partitioned by owner: nodes name entries by address
(:meth:`~slc.osc.cache.OnSurfaceCache.entry_address`) and each maps addresses to its own slots.

A frame is five phases (:data:`PHASES`); each takes the messages addressed to it
(:mod:`slc.distributed.messages`) and returns those it sends. A transport carries them
(:class:`slc.distributed.cluster.Cluster`: in one process, or between Ray actors), ``delay``
frames late:

1. ``begin``: the viewers' G-buffers (and, with ``predict``, the G-buffers of their cameras
   extrapolated ``2 x delay`` frames ahead from their last motion); the entries they need; per
   owner, :class:`~slc.distributed.messages.Requests` (:class:`~slc.distributed.state.Subscriptions`:
   subscriptions, cancellations after ``lease`` frames unneeded, the need bits);
2. ``serve``: the requests of the other nodes; the cache's frame with the viewers' pixels and the
   owned entries other nodes need (``extra``); with delay 0, a
   :class:`~slc.distributed.messages.SeedQuery` to the owners of the coarser entries of each new
   owned entry (a payload that reads LOD seeds starts from the finest one that exists anywhere,
   as in one process);
3. ``answer``: the existing queried entries' records, from before this frame's update;
4. ``update``: new owned entries seeded; every owned entry any node needs updated once, with the
   payload's own update (random numbers keyed by the entry); per node, the
   :class:`~slc.distributed.messages.Records` of the entries it needs now: ``full``, every
   updated record to every node; ``sparse``, a record the node does not hold or one that changed
   by more than ``threshold`` since the record it holds (:func:`~slc.distributed.owners.changed_records`).
   With ``bootstrap`` rays (and a delay), the node updates with that many rays per frame an entry its
   viewers need and hold no record of, until the owner's record arrives;
5. ``shade``: the records that arrived, into the node's slots; its viewers shaded (an entry with
   no value yet shades black).

``single`` (one node, every viewer) and ``independent`` (each node updates every entry its viewers
see, no messages) run the method's own frame. A node that leaves (:meth:`Node.drop`) moves only
its own blocks; their entries start anew at their new owners.
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
from slc.distributed.messages import KEY_BYTES, Records, SeedQuery, SeedReply
from slc.distributed.owners import changed_records, count, owners
from slc.distributed.records import unpack_into
from slc.distributed.rig import Clock, Strategy, extrapolated, make_method
from slc.distributed.seeds import ancestors, finest
from slc.distributed.state import Client, Subscriptions, in_sorted
from slc.methods import FrameContext
from slc.osc.payload import EntryPolicy
from slc.scene import gbuffer as gbuf

PHASES = ("begin", "serve", "answer", "update", "shade")
# bytes by kind: requests (subscriptions and cancellations), need bits, seed queries and replies,
# records of entries new at their owner, first records of an entry the node does not hold, and
# records sent again because the entry changed, by its state after the update (young: in its
# first ``new_updates`` updates; moving: in a motion phase; settled)
KINDS = ("requests", "needs", "seeds", "new", "first", "resend_young", "resend_moving", "resend_settled")


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
    method ``spec`` under ``strategy`` (:class:`Strategy`)."""

    def __init__(self, node: int, live: list, scene, spec: str, viewers: dict, width: int, height: int,
                 strategy: Strategy, seed: int = 0):
        self.id, self.live, self.scene = int(node), [int(n) for n in live], scene
        self.viewers = dict(sorted(viewers.items()))
        self.width, self.height, self.s = int(width), int(height), strategy
        self.m, self.cache = make_method(spec, scene, seed)
        self.subs: dict[int, Subscriptions] = {}       # owner -> this node's subscriptions there
        self.clients: dict[int, Client] = {}           # other node -> what it asked of this owner
        self.value = self.boot = self.lost = self.new_now = None    # per slot (see _grow)
        self.pid = os.getpid()
        self.fr = self.seed = None
        self.missing = 0

    # ------------------------------------------------------------------ helpers
    def _shift(self) -> int:
        return 2 * self.cache.layout.block_shift

    def _owners(self, keys: np.ndarray, live=None) -> np.ndarray:
        return owners(keys, self.live if live is None else live, self._shift())

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

    # ------------------------------------------------------------------ 1. begin
    def begin(self, frame: int) -> list:
        """G-buffers, needed entries, requests (see the module)."""
        self.clock, self.frame = Clock(), int(frame)
        with self.clock.part("gbuffer"):
            self.gbs, pred = self._gbuffers(frame)
        with self.clock.part("work"):
            return self._requests()

    def _gbuffers(self, frame: int) -> tuple:
        """The viewers' G-buffers, and with ``predict`` those of their extrapolated cameras."""
        self.scene.set_frame(frame)
        gbs = [gbuf.render_gbuffer(self.scene, p.camera(frame), self.width, self.height,
                                   p.camera(frame - 1) if frame > 0 else None, p.name) for p in self.viewers.values()]
        gbuf.attach_layers(gbs)
        lead = 2 * self.s.delay
        pred = []
        if self.s.predict and lead > 0 and frame > 0:
            pred = [gbuf.render_gbuffer(self.scene, extrapolated(p.camera(frame - 1), p.camera(frame), lead),
                                        self.width, self.height, None, p.name) for p in self.viewers.values()]
        self.pred = pred
        return gbs, pred

    def _requests(self) -> list:
        if not self.s.sharing:
            return []
        self.need_pixels = self._pixel_keys(self.gbs)
        self.need_pred = np.setdiff1d(self._pixel_keys(self.pred), self.need_pixels).astype(np.uint32)
        need = np.union1d(self.need_pixels, self.need_pred).astype(np.uint32)
        own, out = self._owners(need), []
        for o in self.live:
            if o != self.id:
                msg = self.subs.setdefault(o, Subscriptions()).frame(self.id, o, self.frame, need[own == o],
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

    # ------------------------------------------------------------------ 2. serve
    @_timed
    def serve(self, inbox: list) -> list:
        """The other nodes' requests, the cache's frame, seed queries (see the module)."""
        m, ctx = self.m, FrameContext(frame=self.frame)
        for msg in inbox:
            self.clients.setdefault(msg.src, Client()).apply(msg)
        self.fr = self.seed = None
        if not self.s.sharing:
            return []
        wanted = [c.needed() for c in self.clients.values()] + [self.need_pred]
        extra = np.unique(np.concatenate(wanted)).astype(np.uint32) if wanted else np.zeros(0, np.uint32)
        extra = extra[(self._owners(extra) == self.id) | in_sorted(extra, self.need_pred)]
        fr = m.begin(ctx, self.gbs, NullTimer(), extra=mi.UInt32(extra) if len(extra) else None)
        self._grow()
        self.new_now = dr.zeros(mi.Bool, dr.width(self.value))
        out = []
        if fr.n_active:
            fr.is_new = fr.is_new | dr.gather(mi.Bool, self.lost, fr.active)
            dr.scatter(self.lost, False, fr.active)
            dr.scatter(self.new_now, True, fr.active, fr.is_new)
            for name in ("value", "boot"):        # a new entry holds nothing yet
                dr.scatter(getattr(self, name), False, fr.active, fr.is_new)
            self.keys = np.array(self.cache.entry_address(fr.active), np.uint32)
            self.owned = self._owners(self.keys) == self.id
            new_owned = np.sort(self.keys[self.owned & np.array(fr.is_new, bool)])
            for c in self.clients.values():       # nobody holds a record of a new entry
                c.forget(new_owned)
            if self.s.delay == 0 and m.reads_seeds and len(self.live) > 1:
                out = self._seed_queries(fr)
        self.fr = fr
        return out

    # ------------------------------------------------------------------ seeds
    def _existing(self, keys: np.ndarray) -> tuple:
        """(mask over ``keys``, their slots): owned entries seen before this frame (a seed's
        condition, :func:`slc.osc.requests.lod_seeds`)."""
        s = self.cache.address_slots(mi.UInt32(keys))
        ok = s != INVALID
        ok &= (dr.gather(mi.UInt32, self.cache.pool.slot_seen, s, ok) > 0) & ~dr.gather(mi.Bool, self.new_now, s, ok)
        ok = np.array(ok, bool) & (self._owners(keys) == self.id)
        return ok, s

    def _seed_queries(self, fr) -> list:
        new = np.nonzero(self.owned & np.array(fr.is_new, bool))[0]
        self.seed = None
        if len(new) == 0:
            return []
        keys, ok = ancestors(self.cache, dr.gather(mi.UInt32, fr.active, mi.UInt32(new)))
        self.seed = (new, keys, ok)
        cand = np.unique(keys[ok])
        own = self._owners(cand)
        self.local_seeds = cand[own == self.id]
        return [SeedQuery(self.id, o, self.frame, keys=cand[own == o]) for o in self.live
                if o != self.id and np.any(own == o)]

    # ------------------------------------------------------------------ 3. answer
    @_timed
    def answer(self, inbox: list) -> list:
        """Records of the queried entries that exist, before this frame's update."""
        out = []
        for q in inbox:
            keys, words, nbytes = self._records_of(q.keys)
            if len(keys):
                out.append(SeedReply(self.id, q.src, self.frame, keys=keys, words=words, kinds={"seeds": nbytes}))
        return out

    def _records_of(self, keys: np.ndarray) -> tuple:
        """(keys, words, bytes) of the existing owned entries among ``keys`` (addresses)."""
        if len(keys) == 0:
            return keys, None, 0
        ok, s = self._existing(keys)
        keys = keys[ok]
        if len(keys) == 0:
            return keys, None, 0
        slots = dr.gather(mi.UInt32, s, mi.UInt32(np.nonzero(ok)[0]))
        rec = self.m.pack_records(slots)
        nbytes = int(dr.sum(self.m.record_bytes(rec))[0]) + KEY_BYTES * len(keys)
        return keys, np.stack([np.array(w, np.uint32) for w in rec]), nbytes

    # ------------------------------------------------------------------ 4. update
    @_timed
    def update(self, inbox: list) -> list:
        """Seeds, the owned entries' update, bootstrap, records to the other nodes."""
        m, fr = self.m, self.fr
        self.rays = self.boot_rays = 0
        out = []
        if self.s.sharing and fr is not None and fr.n_active:
            idx = np.nonzero(self.owned)[0]
            sub = _subset(fr, idx)
            sub.seed_slot = self._seed_slots(fr, idx, inbox)
            if dr.width(sub.active):
                m.update_requested(FrameContext(frame=self.frame), sub)
                self.rays = int(dr.sum(m.update_rays)[0])
                dr.scatter(self.value, True, sub.active)
            if self.s.bootstrap > 0 and self.s.delay > 0:
                self._bootstrap(fr)
            out = self._records(sub, self.keys[idx], np.array(sub.is_new, bool))
        return out

    def _seed_slots(self, fr, idx: np.ndarray, replies: list) -> mi.UInt32:
        """The LOD seed of every owned entry ``idx``: with delay 0 the finest coarser entry that
        exists at its owner, its record written into the new entry's own slot (the update reads
        it there); else the cache's own choice when this node holds a value of it."""
        seed = dr.gather(mi.UInt32, fr.seed_slot, mi.UInt32(idx))
        if not self.m.reads_seeds or len(self.live) == 1:
            return seed
        if self.s.delay > 0 or getattr(self, "seed", None) is None:
            ok = seed != INVALID
            return dr.select(ok & dr.gather(mi.Bool, self.value, seed, ok), seed, INVALID)
        new, keys, valid = self.seed
        found = [self._records_of(self.local_seeds)[:2]] + [(r.keys, r.words) for r in replies]
        found = [(k, w) for k, w in found if len(k)]
        self.seed = None
        if not found:
            return dr.full(mi.UInt32, INVALID, len(idx))
        fk, fw = np.concatenate([k for k, _ in found]), np.concatenate([w for _, w in found], axis=1)
        order = np.argsort(fk)
        fw, pick = fw[:, order], finest(keys, valid, fk[order])
        seeded = pick >= 0
        out = dr.full(mi.UInt32, INVALID, len(idx))
        if np.any(seeded):
            slots = dr.gather(mi.UInt32, fr.active, mi.UInt32(new[seeded]))
            unpack_into(self.m, slots, fw[:, pick[seeded]])
            pos = np.searchsorted(idx, new[seeded])
            dr.scatter(out, slots, mi.UInt32(pos))
        return out

    def _bootstrap(self, fr) -> None:
        """``bootstrap`` rays on every entry this node's viewers need, owned elsewhere, of which
        it holds no record: the payload's update on its own copy (the record overwrites it)."""
        m = self.m
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

    def _records(self, sub, keys: np.ndarray, is_new: np.ndarray) -> list:
        """Per other node, the records it gets of the owned entries ``sub`` (see the module)."""
        m = self.m
        if dr.width(sub.active) == 0:
            return []
        rec = m.pack_records(sub.active)
        nb = m.record_bytes(rec) + KEY_BYTES
        st = dr.gather(mi.UInt32, m.policy_state, sub.active)       # after this update
        young = np.array((st & 0xFFFF) <= m.ray_policy().new_updates, bool)
        moving = ~young & np.array((st >> 16) > 0, bool)
        rec_np = np.stack([np.array(w, np.uint32) for w in rec])
        nb = np.array(nb, np.int64)
        out = []
        for j in self.live:
            if j == self.id:
                continue
            c = self.clients.setdefault(j, Client())
            held, last = c.holds(keys)
            if self.s.kind == "full":
                send = np.ones(len(keys), bool)
            else:
                send = in_sorted(keys, c.needed())
                test = np.nonzero(send & held)[0]
                if len(test):
                    t = mi.UInt32(test)
                    changed = changed_records(m, [mi.UInt32(w) for w in last[:, test]],
                                              [dr.gather(mi.UInt32, w, t) for w in rec], self.s.threshold)
                    send[test] = np.array(changed, bool)
            idx = np.nonzero(send)[0]
            if len(idx) == 0:
                continue
            again = held[idx]
            kinds = {"new": is_new[idx], "first": ~is_new[idx] & ~again,
                     "resend_young": again & young[idx], "resend_moving": again & moving[idx],
                     "resend_settled": again & ~young[idx] & ~moving[idx]}
            kb = {k: int(nb[idx][v].sum()) for k, v in kinds.items()}
            words = rec_np[:, idx]
            c.sent(keys[idx], words)
            out.append(Records(self.id, j, self.frame, keys=keys[idx], words=words, kinds=kb))
        return out

    # ------------------------------------------------------------------ 5. shade
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
                self._receive(msg)
            outs = self._shade()
        dr.eval(outs)
        res = {"node": self.id, "pid": self.pid, "rays": self.rays, "boot_rays": self.boot_rays,
               "missing": self.missing, "clock": self.clock, "memory": self.memory_bytes()}
        if images:
            res["images"] = {v: np.array(o, np.float32) for v, o in zip(self.viewers, outs)}
        return res

    def _receive(self, msg: Records) -> None:
        if len(msg.keys) == 0:
            return
        s = self.cache.address_slots(mi.UInt32(msg.keys))
        ok = np.array(s != INVALID, bool)
        if not np.any(ok):
            return
        slots = dr.gather(mi.UInt32, s, mi.UInt32(np.nonzero(ok)[0]))
        unpack_into(self.m, slots, msg.words[:, ok])
        dr.scatter(self.value, True, slots)
        dr.scatter(self.boot, False, slots)

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
        hashing moves only those); no node holds a record of them; nobody subscribes there."""
        self.live = [n for n in live_before if n != dead]
        self.subs.pop(dead, None)
        self.clients.pop(dead, None)
        if self.value is None:
            return
        cap = dr.width(self.value)
        slots = dr.arange(mi.UInt32, cap)
        mapped = dr.gather(mi.UInt32, self.cache.pool.blk_vb, slots // self.cache.layout.block_texels) != INVALID
        keys = np.array(self.cache.entry_address(dr.select(mapped, slots, 0)), np.uint32)
        gone = mi.Bool(np.array(mapped, bool) & (owners(keys, live_before, self._shift()) == dead))
        self.lost |= gone
        self.value &= ~gone
        self.boot &= ~gone
        for c in self.clients.values():
            c.forget(np.sort(keys[np.array(gone, bool)]))

    def memory_bytes(self) -> int:
        """The method's cache and payload, and this node's protocol state."""
        proto = sum(c.nbytes() for c in self.clients.values())
        proto += sum(s.keys.nbytes + s.last.nbytes for s in self.subs.values())
        proto += sum(dr.width(a) for a in (self.value, self.boot, self.lost, self.new_now) if a is not None)
        return int(self.m.memory_bytes()) + int(proto)


def _subset(fr, idx: np.ndarray):
    """``fr`` restricted to its active entries ``idx`` (for the update; no pixels)."""
    i = mi.UInt32(idx)
    return replace(fr, active=dr.gather(mi.UInt32, fr.active, i), si=dr.gather(type(fr.si), fr.si, i),
                   is_new=dr.gather(mi.Bool, fr.is_new, i), seed_slot=dr.gather(mi.UInt32, fr.seed_slot, i),
                   keys=dr.gather(mi.UInt32, fr.keys, i), pixel_slot=[], pixel_index=[], layer_slot=None,
                   layer_index=None, extra_slot=None)
