"""Who owns a cache entry, and when a record changed enough to be sent again.

Ownership is rendezvous hashing of the entry's *region*: every live node scores the region with a
hash of (region, node) and the highest score owns it. Every node computes the same owner without
a message; when a node leaves only its own regions move (each to the live node that scored it
next highest). A region (:class:`Regions`) is the block (B x B texels) of the entry's coarser
entries at level ``T`` that covers it (an entry of level ``T`` or coarser: its own block): an
entry and its coarser entries up to level ``T`` share their owner, so a new entry's LOD seed is
mostly its owner's own, and a block's entries share their owner, so an owner allocates whole
blocks of its own entries and a block's life at its owner (requested in a frame when any node
needs one of its entries) is its life in the single-process cache.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser: a 64-bit hash of ``x`` (uint64)."""
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return (x ^ (x >> np.uint64(31))) & _M64


class Regions:
    """The region of entries of a cache ``layout`` (:class:`slc.osc.layout.CacheLayout`; see the
    module) at level ``level``: ``regions(addresses)`` (numpy) -> each entry's region, the virtual
    block at level min(max(its level, ``level``), its island's top level) that covers it."""

    def __init__(self, layout, level: int):
        self.level, self.levels, self.shift = int(level), int(layout.levels), int(layout.block_shift)
        self.base = np.array(layout.d_lvl_base, np.int64)
        self.nbx = np.array(layout.d_lvl_nbx, np.int64)
        self.maxl = np.array(layout.d_isl_maxl, np.int64)

    def __call__(self, keys) -> np.ndarray:
        return self.of(keys)[0]

    def of(self, keys) -> tuple:
        """(regions, delegatable: the entry's level is at most ``level``, so that its region holds
        every coarser entry covering it up to that level)."""
        vb = np.asarray(keys, np.int64) >> (2 * self.shift)
        k = np.searchsorted(self.base, vb, side="right") - 1       # (island, level) of each block
        isl, lvl = k // self.levels, k % self.levels
        local = vb - self.base[k]
        by, bx = local // self.nbx[k], local % self.nbx[k]
        up = np.maximum(np.minimum(np.maximum(lvl, self.level), self.maxl[isl]), lvl) - lvl
        ka = k + up
        return (self.base[ka] + (by >> up) * self.nbx[ka] + (bx >> up)).astype(np.uint64), lvl <= self.level


def owners(regions, live) -> np.ndarray:
    """The owner node (an id from ``live``) of every region in ``regions`` (numpy): rendezvous
    hashing."""
    k = np.asarray(regions, np.uint64)
    live = [int(n) for n in live]
    if len(live) == 1 or k.size == 0:
        return np.full(k.shape, live[0], np.int64)
    with np.errstate(over="ignore"):
        salts = [_mix(np.array([n + 1], np.uint64) * np.uint64(0x9E3779B97F4A7C15)) for n in live]
    scores = np.stack([_mix(k ^ salt) for salt in salts])
    return np.asarray(live, np.int64)[np.argmax(scores, axis=0)]


def changed_records(codec, last: list, rec: list, threshold: float) -> mi.Bool:
    """Entries whose record ``rec`` changed by more than ``threshold`` since ``last`` (the record
    the node holds; the payload's measure :meth:`slc.distributed.records.RecordCodec.change`); at threshold 0 every
    record whose words differ, so that the node holds the owner's value bit for bit."""
    differ = mi.Bool(False)
    for a, b in zip(last, rec):
        differ |= mi.UInt32(a) != mi.UInt32(b)
    if threshold <= 0:
        return differ
    return differ & (codec.change(last, rec) > threshold)


def count(mask: mi.Bool) -> int:
    """Lanes set in ``mask`` (0 for an empty mask)."""
    return int(dr.count(mask)[0]) if dr.width(mask) else 0
