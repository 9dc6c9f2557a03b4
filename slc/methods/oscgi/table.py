"""The hash table of the secondary cells (:class:`CellTable`, a base of
:class:`slc.methods.oscgi.secondary.SecondaryCache`): race-free insertion by linear probing, lookup
without insertion, and eviction by rebuilding the table with the surviving cells (see
:mod:`slc.methods.oscgi.secondary`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.core.keys import INVALID
from slc.methods.oscgi.cells import EMPTY, NO_RING, REP_WORDS


class CellTable:
    """Open addressing over ``self.slots`` slots with the per-slot arrays of
    :class:`~slc.methods.oscgi.secondary.SecondaryCache` (``keys``, ``home``, ``used``, ``stamp``,
    ``count``, ``pending``, ``rep``, ``layers``)."""

    def find_or_insert(self, key: mi.UInt32, home: mi.UInt32, active: mi.Bool) -> mi.UInt32:
        """Slot of each key (inserted when absent); INVALID where inactive or the table is full."""
        mask = self.slots - 1
        slot, act = mi.UInt32(home), mi.Bool(active)
        found = dr.full(mi.UInt32, INVALID, dr.width(key))
        dr.eval(slot, act, found)
        for r in range(self.probes):
            # ------------- claim the probed slot where it is empty (smallest key wins) -------------
            cur = dr.gather(mi.UInt32, self.keys, slot, act)
            dr.eval(cur)                  # read before the claim (and no copy of the table on write)
            dr.scatter_reduce(dr.ReduceOp.Min, self.keys, key, slot, act & (cur == EMPTY))
            dr.eval(self.keys)
            # --------------------- ours now (or already)? else probe the next slot ---------------------
            cur = dr.gather(mi.UInt32, self.keys, slot, act)
            mine = act & (cur == key)
            found = dr.select(mine, slot, found)
            act &= ~mine
            slot = dr.select(act, (slot + 1) & mask, slot)
            dr.eval(found, act, slot)
            if r % 2 == 1 and not dr.any(act):       # most requests settle in one or two rounds
                break
        self._overflow = self._overflow + mi.UInt32(dr.count(act))
        got = found != INVALID
        dr.scatter(self.home, home, found, got)
        dr.scatter(self.used, dr.opaque(mi.UInt32, self.frame), found, got)
        dr.eval(self.home, self.used)
        return found

    def find(self, key: mi.UInt32, home: mi.UInt32, active: mi.Bool) -> tuple:
        """(slot, found) of each key, looked up without insertion: linear probing from its home
        slot (a symbolic loop, at most ``probes`` rounds) until the key or an empty slot."""
        mask = self.slots - 1
        k0 = dr.gather(mi.UInt32, self.keys, home, active)

        def cond(j, s, k):
            return active & (j < self.probes) & (k != key) & (k != EMPTY)

        def body(j, s, k):
            s = (s + 1) & mask
            return j + 1, s, dr.gather(mi.UInt32, self.keys, s, active)

        _, slot, k = dr.while_loop(state=(mi.UInt32(0), mi.UInt32(home), k0), cond=cond, body=body,
                                   labels=("j", "s", "k"))
        return slot, active & (k == key)

    def evict(self) -> int:
        """Free the cells not touched in the last ``evict_after`` frames by rebuilding the table
        with the others (see the module); returns the number freed."""
        live = self.keys != EMPTY
        old = self._old(live)
        n_live, n_old = int(dr.count(live)[0]), int(dr.count(old)[0])
        cap = int(self.slots * self.max_load)
        if n_live - n_old > cap:
            n_old += self._drop_least_recent(live, old, n_live - n_old - cap)
        if n_old == 0:
            return 0
        keep = dr.compress(live & ~old)
        if dr.width(keep) == 0:                # nothing survives: a fresh table
            ov, frame = self._overflow, self.frame
            self.reset()
            self._overflow, self.evicted, self.frame = ov, n_old, frame
            return n_old
        self._rebuild(keep)
        self.evicted = n_old
        return n_old

    def _old(self, live: mi.Bool) -> mi.Bool:
        """Live cells not touched in the last ``evict_after`` whole frames."""
        f = dr.opaque(mi.UInt32, self.frame)
        return live & (f - self.used > self.evict_after) & (self.used < f)

    def _drop_least_recent(self, live: mi.Bool, old: mi.Bool, n: int) -> int:
        """Over the load cap: mark (in ``old``) the ``n`` least recently touched live cells that
        are not old yet (then lowest slot); returns how many were marked."""
        idx = np.asarray(dr.compress(live & ~old), dtype=np.int64)
        u = np.asarray(dr.gather(mi.UInt32, self.used, mi.UInt32(aligned(idx, np.uint32))), dtype=np.int64)
        drop = idx[np.lexsort((idx, u))[:n]]
        dr.scatter(old, True, mi.UInt32(aligned(np.sort(drop), np.uint32)))
        return int(drop.size)

    def _rebuild(self, keep: mi.UInt32) -> None:
        """An empty table with the cells at slots ``keep`` (evaluated, ascending) re-inserted and
        their data moved; every other slot in its reset state."""
        # every array in memory (a literal one, e.g. ``pending`` with one bounce, would fold into the
        # gathers below and give another kernel than the one built by _warm_rebuild)
        dr.make_opaque(self.home, self.used, self.stamp, self.count, self.pending, self._reuse_count, self.rep,
                       self.layers)
        per_slot = [(self.home, 1), (self.used, 1), (self.stamp, 1), (self.count, 1), (self.pending, 1),
                    (self._reuse_count, 1), (self.rep, REP_WORDS), (self.layers, 3 * self.B)]
        data = [(type(a), [dr.gather(type(a), a, keep * w + j) for j in range(w)], w) for a, w in per_slot]
        kk, kh = dr.gather(mi.UInt32, self.keys, keep), dr.gather(mi.UInt32, self.home, keep)
        dr.eval(kk, kh, *[v for _, vs, _ in data for v in vs])
        # ------------- an empty table, the surviving keys re-inserted, their data moved -------------
        self.keys = dr.full(mi.UInt32, EMPTY, self.slots)
        ov = self._overflow
        new = self.find_or_insert(kk, kh, mi.Bool(True))
        self._overflow = ov            # the table only shrinks: every survivor finds a slot
        ok = new != INVALID
        fresh = [dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.UInt32, self.slots),
                 dr.zeros(mi.UInt32, self.slots), dr.full(mi.UInt32, NO_RING, self.slots),
                 dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.Float, self.slots * REP_WORDS),
                 dr.zeros(mi.Float, self.slots * 3 * self.B)]
        for arr, (_, vs, w) in zip(fresh, data):
            for j, v in enumerate(vs):
                dr.scatter(arr, v, new * w + j, ok)
        dr.eval(*fresh)
        (self.home, self.used, self.stamp, self.count, self.pending, self._reuse_count, self.rep,
         self.layers) = fresh

    def _warm_rebuild(self) -> None:
        """Build the kernels of an eviction (the selection of old cells, the over-cap selection
        and the rebuild) on a stand-in table of three cells, so that the first real eviction,
        often after an experiment's warm-up frames, builds none. The caller then allocates the
        table afresh. The stand-in must look like a running table to the JIT: distinct arrays in
        memory (equal literal arrays are one variable, and gathers from literals are folded) and
        at least two survivors (a width-1 array is read as a scalar)."""
        U, F, n = mi.UInt32, mi.Float, self.slots
        i = dr.arange(U, n)
        self.keys = dr.select(i < 3, i + 1, EMPTY)
        self.home, self.used, self.stamp, self.count = (dr.full(U, 1 + j, n) for j in range(4))
        self.pending, self._reuse_count = dr.full(U, 5, n), dr.full(U, 6, n)
        self.rep, self.layers = dr.full(F, 7.0, n * REP_WORDS), dr.full(F, 8.0, n * 3 * self.B)
        dr.make_opaque(self.keys, self.home, self.used, self.stamp, self.count, self.pending, self.rep,
                       self.layers, self._reuse_count)
        ov, frame = self._overflow, self.frame
        self.frame = 0
        live = self.keys != EMPTY
        old = self._old(live)                             # none (used = 2 > frame 0)
        dr.count(live), dr.count(old)
        dr.eval(dr.compress(live & ~old))                 # evict()'s selection without the cap
        self._drop_least_recent(live, old, 1)             # the cap: one of the three dropped
        self._rebuild(dr.compress(live & ~old))           # two survivors
        self._overflow, self.frame = ov, frame
