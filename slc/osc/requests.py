"""Per-frame request processing of the on-surface cache: the slot dedupe
over all viewers and the LOD seeds of new entries (Dr.Jit, no per-pixel
Python)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID
from slc.osc.blocks import PAGE_SHIFT, BlockPool, widen
from slc.osc.layout import CacheLayout


def requested_blocks(reqs, n_vblocks: int) -> mi.UInt32:
    """The virtual blocks any viewer's pixels request, unique and ascending.

    Two-level flags, so that the per-frame cost grows with the requested
    pages of 64 blocks and not with the scene's whole virtual space (one
    flag per virtual block cost two 32-40 ms compress steps a frame on
    osc-gi's 2x2 blocks, 10.9M flags): 1. flag the pages (``vb >> 6``),
    compress them; 2. number the requested pages, flag the blocks inside
    them, compress, map back. The result equals compressing one flag per
    virtual block (same blocks, same order)."""
    span = 1 << PAGE_SHIFT
    reqs = [r for r in reqs if dr.width(r[1]) > 0]
    n_pages = max(-(-int(n_vblocks) // span), 1)
    # ------------------------------------------------------------------ 1. pages
    page_flag = dr.zeros(mi.Bool, n_pages)
    for valid, vb, _, _ in reqs:
        dr.scatter(page_flag, True, vb >> PAGE_SHIFT, valid)
    pages = dr.compress(page_flag)
    n_req = dr.width(pages)
    if n_req == 0:
        return pages
    # ------------------------------------------------------------------ 2. blocks of the requested pages
    # (one requested page: widened, with its copy numbered 0 too, so that the
    # kernels are those of longer lists; see blocks.widen)
    pages = widen(pages)
    page_slot = dr.zeros(mi.UInt32, n_pages)
    dr.scatter(page_slot, dr.minimum(dr.arange(mi.UInt32, dr.width(pages)), dr.opaque(mi.UInt32, n_req - 1)),
               pages)
    flag = dr.zeros(mi.Bool, n_req * span)
    for valid, vb, _, _ in reqs:
        slot = dr.gather(mi.UInt32, page_slot, vb >> PAGE_SHIFT, valid)
        dr.scatter(flag, True, (slot << PAGE_SHIFT) | (vb & (span - 1)), valid)
    idx = dr.compress(flag)
    return (dr.gather(mi.UInt32, pages, idx >> PAGE_SHIFT) << PAGE_SHIFT) | (idx & (span - 1))


def dedupe(pool: BlockPool, reqs, req_phys, viewers=None):
    """Unique active slots of this frame over all viewers.

    ``reqs``: a list of requests (valid, virtual block, texel in block, level),
    one per viewer or one for all viewers' pixels laid out together;
    ``viewers``: each request's viewer index, an int or a per-pixel ``UInt32``
    (default: the request's position in the list); ``req_phys``: the requested
    physical blocks, ascending, with their rank in ``pool.blk_rank``. Works on
    the compact range of requested blocks x B^2 (not the whole pool), so the
    result stays sorted by slot.

    Which entries more than one viewer asked for, without atomics (at full
    overlap every viewer's pixels hit the same entries, and atomic min/max
    reductions from both threads on one address were most of the cost): every
    pixel writes its viewer into its compact slot (a plain scatter: some writer
    wins), then every pixel whose viewer is not the winner flags the slot. A slot
    is flagged exactly when two viewers or more wrote to it, whichever won.

    Returns (active slots, per-request pixel slots, per-request pixel index
    into ``active``, mask over ``active`` of the entries seen by more than one
    viewer; nothing read back)."""
    B2 = pool.B2
    ncomp = max(dr.width(req_phys) * B2, 1)
    owner = dr.full(mi.UInt32, INVALID, ncomp)
    pixel_slot, pix = [], []
    for v, (valid, vb, within, _) in enumerate(reqs):
        ph = pool.phys(vb, valid)
        ok = valid & (ph != INVALID)
        cid = dr.gather(mi.UInt32, pool.blk_rank, ph, ok) * B2 + within
        vid = v if viewers is None else viewers[v]
        viewer = dr.opaque(mi.UInt32, vid) if isinstance(vid, int) else mi.UInt32(vid)
        dr.scatter(owner, viewer, cid, ok)
        pixel_slot.append(dr.select(ok, ph * B2 + within, INVALID))
        pix.append((ok, cid, viewer))
    dr.schedule(pixel_slot, [p[1] for p in pix])   # in the owner scatter's kernel
    act_c = dr.compress(owner != INVALID)
    n_active = dr.width(act_c)
    if n_active == 0:
        return (mi.UInt32(), pixel_slot, [dr.full(mi.UInt32, INVALID, dr.width(s)) for s in pixel_slot],
                mi.Bool())
    active = dr.gather(mi.UInt32, req_phys, act_c // B2) * B2 + (act_c & (B2 - 1))
    # compact slot -> index into the active list
    rank = dr.empty(mi.UInt32, ncomp)
    dr.scatter(rank, dr.arange(mi.UInt32, n_active), act_c)
    dr.eval(active, rank)
    # one pass over the pixels: their index into the active list, and the shared flags
    shared = dr.zeros(mi.Bool, ncomp)
    pixel_index = []
    for ok, cid, viewer in pix:
        dr.scatter(shared, True, cid, ok & (dr.gather(mi.UInt32, owner, cid, ok) != viewer))
        pixel_index.append(dr.select(ok, dr.gather(mi.UInt32, rank, cid, ok), INVALID))
    dr.eval(shared, pixel_index)
    multi = dr.gather(mi.Bool, shared, act_c)     # left unevaluated (read by the cache's stats)
    return active, pixel_slot, pixel_index, multi


def lod_seeds(layout: CacheLayout, pool: BlockPool, isl, lvl, tx, ty) -> mi.UInt32:
    """Slot of the finest coarser entry (levels lvl+1 .. top) covering texel
    (tx, ty) that is allocated and already seen, else INVALID. Read before
    this frame's entries are marked seen, so a seed holds payload from
    earlier frames."""
    seed = dr.full(mi.UInt32, INVALID, dr.width(isl))
    maxl = dr.gather(mi.UInt32, layout.d_isl_maxl, isl)
    for d in range(1, layout.max_level + 1):
        lc = lvl + d
        m = (seed == INVALID) & (lc <= maxl)
        cx, cy = tx >> d, ty >> d
        vb = layout.vblock(isl * layout.levels + lc, cx, cy, m)
        slot = pool.slot(vb, layout.within(cx, cy), m)
        seed = dr.select(m & (slot != INVALID), slot, seed)
    return seed


def bilinear_taps(layout: CacheLayout, pool: BlockPool, gb, own_slots=None):
    """The 4 entries around each pixel's cache coordinate at the pixel's
    level (texel centres at +0.5), with bilinear weights: ``(slots[4],
    weights[4])``. A tap whose block is not mapped, or whose entry was never
    updated, gets weight 0; the weights of the others are renormalised (all
    zero when none is usable). Taps are clamped to the island's texel
    rectangle, so they never read another island.

    ``own_slots`` (the viewer's ``fr.pixel_slot[v]``): only entries this
    viewer requested in this frame are used. Without it a tap could be an
    entry that exists or is fresh only because another viewer asked for it,
    and a second viewer would change the first one's image (and a tap could be
    an entry last updated many frames ago)."""
    valid, isl, uv, lvl, k = layout.pixel_coords(gb)
    wl, hl = layout.key_extent(k, valid)
    scale = dr.rcp(mi.Float(mi.UInt32(1) << lvl))
    fx, fy = uv.x * scale - 0.5, uv.y * scale - 0.5
    x0, y0 = dr.floor(fx), dr.floor(fy)
    ax, ay = fx - x0, fy - y0
    own = None
    if own_slots is not None:
        own_slots = mi.UInt32(own_slots)
        own = dr.zeros(mi.Bool, max(pool.capacity, 1))
        dr.scatter(own, True, own_slots, own_slots != INVALID)
    slots, weights = [], []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        tx = mi.UInt32(dr.clip(mi.Int32(x0) + dx, 0, wl - 1))
        ty = mi.UInt32(dr.clip(mi.Int32(y0) + dy, 0, hl - 1))
        slot = pool.slot(layout.vblock(k, tx, ty, valid), layout.within(tx, ty), valid)
        if own is not None:
            slot = dr.select((slot != INVALID) & dr.gather(mi.Bool, own, slot, slot != INVALID), slot, INVALID)
        w = (ax if dx else 1.0 - ax) * (ay if dy else 1.0 - ay)
        slots.append(slot)
        weights.append(dr.select(slot != INVALID, w, 0.0))
    total = weights[0] + weights[1] + weights[2] + weights[3]
    inv = dr.select(total > 0.0, dr.rcp(dr.maximum(total, 1e-20)), 0.0)
    return slots, [w * inv for w in weights]
