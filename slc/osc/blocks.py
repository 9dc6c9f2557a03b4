"""The block table and the pool of physical blocks of the on-surface cache.

Virtual blocks (see :mod:`.layout`) are mapped to physical blocks through a
two-level table: a directory with one entry per page of ``2**page_shift``
virtual blocks, and pages (allocated on demand) holding a physical block id
or INVALID per virtual block. A physical block holds ``B x B`` entry slots:
``slot = phys * B^2 + texel_in_block``; payload arrays are indexed by slot.

Blocks are mapped when first requested (lowest free physical block first),
stamped with the frame tick whenever requested, and freed when unused for
more than ``evict_after`` frames. When the pool is full it doubles
(``grow=True``), or the least recently used blocks not requested this frame
are freed early and what still does not fit is reported.

Per slot the pool keeps one word, ``slot_seen``: 0 until the slot's first
frame after allocation, then 1. It tells the cache which entries are new and
which may serve as LOD seeds or filter taps (every active entry is updated
by its payload in the frame that requested it: the cache-method contract).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.osc.layout import CacheLayout

PAGE_SHIFT = 6   # 64 virtual blocks per page: measured best on Sponza at 320x180 (docs/osc.md)


def widen(a):
    """``a`` evaluated, its single element repeated when it has one.

    Dr.Jit loads an evaluated width-1 operand as a scalar, so a kernel fed by
    a per-frame list (new blocks, evicted blocks, new pages, new entries) that
    holds one element is not the kernel fed by a longer list: it would be
    compiled when it first happens, after warm-up too. Callers use widened
    lists only in idempotent operations (gathers, plain scatters of equal
    values) or mask the copy with :func:`lanes`. The copy is made from a
    Python list (a memcpy, no kernel); not from a numpy array, whose memory
    Dr.Jit may keep with an alignment of its own that changes the kernel."""
    dr.eval(a)
    if dr.width(a) == 1:
        a = type(a)(np.array(a).tolist() * 2)
    return a


def lanes(width: int, n: int) -> mi.Bool:
    """The first ``n`` of ``width`` lanes (``n`` opaque: one kernel for every count)."""
    return dr.arange(mi.UInt32, width) < dr.opaque(mi.UInt32, n)


def extend_array(a, fill, size, tp):
    """``a`` (evaluated, of type ``tp``: ``mi.UInt32`` or ``mi.Float``) grown
    to ``size`` entries, the new ones set to ``fill``.

    The copy is evaluated alone, so that it is one kernel per element type
    whatever else grows in the same frame (copies of equal width evaluated
    together would fuse into a kernel of their own); :func:`build_copy_kernels`
    builds these kernels ahead, as a growth may first happen in any frame."""
    out = dr.full(tp, fill, size)
    dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)))
    dr.eval(out)
    return out


def build_copy_kernels() -> None:
    """Build the kernels of :func:`extend_array` for both element types of
    the arrays that grow (block table, pool, surface points, payloads), with
    copies of two elements (a width-1 array would be read as a scalar: another
    kernel). Called when a pool or a payload is set up, so that one that grows
    in a timed frame builds no kernel."""
    for tp in (mi.UInt32, mi.Float):
        extend_array(tp([0, 0]), 0, 4, tp)


class BlockPool:
    """Block table + physical block pool + per-slot ``seen`` flags.

    Parameters: ``layout`` (:class:`.layout.CacheLayout`), ``max_blocks``
    (initial physical blocks), ``grow`` (double when full; else LRU
    eviction and overflow report)."""

    def __init__(self, layout: CacheLayout, max_blocks: int, grow: bool = True):
        self.layout = layout
        self.B2 = layout.block_texels
        self.page_shift = PAGE_SHIFT
        self.page_span = 1 << PAGE_SHIFT
        self.grow = bool(grow)
        self.initial_blocks = int(max_blocks)
        build_copy_kernels()
        self.reset()

    # ------------------------------------------------------------------ state
    @property
    def capacity(self) -> int:
        """Entry slots of the pool (payload arrays are sized by it)."""
        return self.max_blocks * self.B2

    def reset(self) -> None:
        self.max_blocks = self.initial_blocks
        self.n_dir = max(-(-self.layout.n_vblocks // self.page_span), 1)
        self.dir = dr.full(mi.UInt32, INVALID, self.n_dir)
        self._alloc_pages(max(64, min(self.n_dir, 4 * self.max_blocks // self.page_span + 64)))
        self.n_pages = 0
        nb, n = self.max_blocks, self.max_blocks * self.B2
        self.blk_vb = dr.full(mi.UInt32, INVALID, nb)      # physical block -> virtual block
        self.blk_last = dr.zeros(mi.UInt32, nb)             # tick of last request
        self.blk_key = dr.zeros(mi.UInt32, nb)              # island * levels + level
        self.blk_xy = dr.zeros(mi.UInt32, nb)               # bx | by << 16
        self.blk_rank = dr.zeros(mi.UInt32, nb)             # scratch: rank among this frame's blocks
        self.slot_seen = dr.zeros(mi.UInt32, n)             # 0 until the slot's first frame
        # arrays, not literals: the first frame's allocation then runs the kernels of any later one
        dr.make_opaque(self.dir, self.blk_vb, self.blk_last, self.blk_key, self.blk_xy, self.blk_rank,
                       self.slot_seen)
        self.n_blocks = 0
        self.evicted_early = 0

    def _alloc_pages(self, npg):
        self.max_pages = npg
        self.pages = dr.full(mi.UInt32, INVALID, npg * self.page_span)  # physical block or INVALID
        self.pg_dir = dr.full(mi.UInt32, INVALID, npg)             # page -> directory entry (INVALID: free)
        self.pg_count = dr.zeros(mi.UInt32, npg)                   # mapped blocks in the page
        dr.eval(self.pages, self.pg_dir, self.pg_count)

    def _grow_pages(self, need):
        old = self.max_pages
        npg = max(2 * old, old + need)
        self.max_pages = npg
        self.pages = extend_array(self.pages, INVALID, npg * self.page_span, mi.UInt32)
        self.pg_dir = extend_array(self.pg_dir, INVALID, npg, mi.UInt32)
        self.pg_count = extend_array(self.pg_count, 0, npg, mi.UInt32)
        dr.eval(self.pages, self.pg_dir, self.pg_count)

    def _grow_pool(self, need_blocks):
        old = self.max_blocks
        nb = max(2 * old, old + need_blocks)
        self.blk_vb = extend_array(self.blk_vb, INVALID, nb, mi.UInt32)
        self.blk_last = extend_array(self.blk_last, 0, nb, mi.UInt32)
        self.blk_key = extend_array(self.blk_key, 0, nb, mi.UInt32)
        self.blk_xy = extend_array(self.blk_xy, 0, nb, mi.UInt32)
        self.blk_rank = dr.zeros(mi.UInt32, nb)
        self.slot_seen = extend_array(self.slot_seen, 0, nb * self.B2, mi.UInt32)
        self.max_blocks = nb
        dr.eval(self.blk_vb, self.blk_last, self.blk_key, self.blk_xy, self.slot_seen)

    def table_bytes(self) -> int:
        """The block table: directory (4 B per page of 64 virtual blocks) +
        the allocated pages (64 x 4 B + 8 B each) + 16 B per allocated block
        (virtual id, last use, island/level, block x/y)."""
        return 4 * self.n_dir + (4 * self.page_span + 8) * self.n_pages + 16 * self.n_blocks

    # ------------------------------------------------------------------ lookup
    def phys(self, vb, active=True):
        """Physical block of virtual blocks (INVALID when unmapped)."""
        pg = dr.gather(mi.UInt32, self.dir, vb >> self.page_shift, active)
        ok = mi.Bool(active) & (pg != INVALID)
        ph = dr.gather(mi.UInt32, self.pages, (pg << self.page_shift) | (vb & (self.page_span - 1)), ok)
        return dr.select(ok, ph, INVALID)

    def slot(self, vb, within, active=True):
        """Slot of texel ``within`` of virtual block ``vb`` when mapped and
        already seen in an earlier frame, else INVALID."""
        ph = self.phys(vb, active)
        ok = mi.Bool(active) & (ph != INVALID)
        s = dr.select(ok, ph * self.B2 + within, INVALID)
        ok &= dr.gather(mi.UInt32, self.slot_seen, s, ok) > 0
        return dr.select(ok, s, INVALID)

    def entry_texels(self, slots):
        """(island, level, tx, ty) of entry slots."""
        L = self.layout
        B, sh = L.block_size, L.block_shift
        blk = slots >> (2 * sh)
        w = slots & (self.B2 - 1)
        key = dr.gather(mi.UInt32, self.blk_key, blk)
        xy = dr.gather(mi.UInt32, self.blk_xy, blk)
        isl, lvl = key // L.levels, key % L.levels
        tx = ((xy & 0xFFFF) << sh) | (w & (B - 1))
        ty = ((xy >> 16) << sh) | (w >> sh)
        return isl, lvl, tx, ty

    # ------------------------------------------------------------------ eviction
    def evict(self, tick: int, age: int) -> int:
        """Free the blocks not requested for more than ``age`` frames."""
        if self.n_blocks == 0:
            return 0
        t = dr.opaque(mi.UInt32, tick)
        ev = dr.compress((self.blk_vb != INVALID) & (t - self.blk_last > age))
        n = dr.width(ev)
        if n:
            self._unmap(ev)
        return n

    def _unmap(self, phys):
        n = dr.width(phys)
        phys = widen(phys)
        vb = dr.gather(mi.UInt32, self.blk_vb, phys)
        pg = dr.gather(mi.UInt32, self.dir, vb >> self.page_shift)
        dr.scatter(self.pages, INVALID, (pg << self.page_shift) | (vb & (self.page_span - 1)))
        # Local mode: the default (Expand on the CPU) bakes the target's size into the kernel
        dr.scatter_reduce(dr.ReduceOp.Add, self.pg_count, mi.UInt32(INVALID), pg,   # -1 (mod 2^32)
                          lanes(dr.width(phys), n), mode=dr.ReduceMode.Local)
        dr.scatter(self.blk_vb, INVALID, phys)
        dr.eval(self.pages, self.pg_count, self.blk_vb)
        self.n_blocks -= n
        # free the pages that became empty
        empty = dr.compress((self.pg_dir != INVALID) & (self.pg_count == 0))
        n_empty = dr.width(empty)
        if n_empty:
            empty = widen(empty)
            dr.scatter(self.dir, INVALID, dr.gather(mi.UInt32, self.pg_dir, empty))
            dr.scatter(self.pg_dir, INVALID, empty)
            dr.eval(self.dir, self.pg_dir)
            self.n_pages -= n_empty

    def _evict_lru(self, need: int, req_vb) -> None:
        """Pool full: free the ``need`` least recently used blocks that are
        not requested this frame (O(blocks) numpy bookkeeping)."""
        last = np.array(self.blk_last)
        used = np.array(self.blk_vb) != INVALID
        cur = np.zeros(len(last), bool)
        ph = np.array(self.phys(req_vb))
        cur[ph[ph != INVALID]] = True
        cand = np.nonzero(used & ~cur)[0]
        if len(cand) == 0:
            return
        order = cand[np.lexsort((cand, last[cand]))][:need]
        self._unmap(mi.UInt32(order.astype(np.uint32).tolist()))   # not numpy memory: see widen
        self.evicted_early += len(order)

    # ------------------------------------------------------------------ allocation
    def allocate(self, req_vb) -> tuple[int, int, bool]:
        """Map the unmapped blocks of ``req_vb`` (sorted unique virtual
        blocks). Returns (blocks newly mapped, blocks that did not fit, grown)."""
        self.evicted_early = 0
        miss = dr.compress(self.phys(req_vb) == INVALID)
        n_new = dr.width(miss)
        if n_new == 0:
            return 0, 0, False
        miss = widen(miss)      # only its first n_alloc (<= n_new) lanes are used
        new_vb = dr.gather(mi.UInt32, req_vb, miss)
        free = dr.compress(self.blk_vb == INVALID)
        grown = False
        if dr.width(free) < n_new:
            if self.grow:
                self._grow_pool(n_new - dr.width(free))
                grown = True
            else:
                self._evict_lru(n_new - dr.width(free), req_vb)
            free = dr.compress(self.blk_vb == INVALID)
        n_alloc = min(n_new, dr.width(free))
        if n_alloc:
            sel = dr.arange(mi.UInt32, n_alloc)
            # one free block is a width-1 list, loaded as a scalar (widen): widened, as new_vb
            self._map(dr.gather(mi.UInt32, new_vb, sel), dr.gather(mi.UInt32, widen(free), sel))
        self.n_blocks += n_alloc
        return n_alloc, n_new - n_alloc, grown

    def _map(self, vb, phys):
        """Map virtual blocks to physical ones; record island/level/block xy;
        reset the blocks' slots to unseen."""
        n = dr.width(phys)
        dr.eval(vb, phys)
        vb, phys = widen(vb), widen(phys)
        k, bx, by = self.layout.block_of(vb)
        # pages of the block table for directory entries seen for the first time
        d = vb >> self.page_shift
        dr.eval(k, bx, by, d)           # whether or not a page is added below: the same kernels after it
        need = dr.zeros(mi.Bool, self.n_dir)
        dr.scatter(need, True, d, dr.gather(mi.UInt32, self.dir, d) == INVALID)
        new_d = dr.compress(need)
        nd = dr.width(new_d)
        if nd:
            new_d = widen(new_d)
            free = dr.compress(self.pg_dir == INVALID)
            if dr.width(free) < nd:
                self._grow_pages(nd - dr.width(free))
                free = dr.compress(self.pg_dir == INVALID)
            # a repeated directory entry (widened list) gets the same page
            new_pg = dr.gather(mi.UInt32, widen(free), dr.minimum(dr.arange(mi.UInt32, dr.width(new_d)),
                                                           dr.opaque(mi.UInt32, nd - 1)))
            dr.scatter(self.dir, new_pg, new_d)
            dr.scatter(self.pg_dir, new_d, new_pg)
            dr.eval(self.dir, self.pg_dir)
            self.n_pages += nd
        pg = dr.gather(mi.UInt32, self.dir, d)
        dr.scatter(self.pages, phys, (pg << self.page_shift) | (vb & (self.page_span - 1)))
        dr.scatter_reduce(dr.ReduceOp.Add, self.pg_count, mi.UInt32(1), pg, lanes(dr.width(phys), n),
                          mode=dr.ReduceMode.Local)
        dr.scatter(self.blk_vb, vb, phys)
        dr.scatter(self.blk_key, k, phys)
        dr.scatter(self.blk_xy, bx | (by << 16), phys)
        B2 = self.B2
        j = dr.arange(mi.UInt32, dr.width(phys) * B2)     # repeated blocks reset the same slots
        dr.scatter(self.slot_seen, mi.UInt32(0), dr.gather(mi.UInt32, phys, j // B2) * B2 + j % B2)
        dr.eval(self.pages, self.pg_count, self.blk_vb, self.blk_key, self.blk_xy, self.slot_seen)

    def touch(self, req_vb, tick: int):
        """Stamp the requested blocks with ``tick``; return them as sorted
        physical blocks, and leave each one's rank among them in ``blk_rank``."""
        t = dr.opaque(mi.UInt32, tick)
        phys = self.phys(req_vb)
        dr.scatter(self.blk_last, t, phys, phys != INVALID)
        req_phys = dr.compress((self.blk_last == t) & (self.blk_vb != INVALID))
        dr.scatter(self.blk_rank, dr.arange(mi.UInt32, dr.width(req_phys)), req_phys)
        return req_phys
