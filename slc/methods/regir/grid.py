r"""A world-space hash grid of cells: 64-bit cell keys in an open-addressed table with buckets
of 32 slots (the layout of SHaRC's ``HashGridCommon``).

A point ``p`` with normal ``n`` lies in the cell ``c = floor(p / h)`` (``h`` the fixed cell size
of the scene) of the normal's octant (the signs of its three components). The key packs the three
cell coordinates (20 bits each, two's complement offset by 2^19, clamped) and the octant (3 bits)
in 63 bits; ``EMPTY`` (all bits set) is never a key.

A key's home bucket is a 32-bit TEA hash of its two words; a key lives in one of the bucket's 32
slots. Insertion is race-free and deterministic: in round ``r`` every key not yet placed looks at
slot ``r`` of its bucket; a slot holding the key places it, an empty slot is claimed by
``scatter_reduce(min)`` (the smallest contending key wins, the others go on to the next slot). A
key that finds no slot in its bucket gets ``INVALID`` (an overflow; the caller falls back).

Eviction frees the cells not used for ``evict_after`` frames. A freed slot can be claimed again
by a key stored further along the bucket; the key then has two cells, the older of which is not
used and is freed in turn: every cell is still a cell of its own key, only its history is lost.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID

BUCKET = 32                      # slots per bucket (SHaRC's HASH_GRID_HASH_MAP_BUCKET_SIZE)
EMPTY = 0xFFFFFFFFFFFFFFFF       # key of a free slot
_BITS = 20
_BIAS = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
KEY_BYTES = 8 + 4 + 4            # key, last frame used, frame claimed


def cell_key(p: mi.Point3f, n: mi.Vector3f, h) -> mi.UInt64:
    """64-bit key of the cells of points ``p`` with normals ``n`` (cell size ``h``)."""
    c = dr.floor(mi.Vector3f(p) / h)
    c = dr.clip(c, -float(_BIAS), float(_BIAS - 1))
    u = [mi.UInt64(mi.UInt32(mi.Int32(c[k]) + _BIAS) & _MASK) for k in range(3)]
    octant = mi.UInt64(dr.select(n.x < 0.0, 1, 0) | dr.select(n.y < 0.0, 2, 0) | dr.select(n.z < 0.0, 4, 0))
    return u[0] | (u[1] << _BITS) | (u[2] << (2 * _BITS)) | (octant << (3 * _BITS))


def key_hash(key: mi.UInt64) -> tuple[mi.UInt32, mi.UInt32]:
    """Two 32-bit hash words of keys (TEA of their two halves): home bucket, random stream."""
    return mi.sample_tea_32(mi.UInt32(key & 0xFFFFFFFF), mi.UInt32(key >> 32), 4)


class HashGrid:
    """The table: ``keys`` (UInt64 per slot), ``used`` (last frame a slot was used) and ``born``
    (frame its key was placed), ``capacity`` slots (a power of two, at least one bucket)."""

    def __init__(self, capacity: int, h: float):
        cap = BUCKET
        while cap < capacity:
            cap *= 2
        self.capacity, self.h = cap, float(h)
        self.buckets = cap // BUCKET
        self.overflow = 0.0
        self.reset()

    def reset(self) -> None:
        self.keys = dr.full(mi.UInt64, EMPTY, self.capacity)
        self.used = dr.zeros(mi.UInt32, self.capacity)
        self.born = dr.zeros(mi.UInt32, self.capacity)
        dr.eval(self.keys, self.used, self.born)

    def memory_bytes(self) -> int:
        return KEY_BYTES * self.capacity

    def load(self) -> float:
        """Fraction of slots holding a key."""
        return float(dr.count(self.keys != EMPTY)[0]) / self.capacity

    def evict(self, frame: mi.UInt32, age: int) -> None:
        """Free the cells last used more than ``age`` frames before ``frame``."""
        old = (self.keys != EMPTY) & (frame - self.used > dr.opaque(mi.UInt32, age))
        self.keys = dr.select(old, EMPTY, self.keys)
        dr.eval(self.keys)

    def insert(self, key: mi.UInt64, active: mi.Bool, frame: mi.UInt32) -> tuple[mi.UInt32, mi.Bool]:
        """Slot of every active key (placed if new; ``INVALID`` where the bucket is full or the
        lane inactive) and whether the lane's key was placed now; marks the slots used in
        ``frame`` and new ones born in it."""
        n = dr.width(key)
        slot = dr.full(mi.UInt32, INVALID, n)
        new = dr.zeros(mi.Bool, n)
        home = (key_hash(key)[0] & (self.buckets - 1)) * BUCKET
        lanes = dr.compress(mi.Bool(active))
        requests = dr.width(lanes)
        for r in range(BUCKET):
            if dr.width(lanes) == 0:
                break
            k = dr.gather(mi.UInt64, key, lanes)
            s = dr.gather(mi.UInt32, home, lanes) + dr.opaque(mi.UInt32, r)
            free = dr.gather(mi.UInt64, self.keys, s) == EMPTY
            dr.scatter_reduce(dr.ReduceOp.Min, self.keys, k, s, free)
            dr.eval(self.keys)
            found = dr.gather(mi.UInt64, self.keys, s) == k
            dr.scatter(slot, s, lanes, found)
            dr.scatter(self.born, frame, s, found & free)
            dr.scatter(new, True, lanes, found & free)
            dr.eval(slot, self.born, new)
            lanes = dr.gather(mi.UInt32, lanes, dr.compress(~found))
        self.overflow = dr.width(lanes) / max(requests, 1)
        dr.scatter(self.used, frame, slot, slot != INVALID)
        dr.eval(self.used)
        return slot, new

    def touched(self, frame: mi.UInt32) -> mi.UInt32:
        """Slots used in ``frame``, in slot order."""
        return dr.compress((self.keys != EMPTY) & (self.used == frame))
