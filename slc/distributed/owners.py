"""Who owns a cache entry, and what a node holds of the entries it does not own.

Ownership is rendezvous hashing of the entry's viewer-independent 32-bit key
(:attr:`slc.osc.protocol.FrameRequests.keys`): every live node scores the key
with a hash of (key, node) and the highest score owns it. Every node computes
the same owner without a message, and when a node leaves only its own
entries move (each to the live node that scored it next highest).

A message between nodes holds, per entry, its 4-byte key and, for a record,
the payload's packed words (:meth:`slc.osc.payload.PayloadMethod.pack_records`;
slc's 3 cones: 9 words, 36 bytes). Requests (a subscription to an entry, or
its end) are one key each.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.osc.blocks import extend_array

KEY_BYTES = 4          # an entry's key in a request or in front of a record


def owners(keys: mi.UInt32, live: list) -> mi.UInt32:
    """The owner node (an id from ``live``) of every key: rendezvous hashing."""
    best, owner = dr.zeros(mi.UInt32, dr.width(keys)), dr.full(mi.UInt32, live[0], dr.width(keys))
    for node in live:
        score, _ = mi.sample_tea_32(mi.UInt32(keys), dr.opaque(mi.UInt32, 0x51ED0000 + int(node)), 4)
        take = score > best
        owner = dr.select(take, mi.UInt32(node), owner)
        best = dr.select(take, score, best)
    return owner


@dataclass
class Message:
    """Records on their way to one node: sent in frame ``sent``, applied in frame ``arrive``."""
    sent: int
    arrive: int
    slots: mi.UInt32
    words: list


@dataclass
class NodeCopy:
    """One node's copy of the cache under one strategy.

    ``state``: the payload's per-entry arrays (:meth:`PayloadMethod.entry_state`) the node
    shades from; ``have``: the node holds a record of the entry; ``sub``: the node has asked
    the entry's owner for it (and not cancelled); ``sent``: per word, the record the owner last
    sent this node (what the change threshold compares with); ``queue``: records not yet
    arrived."""
    state: dict
    have: mi.Bool
    sub: mi.Bool
    sent: list
    last_need: mi.UInt32 = None
    queue: list = field(default_factory=list)

    @classmethod
    def blank(cls, template: dict, capacity: int, words: int) -> "NodeCopy":
        """An empty copy shaped as ``template`` (the owner's entry state)."""
        state = {k: dr.zeros(type(v), dr.width(v)) for k, v in template.items()}
        for v in state.values():
            dr.make_opaque(v)      # in memory: frozen shading kernels take it as an input
        return cls(state, dr.zeros(mi.Bool, capacity), dr.zeros(mi.Bool, capacity),
                   [dr.zeros(mi.UInt32, capacity) for _ in range(words)], dr.zeros(mi.UInt32, capacity))

    def grow(self, template: dict, capacity: int) -> None:
        """Arrays grown to the owner's (new contents zero, old kept)."""
        for k, v in template.items():
            if dr.width(self.state[k]) < dr.width(v):
                self.state[k] = extend_array(self.state[k], 0, dr.width(v), type(v))
        if dr.width(self.have) < capacity:
            self.have = extend_bool(self.have, capacity)
            self.sub = extend_bool(self.sub, capacity)
            self.sent = [extend_array(w, 0, capacity, mi.UInt32) for w in self.sent]
            self.last_need = extend_array(self.last_need, 0, capacity, mi.UInt32)

    def forget(self, mask: mi.Bool) -> None:
        """Entries (a mask over slots) whose owner is gone: neither held nor asked for."""
        self.have &= ~mask
        self.sub &= ~mask


def changed_records(method, last: list, rec: list, threshold: float) -> mi.Bool:
    """Entries whose record ``rec`` changed by more than ``threshold`` since ``last`` (the record
    the node holds; :meth:`~slc.osc.payload.PayloadMethod.record_change`); at threshold 0 every
    record whose words differ, so that the node holds the owner's value bit for bit."""
    differ = mi.Bool(False)
    for a, b in zip(last, rec):
        differ |= mi.UInt32(a) != mi.UInt32(b)
    if threshold <= 0:
        return differ
    return differ & (method.record_change(last, rec) > threshold)


def extend_bool(a: mi.Bool, size: int) -> mi.Bool:
    """A mask grown to ``size`` lanes (the new ones False)."""
    out = dr.zeros(mi.Bool, size)
    dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)))
    dr.eval(out)
    return out


def count(mask: mi.Bool) -> int:
    """Lanes set in ``mask`` (0 for an empty mask)."""
    return int(dr.count(mask)[0]) if dr.width(mask) else 0


def mask_of(slots, capacity: int, active=True) -> mi.Bool:
    """A mask over ``capacity`` slots, set at ``slots`` (where ``active``)."""
    out = dr.zeros(mi.Bool, capacity)
    dr.scatter(out, True, mi.UInt32(slots), active)
    return out
