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
   (its key to the owner), one n's viewers have not needed for ``lease`` frames a cancellation
   (its key); nothing is sent for an entry n keeps needing or needs again within the lease.
2. *records*: the owner sends n an entry's packed record when n holds none of it (it is new, or
   n never got it), or, ``sparse``, when it changed by more than ``threshold`` since the record
   n holds (:func:`slc.distributed.owners.changed_records`); n keeps the records of entries it
   stopped needing. ``full`` sends every record updated in the frame to every other node.
   :attr:`Traffic.kinds` splits the bytes by kind (:data:`KINDS`).
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
from slc.distributed.owners import KEY_BYTES, Message, NodeCopy, changed_records, count, mask_of, owners
from slc.osc.payload import PayloadMethod
from slc.osc.protocol import FrameRequests


@dataclass(frozen=True)
class Strategy:
    """How owners share records: ``full`` (every updated record to every other node) or
    ``sparse`` (a record the node does not hold, or one changed by more than ``threshold``
    since the record it holds), arriving ``delay`` frames after it is sent; a node stays
    subscribed to an entry ``lease`` frames after its viewers last needed it."""
    kind: str
    delay: int = 0
    threshold: float = 0.0
    lease: int = 0

    @property
    def label(self) -> str:
        return f"{self.kind}-d{self.delay}" + (
            (f"-t{self.threshold:g}" + (f"-l{self.lease}" if self.lease else "")) if self.kind == "sparse" else "")


# the kinds of bytes a frame's traffic is split into (:attr:`Traffic.kinds`): subscriptions and
# cancellations; records of entries new in the frame; first records of an entry the node does not
# hold; records sent again because the entry changed, by the entry's state after the update
# (:class:`slc.osc.payload.RayPolicy`: young in its first ``new_updates`` updates, else moving in
# a motion phase, else settled)
KINDS = ("requests", "new", "first", "resend_young", "resend_moving", "resend_settled")


@dataclass
class Traffic:
    """One frame's bytes sent by all nodes under one strategy."""
    request_bytes: int = 0
    record_bytes: int = 0
    records: int = 0
    node_ms: dict = field(default_factory=dict)    # node -> ms of its exchange and shading
    kinds: dict = field(default_factory=lambda: dict.fromkeys(KINDS, 0))   # kind -> bytes (:data:`KINDS`)

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
        # a reallocated slot holds another entry: the node neither holds nor asks for it (every
        # node knows this from the directory, without a message)
        dr.scatter(c.have, False, fr.active, fr.is_new)
        dr.scatter(c.sub, False, fr.active, fr.is_new)
        # a node stays subscribed to an entry for ``lease`` frames after its viewers last needed it
        dr.scatter(c.last_need, mi.UInt32(frame + 1), dr.compress(need))
        keep = c.sub & ~need & (mi.UInt32(frame + 1) - c.last_need <= s.lease)
        owned = owner == n
        remote = dr.gather(mi.Bool, need | keep, fr.active) & ~owned

        # ------------------------------- requests: subscriptions and cancellations (a key each)
        new_sub = remote & ~dr.gather(mi.Bool, c.sub, fr.active)
        sub = mask_of(fr.active, cap, remote) | (keep & ~mask_of(fr.active, cap, owned))
        cancel = c.sub & ~sub
        req = KEY_BYTES * (count(new_sub) + count(cancel))
        traffic.request_bytes += req
        traffic.kinds["requests"] += req
        c.sub = sub

        # ------------------------------- records from the owners
        if s.kind == "full":
            send = remote
        else:
            # a node keeps the records of the entries it stopped needing: one it subscribes to
            # again is sent only if it changed since the record the node holds
            fresh = ~dr.gather(mi.Bool, c.have, fr.active)
            last = [dr.gather(mi.UInt32, w, fr.active) for w in c.sent]
            send = remote & (fresh | changed_records(m, last, rec, s.threshold))
            traffic.records += count(send)
            traffic.record_bytes += _account(traffic, m, fr, send, fresh, rec_bytes + KEY_BYTES)
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
        m.unpack_records(c.state, fr.active, rec, dr.gather(mi.Bool, need, fr.active) & owned)
        while c.queue and c.queue[0].arrive <= frame:
            msg = c.queue.pop(0)
            m.unpack_records(c.state, msg.slots, msg.words)
        dr.eval(c.state, c.have, c.sub, c.sent, c.last_need)

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


def _account(traffic: Traffic, m: PayloadMethod, fr: FrameRequests, send: mi.Bool, fresh: mi.Bool,
             nbytes: mi.UInt32) -> int:
    """The bytes of the records ``send`` (``nbytes`` each, over ``fr.active``) added to
    ``traffic.kinds`` by kind (:data:`KINDS`); returns their sum."""
    state = dr.gather(mi.UInt32, m.policy_state, fr.active)      # after this frame's update
    young = (state & 0xFFFF) <= m.ray_policy().new_updates
    moving = ~young & ((state >> 16) > 0)
    again = send & ~fresh
    masks = {"new": send & fr.is_new, "first": send & fresh & ~fr.is_new, "resend_young": again & young,
             "resend_moving": again & moving, "resend_settled": again & ~young & ~moving}
    sums = {k: dr.sum(dr.select(v, nbytes, 0)) for k, v in masks.items()}
    dr.eval(sums)
    for k, v in sums.items():
        traffic.kinds[k] += int(v[0])
    return sum(int(v[0]) for v in sums.values())
