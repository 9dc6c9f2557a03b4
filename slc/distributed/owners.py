"""Who owns a cache entry, and when a record changed enough to be sent again.

Ownership is rendezvous hashing of the entry's *block* (its address with the texel in the block
dropped, :meth:`slc.osc.cache.OnSurfaceCache.entry_address`): every live node scores the block
with a hash of (block, node) and the highest score owns it. Every node computes the same owner
without a message; when a node leaves only its own blocks move (each to the live node that
scored it next highest). A block's entries share their owner, so an owner allocates whole blocks
of its own entries (a block of B^2 entries split over the nodes would be allocated on each of
them) and a block's life at its owner (requested in a frame when any node needs one of its
entries) is its life in the single-process cache.
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


def owners(keys, live, block_shift: int) -> np.ndarray:
    """The owner node (an id from ``live``) of every entry address in ``keys`` (numpy or Dr.Jit;
    ``block_shift``: log2 of the entries per block): rendezvous hashing of the block."""
    k = np.asarray(keys, np.uint64) >> np.uint64(block_shift)
    live = [int(n) for n in live]
    if len(live) == 1 or k.size == 0:
        return np.full(k.shape, live[0], np.int64)
    with np.errstate(over="ignore"):
        salts = [_mix(np.array([n + 1], np.uint64) * np.uint64(0x9E3779B97F4A7C15)) for n in live]
    scores = np.stack([_mix(k ^ salt) for salt in salts])
    return np.asarray(live, np.int64)[np.argmax(scores, axis=0)]


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


def count(mask: mi.Bool) -> int:
    """Lanes set in ``mask`` (0 for an empty mask)."""
    return int(dr.count(mask)[0]) if dr.width(mask) else 0
