"""A pool of fixed-size payload records with a free list (Dr.Jit, vectorized).

The adaptive cache keeps one pool per representation, so that an entry
stores only the representation it uses. A pool holds ``capacity`` records of
``words`` 32-bit words (``data[slot * words + k]``) and a stack of free
slots (``free[0 .. top-1]``). Allocation and release are vectorized over
entries: the ``k``-th requesting lane (exclusive prefix sum of the request
mask, deterministic) takes ``free[top - 1 - k]``; releases push onto the
stack the same way. ``top`` is a host integer, passed to kernels as an
opaque value (no recompilation when it changes). The pool grows (doubling,
old records kept) when a frame asks for more slots than are free.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID


def _exclusive_rank(mask: mi.Bool) -> mi.UInt32:
    """Rank of every true lane among the true lanes (0, 1, ...); deterministic."""
    m = mi.UInt32(dr.select(mask, 1, 0))
    return dr.prefix_sum(m)               # exclusive


class Pool:
    """Records of ``words`` UInt32 words with a free list (see the module)."""

    def __init__(self, name: str, words: int, initial: int = 64):
        self.name, self.words = name, int(words)
        self.capacity, self.top = 0, 0
        self.data = dr.zeros(mi.UInt32, 0)
        self.free = dr.zeros(mi.UInt32, 0)
        # two steps, so that the growth kernels are built here and not in a timed frame
        self._resize(max(int(initial) // 2, 32))
        self._resize(max(int(initial), 64))

    # ------------------------------------------------------------------ size
    @property
    def used(self) -> int:
        return self.capacity - self.top

    def bytes_allocated(self) -> int:
        """Records and free list: what the pool holds in memory."""
        return self.capacity * (4 * self.words + 4)

    def bytes_used(self) -> int:
        return self.used * 4 * self.words

    def _grow(self, need_free: int) -> None:
        if self.top < need_free:
            old = self.capacity
            self._resize(max(2 * old, old + need_free - self.top, 64))

    def _resize(self, cap: int) -> None:
        """Grow to ``cap`` records (whole arrays copied: widths >= 32, never a
        width-1 array, which a kernel would read as a scalar)."""
        old = self.capacity
        data = dr.zeros(mi.UInt32, cap * self.words)
        free = dr.zeros(mi.UInt32, cap)
        if old > 0:
            dr.scatter(data, self.data, dr.arange(mi.UInt32, old * self.words))
            dr.scatter(free, self.free, dr.arange(mi.UInt32, old))
        # the new slots join the stack above the old free ones
        added = cap - old
        dr.scatter(free, dr.arange(mi.UInt32, added) + dr.opaque(mi.UInt32, old),
                   dr.arange(mi.UInt32, added) + dr.opaque(mi.UInt32, self.top))
        self.data, self.free = data, free
        self.capacity, self.top = cap, self.top + added
        dr.eval(self.data, self.free)

    # ------------------------------------------------------------------ alloc / free
    def acquire(self, mask: mi.Bool, n: int | None = None) -> mi.UInt32:
        """A fresh slot for every true lane of ``mask`` (INVALID elsewhere); ``n``,
        when given, is the mask's lane count (else counted here: a wait). The
        record's contents are stale: the caller initialises it."""
        if n is None:
            n = int(dr.count(mask)[0]) if dr.width(mask) else 0
        # no early exit when n == 0: the same kernels run in every frame (none built after warm-up)
        self._grow(n)
        rank = _exclusive_rank(mask)
        pos = dr.opaque(mi.UInt32, max(self.top - 1, 0)) - rank
        slot = dr.gather(mi.UInt32, self.free, pos, mask)
        self.top -= n
        slot = dr.select(mask, slot, INVALID)
        dr.eval(slot)
        return slot

    def release(self, slot: mi.UInt32, mask: mi.Bool, n: int | None = None) -> None:
        """Return the slots of the true lanes of ``mask`` to the free list (each
        once); ``n``, when given, is the count of true lanes of ``mask`` with a
        valid slot (else counted here: a wait)."""
        mask = mi.Bool(mask) & (mi.UInt32(slot) != INVALID)
        if n is None:
            n = int(dr.count(mask)[0]) if dr.width(mask) else 0
        rank = _exclusive_rank(mask)
        dr.scatter(self.free, mi.UInt32(slot), dr.opaque(mi.UInt32, self.top) + rank, mask)
        self.top += n
        dr.eval(self.free)

    def gather(self, slot: mi.UInt32, active=True) -> list:
        base = mi.UInt32(slot) * self.words
        return [dr.gather(mi.UInt32, self.data, base + k, active) for k in range(self.words)]

    def scatter(self, words, slot: mi.UInt32, active=True) -> None:
        base = mi.UInt32(slot) * self.words
        for k in range(self.words):
            dr.scatter(self.data, mi.UInt32(words[k]), base + k, active)
