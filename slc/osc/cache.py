"""The on-surface cache (OSC): virtual texture of blocks over per-island
texture spaces, shared by all viewers.

Per frame (:meth:`OnSurfaceCache.begin_frame`), all in Dr.Jit:

1. requests: each valid pixel of each viewer -> (island, mip level, texel)
   -> virtual block + texel within the block; requested virtual blocks are
   flagged in a flag array (one ``dr.scatter``).
2. allocate: evict blocks unused for ``evict_after`` frames, compress the
   flag array to the sorted unique requested blocks, map the unmapped ones
   to free physical blocks (lowest free first), then every pixel gets its
   entry slot (``phys_block * B^2 + texel_in_block``); slots are deduped with
   a min/max-viewer scatter (``dr.scatter_reduce``) + ``dr.compress``, which
   also measures the viewer overlap.
3. queue: update counters -> rays per entry (8 while new or after motion, 1
   when settled), LOD seeds for new entries, the texel's own surface point
   (a triangle lookup done once per entry and kept, then
   ``PreliminaryIntersection3f.compute_surface_interaction``).

See ``docs/osc.md`` for the design decisions and numbers.
"""
from __future__ import annotations

import math
import time
import warnings
from contextlib import nullcontext
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .islands import DEFAULT_MAX_ANGLE, DEFAULT_MAX_TRIANGLES, MeshIslands, build_mesh_islands

INVALID = 0xFFFFFFFF
DEFAULT_TARGET_TEXELS = 2 ** 24      # level-0 texels over the whole scene when texel_size is None
DEFAULT_CAPACITY_ENTRIES = 2 ** 20   # default initial pool: 1M entries (16384 blocks of 8x8), at most the virtual size
MAX_LEVELS = 20
_UPD_MASK = 0xFFFF


@dataclass
class FrameRequests:
    """What :meth:`OnSurfaceCache.begin_frame` returns.

    Per viewer: ``pixel_slot`` (entry slot per pixel, INVALID where the
    G-buffer is invalid or the pool overflowed), ``pixel_index`` (index of
    the pixel's entry in ``active``/``si``/``rays``..., INVALID likewise:
    saves a capacity-sized inverse map), ``pixel_level`` (mip level).
    Per active slot (unique, sorted ascending): ``si`` (the texel's own
    surface point), ``rays`` (update samples this frame), ``is_new`` (first
    update since allocation: reset the payload), ``seed_slot`` (an existing,
    already updated coarser entry covering a new entry, else INVALID),
    ``level``, ``texel_world`` (texel edge length in world units at the
    entry's level) and ``island``.
    """
    frame: int
    pixel_slot: list
    pixel_index: list
    pixel_level: list
    active: mi.UInt32
    si: mi.SurfaceInteraction3f
    rays: mi.UInt32
    is_new: mi.Bool
    seed_slot: mi.UInt32
    level: mi.UInt32
    texel_world: mi.Float
    island: mi.UInt32
    capacity: int
    n_active: int = 0
    n_new: int = 0
    grown: bool = False


def _timer_stage(timer, name):
    if timer is None:
        return nullcontext(_NullStage())
    return timer.stage(name)


class _NullStage:
    def outputs(self, *values):
        dr.eval(*values)


def _u32(a) -> mi.UInt32:
    return mi.UInt32(np.ascontiguousarray(a, dtype=np.uint32))


def _f32(a) -> mi.Float:
    return mi.Float(np.ascontiguousarray(a, dtype=np.float32))


def _widen(a):
    """``a`` evaluated, its single element repeated when it has one.

    Dr.Jit loads an evaluated width-1 operand as a scalar, so a kernel fed
    by a per-frame list (new blocks, evicted blocks, new pages, new entries)
    that holds one element is not the kernel fed by a longer list: it is
    compiled when it first happens, after warm-up too. Callers use widened
    lists only in idempotent operations (gathers, plain scatters of equal
    values) or mask the copy with :func:`_lanes`. The copy is made from a
    Python list (a memcpy, no kernel); not from a numpy array, whose memory
    Dr.Jit may keep with an alignment of its own that changes the kernel."""
    dr.eval(a)
    if dr.width(a) == 1:
        a = type(a)(np.array(a).tolist() * 2)
    return a


def _lanes(width: int, n: int) -> mi.Bool:
    """The first ``n`` of ``width`` lanes (``n`` opaque: one kernel for every count)."""
    return dr.arange(mi.UInt32, width) < dr.opaque(mi.UInt32, n)


class OnSurfaceCache:
    """Shared on-surface cache of a scene (see module and ``docs/osc.md``).

    Parameters
    ----------
    scene: :class:`slc.scenes.Scene` (its triangle meshes get islands; other
        shapes are not cached and their pixels get INVALID slots).
    block_size: texels per block edge (8 as in OSC, 2 as in the slides);
        power of two.
    bias: mip bias; level = round(log2(footprint * bias / texel_size)).
    evict_after: a block unused for this many frames is freed.
    texel_size: world size of a level-0 texel; default
        ``sqrt(total cached area / 2**24)`` (about 16M level-0 texels).
    max_blocks: physical blocks in the pool; default
        ``min(virtual blocks, 2**20 / block_size**2)`` (1M entries).
    max_angle, max_triangles: island bounds (degrees, triangles).
    grow: when the pool is full, double it (default; ``capacity`` changes,
        payload arrays must follow it, ``FrameRequests.grown`` tells). With
        ``grow=False`` the least recently used blocks not requested this
        frame are evicted early, and what still does not fit is reported
        (``stats()['overflow_blocks']``, a warning) and its pixels get
        INVALID slots.
    """

    def __init__(self, scene, block_size: int = 8, bias: float = 1.0, evict_after: int = 60,
                 texel_size: float | None = None, max_blocks: int | None = None,
                 max_angle: float = DEFAULT_MAX_ANGLE, max_triangles: int = DEFAULT_MAX_TRIANGLES,
                 new_rays: int = 8, new_updates: int = 8, settled_rays: int = 1,
                 motion_rays: int = 8, motion_updates: int = 8, grow: bool = True,
                 entry_bytes: int = 36):
        B = int(block_size)
        if B < 1 or B & (B - 1):
            raise ValueError(f"block_size must be a power of two, got {block_size}")
        self.scene = scene
        self.mi_scene = scene.mi_scene if hasattr(scene, "mi_scene") else scene
        self.block_size = B
        self.block_shift = B.bit_length() - 1
        self.block_texels = B * B
        # virtual blocks per page of the two-level block table; 64 measured
        # best on Sponza at 320x180 (16 or 256: 1.2-2.4x larger table for
        # 2x2 blocks, about the same or 1.7x larger for 8x8)
        self.page_shift = 6
        self.page_span = 1 << self.page_shift
        self.bias = float(bias)
        self.evict_after = int(evict_after)
        self.max_angle = float(max_angle)
        self.max_triangles = int(max_triangles)
        self.new_rays, self.new_updates = int(new_rays), int(new_updates)
        self.settled_rays = int(settled_rays)
        self.motion_rays, self.motion_updates = int(motion_rays), int(motion_updates)
        self.grow = bool(grow)
        self.entry_bytes = int(entry_bytes)
        self.profile = None
        self._t_mark = 0.0
        self._build_islands(texel_size)
        self._build_tables()
        if max_blocks is None:
            max_blocks = max(1, min(self.n_vblocks, DEFAULT_CAPACITY_ENTRIES // self.block_texels))
        self.max_blocks = int(max_blocks)
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _meshes(self):
        out = []
        for k, sh in enumerate(self.mi_scene.shapes()):
            if not sh.is_mesh():
                continue
            V = np.array(sh.vertex_positions_buffer(), np.float32).reshape(-1, 3)
            F = np.array(sh.faces_buffer(), np.uint32).reshape(-1, 3)
            if len(F) == 0:
                continue
            out.append((k, V, F))
        return out

    def _build_islands(self, texel_size):
        meshes = self._meshes()
        self.n_shapes = len(self.mi_scene.shapes())
        area = 0.0
        for _, V, F in meshes:
            V64 = V.astype(np.float64)
            c = np.cross(V64[F[:, 1]] - V64[F[:, 0]], V64[F[:, 2]] - V64[F[:, 0]])
            area += 0.5 * float(np.linalg.norm(c, axis=1).sum())
        self.total_area = area
        if texel_size is None:
            texel_size = math.sqrt(max(area, 1e-12) / DEFAULT_TARGET_TEXELS)
        self.texel_size = float(texel_size)
        self.islands: list[MeshIslands] = []
        self.mesh_data = {}
        for k, V, F in meshes:
            isl = build_mesh_islands(V, F, self.texel_size, shape_index=k,
                                     max_angle=self.max_angle, max_triangles=self.max_triangles)
            self.islands.append(isl)
            self.mesh_data[k] = (V, F)

    def _build_tables(self):
        B = self.block_size
        tri_base = np.full(self.n_shapes, 0, np.int64)
        has_cache = np.zeros(self.n_shapes, bool)
        tri_island, tri_uv, isl_shape, isl_dims = [], [], [], []
        nt = ni = 0
        self.island_base = {}
        for m in self.islands:
            k = m.shape_index
            tri_base[k] = nt
            has_cache[k] = True
            self.island_base[k] = ni
            tri_island.append(m.face_island + ni)
            tri_uv.append(m.corner_uv.reshape(-1, 6))
            isl_shape.append(np.full(m.n_islands, k))
            isl_dims.append(m.dims)
            nt += len(m.face_island)
            ni += m.n_islands
        self.n_triangles, self.n_islands = nt, ni
        tri_island = np.concatenate(tri_island) if tri_island else np.zeros(0, np.int64)
        tri_uv = np.concatenate(tri_uv) if tri_uv else np.zeros((0, 6))
        isl_shape = np.concatenate(isl_shape) if isl_shape else np.zeros(0, np.int64)
        dims = np.concatenate(isl_dims) if isl_dims else np.zeros((0, 2), np.int64)
        self._np_tri_island, self._np_isl_shape, self._np_dims = tri_island, isl_shape, dims
        self._np_tri_base = tri_base
        # per-island levels: the island is one texel at its top level
        ext = np.maximum(dims.max(1), 1) if ni else np.zeros(0, np.int64)
        maxl = np.ceil(np.log2(ext)).astype(np.int64) if ni else np.zeros(0, np.int64)
        maxl = np.minimum(maxl, MAX_LEVELS - 1)
        self.max_level = int(maxl.max()) if ni else 0
        M1 = self.max_level + 1
        self.levels = M1
        Ls = np.arange(M1)
        w = -(-dims[:, :1] // (1 << Ls)[None, :])          # ceil(w0 / 2^L), (I, M1)
        h = -(-dims[:, 1:2] // (1 << Ls)[None, :])
        nbx = -(-w // B)
        nby = -(-h // B)
        nblk = np.where(Ls[None, :] <= maxl[:, None], nbx * nby, 0)
        flat = nblk.ravel()
        base = np.concatenate([[0], np.cumsum(flat)[:-1]]) if len(flat) else np.zeros(0, np.int64)
        self.n_vblocks = int(flat.sum())
        if self.n_vblocks >= 2 ** 31:
            raise ValueError(f"OSC virtual space too large ({self.n_vblocks} blocks): raise texel_size "
                             f"(now {self.texel_size:g})")
        self._np_lvl_base = base
        # island-sorted triangles for the texel -> triangle lookup
        order = np.argsort(tri_island, kind="stable")
        counts = np.bincount(tri_island, minlength=ni) if ni else np.zeros(0, np.int64)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if ni else np.zeros(0, np.int64)
        # Dr.Jit tables
        self.d_tri_base = _u32(tri_base)
        self.d_has_cache = mi.Bool(has_cache.tolist()) if self.n_shapes else mi.Bool()
        self.d_tri_island = _u32(tri_island)
        self.d_tri_uv = _f32(tri_uv.ravel())            # 6 floats per triangle
        self.d_isl_shape = _u32(isl_shape)
        self.d_isl_maxl = _u32(maxl)
        self.d_isl_start = _u32(starts)
        self.d_isl_count = _u32(counts)
        self.d_sorted_tri = _u32(order)
        self.d_sorted_uv = _f32(tri_uv[order].ravel())
        self.d_lvl_base = _u32(base)
        self.d_lvl_nbx = _u32(nbx.ravel())
        self.d_lvl_w = _u32(w.ravel())
        self.d_lvl_h = _u32(h.ravel())
        self.d_isl_dims = _u32(dims.ravel())

    # ------------------------------------------------------------------ state
    @property
    def capacity(self) -> int:
        return self.max_blocks * self.block_texels

    def reset(self) -> None:
        """Forget every entry (all blocks free, counters and stats cleared)."""
        # two-level block table: directory (one entry per self.page_span virtual
        # blocks) -> pages of self.page_span physical block ids, allocated on demand
        self.n_dir = max(-(-self.n_vblocks // self.page_span), 1)
        self.dir = dr.full(mi.UInt32, INVALID, self.n_dir)
        self._alloc_pages(max(64, min(self.n_dir, 4 * self.max_blocks // self.page_span + 64)))
        self.n_pages = 0
        self._alloc_pool(self.max_blocks)
        self.tick = 0
        self.n_blocks = 0
        self._stats = dict(blocks=0, entries_allocated=0, entries_requested=0, fill_ratio=0.0,
                           measured_overlap=0.0, evicted=0, new_entries=0, new_blocks=0,
                           overflow_blocks=0, pixels=0, capacity=self.capacity)
        self._warned = False

    def _alloc_pool(self, nb):
        n = nb * self.block_texels
        self.blk_vb = dr.full(mi.UInt32, INVALID, nb)      # physical block -> virtual block
        self.blk_last = dr.zeros(mi.UInt32, nb)             # tick of last use
        self.blk_key = dr.zeros(mi.UInt32, nb)              # island * levels + level
        self.blk_xy = dr.zeros(mi.UInt32, nb)               # bx | by << 16
        self.blk_rank = dr.zeros(mi.UInt32, nb)             # scratch: rank among this frame's blocks
        self.slot_state = dr.zeros(mi.UInt32, n)            # updates (16 bit) | motion left << 16
        self.slot_tri = dr.zeros(mi.UInt32, n)              # global triangle of the texel's point
        self.slot_b = dr.zeros(mi.Point2f, n)               # its barycentrics (Mitsuba prim_uv)
        dr.eval(self.blk_vb, self.blk_last, self.blk_key, self.blk_xy, self.slot_state,
                self.slot_tri, self.slot_b)

    def _alloc_pages(self, npg):
        self.max_pages = npg
        self.pages = dr.full(mi.UInt32, INVALID, npg * self.page_span)  # page entries: physical block or INVALID
        self.pg_dir = dr.full(mi.UInt32, INVALID, npg)             # page -> directory entry (INVALID: free)
        self.pg_count = dr.zeros(mi.UInt32, npg)                   # mapped blocks in the page
        dr.eval(self.pages, self.pg_dir, self.pg_count)

    def _grow_pages(self, need):
        old = self.max_pages
        npg = max(2 * old, old + need)
        pages, pg_dir, pg_count = self.pages, self.pg_dir, self.pg_count
        self.max_pages = npg
        self.pages = dr.full(mi.UInt32, INVALID, npg * self.page_span)
        dr.scatter(self.pages, pages, dr.arange(mi.UInt32, old * self.page_span))
        self.pg_dir = dr.full(mi.UInt32, INVALID, npg)
        dr.scatter(self.pg_dir, pg_dir, dr.arange(mi.UInt32, old))
        self.pg_count = dr.zeros(mi.UInt32, npg)
        dr.scatter(self.pg_count, pg_count, dr.arange(mi.UInt32, old))
        dr.eval(self.pages, self.pg_dir, self.pg_count)

    def _phys(self, vb, active=True):
        """Physical block of virtual blocks (INVALID when unmapped)."""
        pg = dr.gather(mi.UInt32, self.dir, vb >> self.page_shift, active)
        ok = mi.Bool(active) & (pg != INVALID)
        ph = dr.gather(mi.UInt32, self.pages, (pg << self.page_shift) | (vb & (self.page_span - 1)), ok)
        return dr.select(ok, ph, INVALID)

    def _grow_pool(self, need_blocks):
        old = self.max_blocks
        nb = max(2 * old, old + need_blocks)
        n_old, n = old * self.block_texels, nb * self.block_texels

        def ext(a, fill, size, tp):
            out = dr.full(tp, fill, size)
            dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)))
            return out
        self.blk_vb = ext(self.blk_vb, INVALID, nb, mi.UInt32)
        self.blk_last = ext(self.blk_last, 0, nb, mi.UInt32)
        self.blk_key = ext(self.blk_key, 0, nb, mi.UInt32)
        self.blk_xy = ext(self.blk_xy, 0, nb, mi.UInt32)
        self.blk_rank = dr.zeros(mi.UInt32, nb)
        self.slot_state = ext(self.slot_state, 0, n, mi.UInt32)
        self.slot_tri = ext(self.slot_tri, 0, n, mi.UInt32)
        sb = dr.zeros(mi.Point2f, n)
        dr.scatter(sb, self.slot_b, dr.arange(mi.UInt32, n_old))
        self.slot_b = sb
        self.max_blocks = nb
        dr.eval(self.blk_vb, self.blk_last, self.blk_key, self.blk_xy, self.slot_state,
                self.slot_tri, self.slot_b)

    def set_entry_bytes(self, n: int) -> None:
        """Packed bytes per entry of the payload (e.g. 36 for SLC's 286 bits)."""
        self.entry_bytes = int(n)

    def table_bytes(self) -> int:
        """The block table: directory (4 B per page of 64 virtual blocks) +
        the allocated pages (64 x 4 B + 8 B each) + 16 B per allocated block
        (virtual id, last use, island/level, block x/y)."""
        return 4 * self.n_dir + (4 * self.page_span + 8) * self.n_pages + 16 * self.n_blocks

    def memory_bytes(self) -> int:
        """Allocated blocks x block texels x entry bytes + the block table."""
        return self.n_blocks * self.block_texels * self.entry_bytes + self.table_bytes()

    def stats(self) -> dict:
        s = dict(self._stats)
        s["memory_bytes"] = self.memory_bytes()
        return s

    # ------------------------------------------------------------------ per pixel
    def _pixel_coords(self, gb):
        """Per pixel: (valid, island, island-local level-0 coordinates, level,
        the island-level key ``isl * levels + lvl``)."""
        sidx = mi.UInt32(gb.shape_index)
        valid = mi.Bool(gb.valid) & (sidx < self.n_shapes)
        valid &= dr.gather(mi.Bool, self.d_has_cache, sidx, valid)
        tri = dr.gather(mi.UInt32, self.d_tri_base, sidx, valid) + mi.UInt32(gb.prim_index)
        isl = dr.gather(mi.UInt32, self.d_tri_island, tri, valid)
        uv = self._bary_uv(tri, gb.prim_uv, valid)
        lvl = self.level_of(gb.footprint, isl, valid)
        return valid, isl, uv, lvl, isl * self.levels + lvl

    def _pixel_requests(self, gb):
        """Virtual block, texel-in-block and level of every pixel of a G-buffer."""
        B, sh = self.block_size, self.block_shift
        valid, isl, uv, lvl, k = self._pixel_coords(gb)
        wl = dr.gather(mi.UInt32, self.d_lvl_w, k, valid)
        hl = dr.gather(mi.UInt32, self.d_lvl_h, k, valid)
        scale = dr.rcp(mi.Float(mi.UInt32(1) << lvl))
        tx = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.x * scale)), 0, mi.Int32(wl) - 1))
        ty = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.y * scale)), 0, mi.Int32(hl) - 1))
        vb = dr.gather(mi.UInt32, self.d_lvl_base, k, valid) + \
            (ty >> sh) * dr.gather(mi.UInt32, self.d_lvl_nbx, k, valid) + (tx >> sh)
        within = ((ty & (B - 1)) << sh) | (tx & (B - 1))
        return valid, vb, within, lvl

    def bilinear_taps(self, gb):
        """The 4 entries around each pixel's cache coordinate at the pixel's level
        (texel centres at +0.5), with bilinear weights: ``(slots[4], weights[4])``.
        A tap whose block is not mapped, or whose entry was never updated, gets
        weight 0; the weights of the others are renormalised (all zero when none
        is usable). Taps are clamped to the island's texel rectangle, so they
        never read another island."""
        B, sh = self.block_size, self.block_shift
        valid, isl, uv, lvl, k = self._pixel_coords(gb)
        wl = mi.Int32(dr.gather(mi.UInt32, self.d_lvl_w, k, valid))
        hl = mi.Int32(dr.gather(mi.UInt32, self.d_lvl_h, k, valid))
        base = dr.gather(mi.UInt32, self.d_lvl_base, k, valid)
        nbx = dr.gather(mi.UInt32, self.d_lvl_nbx, k, valid)
        scale = dr.rcp(mi.Float(mi.UInt32(1) << lvl))
        fx, fy = uv.x * scale - 0.5, uv.y * scale - 0.5
        x0, y0 = dr.floor(fx), dr.floor(fy)
        ax, ay = fx - x0, fy - y0
        slots, weights = [], []
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            tx = mi.UInt32(dr.clip(mi.Int32(x0) + dx, 0, wl - 1))
            ty = mi.UInt32(dr.clip(mi.Int32(y0) + dy, 0, hl - 1))
            vb = base + (ty >> sh) * nbx + (tx >> sh)
            ph = self._phys(vb, valid)
            ok = valid & (ph != INVALID)
            slot = dr.select(ok, ph * self.block_texels + (((ty & (B - 1)) << sh) | (tx & (B - 1))), INVALID)
            ok &= (dr.gather(mi.UInt32, self.slot_state, slot, ok) & _UPD_MASK) > 0
            w = (ax if dx else 1.0 - ax) * (ay if dy else 1.0 - ay)
            slots.append(dr.select(ok, slot, INVALID))
            weights.append(dr.select(ok, w, 0.0))
        total = weights[0] + weights[1] + weights[2] + weights[3]
        inv = dr.select(total > 0.0, dr.rcp(dr.maximum(total, 1e-20)), 0.0)
        return slots, [w * inv for w in weights]

    def _bary_uv(self, tri, prim_uv, active):
        """Island-local level-0 texel coordinates of a hit: Mitsuba's
        barycentrics p = (1-u-v) p0 + u p1 + v p2."""
        c0 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 0, active)
        c1 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 1, active)
        c2 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 2, active)
        u, v = prim_uv.x, prim_uv.y
        return c0 * (1.0 - u - v) + c1 * u + c2 * v

    def level_of(self, footprint, isl, active=True) -> mi.UInt32:
        """Mip level clamp(round(log2(footprint * bias / texel_size)), 0, island top level)."""
        r = mi.Float(footprint) * (self.bias / self.texel_size)
        lf = dr.round(dr.log2(dr.maximum(r, 1e-30)))
        maxl = dr.gather(mi.UInt32, self.d_isl_maxl, isl, active)
        return dr.minimum(mi.UInt32(dr.clip(lf, 0.0, float(self.max_level))), maxl)

    # ------------------------------------------------------------------ frame
    def begin_frame(self, frame: int, gbuffers, timer=None) -> FrameRequests:
        """Requests from every viewer's G-buffer, dedupe, allocation, update
        queue; timed as stages "requests", "allocate", "queue"."""
        B2 = self.block_texels
        nvb = max(self.n_vblocks, 1)
        # ---- 1. requests
        with _timer_stage(timer, "requests") as st:
            reqs = [self._pixel_requests(gb) for gb in gbuffers]
            flag = dr.zeros(mi.Bool, nvb)
            for valid, vb, _, _ in reqs:
                dr.scatter(flag, True, vb, valid)
            st.outputs(flag, *[x for r in reqs for x in r])
        # ---- 2. allocate + slot dedupe
        grown = False
        with _timer_stage(timer, "allocate") as st:
            self.tick += 1
            # opaque: a literal that changes every frame would recompile kernels
            tick = dr.opaque(mi.UInt32, self.tick)
            self._mark(None)
            self._evicted_early = 0
            evicted = self._evict(self.evict_after)
            self._mark("evict")
            req_vb = dr.compress(flag)
            n_req = dr.width(req_vb)
            if n_req == 0:      # nothing cacheable in view (or no viewer)
                st.outputs(self.blk_vb)
                return self._empty_frame(frame, gbuffers, reqs, evicted)
            phys = self._phys(req_vb)
            miss = dr.compress(phys == INVALID)
            n_new_blocks = dr.width(miss)
            miss = _widen(miss)     # only its first n_alloc (<= n_new_blocks) lanes are used
            overflow = 0
            if n_new_blocks:
                new_vb = dr.gather(mi.UInt32, req_vb, miss)
                free = dr.compress(self.blk_vb == INVALID)
                if dr.width(free) < n_new_blocks:
                    if self.grow:
                        self._grow_pool(n_new_blocks - dr.width(free))
                        grown = True
                    else:
                        self._evict_lru(n_new_blocks - dr.width(free), req_vb)
                    free = dr.compress(self.blk_vb == INVALID)
                n_alloc = min(n_new_blocks, dr.width(free))
                overflow = n_new_blocks - n_alloc
                if overflow and not self._warned:
                    warnings.warn(f"OSC pool full ({self.max_blocks} blocks): {overflow} requested blocks "
                                  f"not allocated this frame (pixels get INVALID); pass max_blocks or grow=True")
                    self._warned = True
                if n_alloc:
                    sel = dr.arange(mi.UInt32, n_alloc)
                    new_vb = dr.gather(mi.UInt32, new_vb, sel)
                    new_phys = dr.gather(mi.UInt32, free, sel)
                    self._map_blocks(new_vb, new_phys)
                self.n_blocks += n_alloc
            self._mark("map")
            phys = self._phys(req_vb)
            dr.scatter(self.blk_last, tick, phys, phys != INVALID)
            # requested physical blocks, ascending, and their rank: the slot
            # dedupe then works on a compact range (requested blocks x B^2),
            # not on the whole pool, and stays sorted by slot
            req_phys = dr.compress((self.blk_last == tick) & (self.blk_vb != INVALID))
            n_rp = dr.width(req_phys)
            dr.scatter(self.blk_rank, dr.arange(mi.UInt32, n_rp), req_phys)
            self._mark("rank")
            ncomp = max(n_rp * B2, 1)
            vmin = dr.full(mi.UInt32, INVALID, ncomp)
            vmax = dr.zeros(mi.UInt32, ncomp)
            pixel_slot, pix_cid = [], []
            for v, (valid, vb, within, _) in enumerate(reqs):
                ph = self._phys(vb, valid)
                ok = valid & (ph != INVALID)
                slot = dr.select(ok, ph * B2 + within, INVALID)
                cid = dr.gather(mi.UInt32, self.blk_rank, ph, ok) * B2 + within
                dr.scatter_reduce(dr.ReduceOp.Min, vmin, mi.UInt32(v), cid, ok, mode=dr.ReduceMode.Local)
                dr.scatter_reduce(dr.ReduceOp.Max, vmax, mi.UInt32(v), cid, ok, mode=dr.ReduceMode.Local)
                pixel_slot.append(slot)
                pix_cid.append((ok, cid))
            act_c = dr.compress(vmin != INVALID)
            n_active = dr.width(act_c)
            self._mark("dedupe")
            if n_active:
                active = dr.gather(mi.UInt32, req_phys, act_c // B2) * B2 + (act_c & (B2 - 1))
                multi = dr.gather(mi.UInt32, vmax, act_c) != dr.gather(mi.UInt32, vmin, act_c)
                n_multi = int(dr.count(multi)[0])
                # pixel -> index into the active list (reuse vmax as the map)
                dr.scatter(vmax, dr.arange(mi.UInt32, n_active), act_c)
                pixel_index = [dr.select(ok, dr.gather(mi.UInt32, vmax, cid, ok), INVALID)
                               for ok, cid in pix_cid]
            else:
                active, n_multi = mi.UInt32(), 0
                pixel_index = [dr.full(mi.UInt32, INVALID, dr.width(s_)) for s_ in pixel_slot]
            dr.eval(active)    # apart: n_active may equal a viewer's pixel count (same-sized values fuse)
            dr.eval(*pixel_slot, *pixel_index)
            self._mark("pixel_index")
            st.outputs(active, *pixel_slot, *pixel_index, self.blk_vb, self.blk_last)
        # ---- 3. update queue
        with _timer_stage(timer, "queue") as st:
            q = self._queue(active)
            st.outputs(*q.values())
        self._stats = dict(blocks=self.n_blocks, entries_allocated=self.n_blocks * B2,
                           entries_requested=n_active,
                           fill_ratio=n_active / max(self.n_blocks * B2, 1),
                           measured_overlap=100.0 * n_multi / max(n_active, 1),
                           evicted=evicted, new_entries=q.pop("n_new"), new_blocks=n_new_blocks - overflow,
                           overflow_blocks=overflow, evicted_early=self._evicted_early,
                           requested_blocks=n_req,
                           pixels=int(sum(dr.count(r[0]) for r in reqs)[0]) if reqs else 0,
                           capacity=self.capacity)
        return FrameRequests(frame=frame, pixel_slot=pixel_slot, pixel_index=pixel_index,
                             pixel_level=[r[3] for r in reqs],
                             active=active, si=q["si"], rays=q["rays"], is_new=q["is_new"],
                             seed_slot=q["seed"], level=q["level"], texel_world=q["texel_world"],
                             island=q["island"], capacity=self.capacity, n_active=n_active,
                             n_new=self._stats["new_entries"], grown=grown)

    def _empty_frame(self, frame, gbuffers, reqs, evicted) -> FrameRequests:
        self._stats = dict(blocks=self.n_blocks, entries_allocated=self.n_blocks * self.block_texels,
                           entries_requested=0, fill_ratio=0.0, measured_overlap=0.0, evicted=evicted,
                           new_entries=0, new_blocks=0, overflow_blocks=0, evicted_early=0,
                           requested_blocks=0, pixels=0, capacity=self.capacity)
        inv = [dr.full(mi.UInt32, INVALID, gb.size) for gb in gbuffers]
        return FrameRequests(frame=frame, pixel_slot=inv, pixel_index=[mi.UInt32(x) for x in inv],
                             pixel_level=[r[3] for r in reqs], active=mi.UInt32(),
                             si=dr.zeros(mi.SurfaceInteraction3f, 0), rays=mi.UInt32(), is_new=mi.Bool(),
                             seed_slot=mi.UInt32(), level=mi.UInt32(), texel_world=mi.Float(),
                             island=mi.UInt32(), capacity=self.capacity, n_active=0, n_new=0)

    def _mark(self, name):
        """Sub-stage profiling (``cache.profile = {}`` turns it on)."""
        if self.profile is None:
            return
        dr.sync_thread()
        t = time.perf_counter()
        if name is not None:
            self.profile[name] = self.profile.get(name, 0.0) + (t - self._t_mark) * 1e3
        self._t_mark = t

    def _evict(self, age: int) -> int:
        if self.n_blocks == 0:
            return 0
        tick = dr.opaque(mi.UInt32, self.tick)
        mask = (self.blk_vb != INVALID) & (tick - self.blk_last > age)
        ev = dr.compress(mask)
        n = dr.width(ev)
        if n:
            self._unmap(ev)
        return n

    def _unmap(self, phys):
        n = dr.width(phys)
        phys = _widen(phys)
        vb = dr.gather(mi.UInt32, self.blk_vb, phys)
        pg = dr.gather(mi.UInt32, self.dir, vb >> self.page_shift)
        dr.scatter(self.pages, INVALID, (pg << self.page_shift) | (vb & (self.page_span - 1)))
        dr.scatter_reduce(dr.ReduceOp.Add, self.pg_count, mi.UInt32(INVALID), pg,   # -1 (mod 2^32)
                          _lanes(dr.width(phys), n), mode=dr.ReduceMode.Local)
        dr.scatter(self.blk_vb, INVALID, phys)
        dr.eval(self.pages, self.pg_count, self.blk_vb)
        self.n_blocks -= n
        # free the pages that became empty
        empty = dr.compress((self.pg_dir != INVALID) & (self.pg_count == 0))
        n_empty = dr.width(empty)
        if n_empty:
            empty = _widen(empty)
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
        ph = np.array(self._phys(req_vb))
        cur[ph[ph != INVALID]] = True
        cand = np.nonzero(used & ~cur)[0]
        if len(cand) == 0:
            return
        order = cand[np.lexsort((cand, last[cand]))][:need]
        self._unmap(mi.UInt32(order.astype(np.uint32).tolist()))   # not numpy memory: see _widen
        self._evicted_early += len(order)

    def _map_blocks(self, vb, phys):
        """Map virtual blocks to physical ones; record island/level/block xy
        (binary search of the virtual block in the per-(island, level) bases)
        and reset the blocks' entry counters."""
        B2 = self.block_texels
        n = dr.width(phys)
        dr.eval(vb, phys)
        vb, phys = _widen(vb), _widen(phys)
        n_tab = dr.width(self.d_lvl_base)
        k = mi.UInt32(dr.binary_search(0, n_tab, lambda i: dr.gather(mi.UInt32, self.d_lvl_base, i) <= vb)) - 1
        local = vb - dr.gather(mi.UInt32, self.d_lvl_base, k)
        # max(.., 1): masked-off SIMD lanes of a gather read 0, and an integer
        # division by 0 in any lane raises SIGFPE on the LLVM backend
        nbx = dr.maximum(dr.gather(mi.UInt32, self.d_lvl_nbx, k), 1)
        by = local // nbx
        bx = local - by * nbx
        # pages of the block table for directory entries seen for the first time
        d = vb >> self.page_shift
        need = dr.zeros(mi.Bool, self.n_dir)
        dr.scatter(need, True, d, dr.gather(mi.UInt32, self.dir, d) == INVALID)
        new_d = dr.compress(need)
        nd = dr.width(new_d)
        if nd:
            new_d = _widen(new_d)
            free = dr.compress(self.pg_dir == INVALID)
            if dr.width(free) < nd:
                self._grow_pages(nd - dr.width(free))
                free = dr.compress(self.pg_dir == INVALID)
            # a repeated directory entry gets the same page
            new_pg = dr.gather(mi.UInt32, free, dr.minimum(dr.arange(mi.UInt32, dr.width(new_d)),
                                                           dr.opaque(mi.UInt32, nd - 1)))
            dr.scatter(self.dir, new_pg, new_d)
            dr.scatter(self.pg_dir, new_d, new_pg)
            dr.eval(self.dir, self.pg_dir)
            self.n_pages += nd
        pg = dr.gather(mi.UInt32, self.dir, d)
        dr.scatter(self.pages, phys, (pg << self.page_shift) | (vb & (self.page_span - 1)))
        dr.scatter_reduce(dr.ReduceOp.Add, self.pg_count, mi.UInt32(1), pg, _lanes(dr.width(phys), n),
                          mode=dr.ReduceMode.Local)
        dr.scatter(self.blk_vb, vb, phys)
        dr.scatter(self.blk_key, k, phys)
        dr.scatter(self.blk_xy, bx | (by << 16), phys)
        j = dr.arange(mi.UInt32, dr.width(phys) * B2)
        dr.scatter(self.slot_state, mi.UInt32(0), dr.gather(mi.UInt32, phys, j // B2) * B2 + j % B2)
        dr.eval(self.pages, self.pg_count, self.blk_vb, self.blk_key, self.blk_xy, self.slot_state)

    def entry_texels(self, slots):
        """(island, level, tx, ty) of entry slots (Dr.Jit arrays)."""
        B, sh = self.block_size, self.block_shift
        blk = slots >> (2 * sh)
        w = slots & (self.block_texels - 1)
        key = dr.gather(mi.UInt32, self.blk_key, blk)
        xy = dr.gather(mi.UInt32, self.blk_xy, blk)
        isl, lvl = key // self.levels, key % self.levels
        tx = ((xy & 0xFFFF) << sh) | (w & (B - 1))
        ty = ((xy >> 16) << sh) | (w >> sh)
        return isl, lvl, tx, ty

    def entry_keys(self, slots) -> mi.UInt32:
        """A 32-bit hash of each slot's (island, level, tx, ty): the same for a
        texel whatever physical block it landed in, so payload random numbers
        keyed by it do not depend on which viewers asked for what."""
        isl, lvl, tx, ty = self.entry_texels(mi.UInt32(slots))
        k0, _ = mi.sample_tea_32(isl * self.levels + lvl, (ty << 16) | tx, 4)
        return k0

    def entry_info(self, slots) -> dict:
        """numpy (island, level, tx, ty) of slots: a viewer-independent key."""
        isl, lvl, tx, ty = self.entry_texels(mi.UInt32(slots))
        return dict(island=np.array(isl), level=np.array(lvl), tx=np.array(tx), ty=np.array(ty))

    def _queue(self, active) -> dict:
        n = dr.width(active)
        st = dr.gather(mi.UInt32, self.slot_state, active)
        upd, mot = st & _UPD_MASK, st >> 16
        is_new = upd == 0
        rays = dr.select(upd < self.new_updates, mi.UInt32(self.new_rays),
                         dr.select(mot > 0, mi.UInt32(self.motion_rays), mi.UInt32(self.settled_rays)))
        isl, lvl, tx, ty = self.entry_texels(active)
        self._mark(None)
        new_idx = dr.compress(is_new)
        n_new = dr.width(new_idx)
        seed = dr.full(mi.UInt32, INVALID, n)
        if n_new:
            new_idx = _widen(new_idx)   # a repeated entry computes and writes the same values
            ns = dr.gather(mi.UInt32, active, new_idx)
            nisl, nlvl = dr.gather(mi.UInt32, isl, new_idx), dr.gather(mi.UInt32, lvl, new_idx)
            ntx, nty = dr.gather(mi.UInt32, tx, new_idx), dr.gather(mi.UInt32, ty, new_idx)
            # LOD seed: the finest existing, already updated coarser entry
            dr.scatter(seed, self._seed(nisl, nlvl, ntx, nty), new_idx)
            # texel -> surface point: triangle lookup once per new entry, kept
            size = mi.Float(mi.UInt32(1) << nlvl)
            c = mi.Point2f((mi.Float(ntx) + 0.5) * size, (mi.Float(nty) + 0.5) * size)
            tri, b = self._lookup(nisl, c)
            dr.scatter(self.slot_tri, tri, ns)
            dr.scatter(self.slot_b, b, ns)
            # apart from the n-sized values below: a kernel must not depend on
            # whether n_new happens to equal n (same-sized values fuse)
            dr.eval(seed, self.slot_tri, self.slot_b)
        dr.eval(seed)
        dr.eval(rays, is_new)
        self._mark("seed_lookup")
        tri = dr.gather(mi.UInt32, self.slot_tri, active)
        b = dr.gather(mi.Point2f, self.slot_b, active)
        si = self._surface_interaction(isl, tri, b)
        # advance the counters (every active entry is updated once this frame)
        upd2 = dr.minimum(upd + 1, _UPD_MASK)
        mot2 = dr.select(mot > 0, mot - 1, 0)
        dr.scatter(self.slot_state, upd2 | (mot2 << 16), active)
        texel_world = self.texel_size * mi.Float(mi.UInt32(1) << lvl)
        return dict(si=si, rays=rays, is_new=is_new, seed=seed, level=lvl, texel_world=texel_world,
                    island=isl, state=self.slot_state, n_new=n_new)

    def _seed(self, isl, lvl, tx, ty):
        """Slot of the finest coarser entry (levels lvl+1 .. top) covering
        texel (tx, ty) that is allocated and already updated, else INVALID.
        Read before this frame's counters advance, so a seed holds payload
        from earlier frames."""
        B, sh = self.block_size, self.block_shift
        seed = dr.full(mi.UInt32, INVALID, dr.width(isl))
        maxl = dr.gather(mi.UInt32, self.d_isl_maxl, isl)
        for d in range(1, self.max_level + 1):
            lc = lvl + d
            m = (seed == INVALID) & (lc <= maxl)
            k = isl * self.levels + lc
            cx, cy = tx >> d, ty >> d
            vb = dr.gather(mi.UInt32, self.d_lvl_base, k, m) + \
                (cy >> sh) * dr.gather(mi.UInt32, self.d_lvl_nbx, k, m) + (cx >> sh)
            ph = self._phys(vb, m)
            m &= ph != INVALID
            slot = ph * self.block_texels + (((cy & (B - 1)) << sh) | (cx & (B - 1)))
            m &= (dr.gather(mi.UInt32, self.slot_state, slot, m) & _UPD_MASK) > 0
            seed = dr.select(m, slot, seed)
        return seed

    def _lookup(self, isl, c):
        """Triangle of island ``isl`` containing the 2D point ``c`` (island
        level-0 texel coordinates), else the nearest one; returns the global
        triangle and Mitsuba barycentrics (u, v) of the closest point. Brute
        force over the island's triangles (<= max_triangles) in a symbolic
        loop; the first triangle in island order wins ties, so the answer
        does not depend on who asked."""
        start = dr.gather(mi.UInt32, self.d_isl_start, isl)
        count = dr.gather(mi.UInt32, self.d_isl_count, isl)
        n = dr.width(isl)
        i = dr.zeros(mi.UInt32, n)
        best_d = dr.full(mi.Float, dr.inf, n)
        best_j = mi.UInt32(start)
        bu, bv = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        uv = self.d_sorted_uv

        def cond(i, best_d, best_j, bu, bv):
            return i < count

        def body(i, best_d, best_j, bu, bv):
            j = start + i
            p0 = dr.gather(mi.Point2f, uv, j * 3 + 0)
            p1 = dr.gather(mi.Point2f, uv, j * 3 + 1)
            p2 = dr.gather(mi.Point2f, uv, j * 3 + 2)
            d2, u, v = _closest_on_triangle(c, p0, p1, p2)
            better = d2 < best_d
            best_d = dr.select(better, d2, best_d)
            best_j = dr.select(better, j, best_j)
            bu = dr.select(better, u, bu)
            bv = dr.select(better, v, bv)
            i = dr.select(best_d <= 0.0, count, i + 1)   # inside: done
            return i, best_d, best_j, bu, bv

        i, best_d, best_j, bu, bv = dr.while_loop((i, best_d, best_j, bu, bv), cond, body)
        tri = dr.gather(mi.UInt32, self.d_sorted_tri, best_j)
        return tri, mi.Point2f(bu, bv)

    def _surface_interaction(self, isl, tri, b) -> mi.SurfaceInteraction3f:
        n = dr.width(tri)
        shape_idx = dr.gather(mi.UInt32, self.d_isl_shape, isl)
        pi = dr.zeros(mi.PreliminaryIntersection3f, n)
        pi.t = dr.full(mi.Float, 1.0, n)
        pi.valid = dr.full(mi.Bool, True, n)
        pi.prim_uv = mi.Point2f(b)
        pi.prim_index = tri - dr.gather(mi.UInt32, self.d_tri_base, shape_idx)
        pi.shape_index = shape_idx
        pi.shape = dr.gather(mi.ShapePtr, self.mi_scene.shapes_dr(), shape_idx)
        ray = mi.Ray3f(mi.Point3f(0.0), mi.Vector3f(0.0, 0.0, 1.0))
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
        si.wi = mi.Vector3f(0.0, 0.0, 1.0)     # "viewer" along the shading normal
        return si

    # ------------------------------------------------------------------ payload feedback
    def mark_motion(self, slots, mask=True) -> None:
        """Detected motion: these entries get ``motion_rays`` for their next
        ``motion_updates`` updates."""
        slots = mi.UInt32(slots)
        m = mi.Bool(mask) & (slots != INVALID) & (slots < self.capacity)
        st = dr.gather(mi.UInt32, self.slot_state, slots, m)
        dr.scatter(self.slot_state, (st & _UPD_MASK) | (mi.UInt32(self.motion_updates) << 16), slots, m)
        dr.eval(self.slot_state)


def _closest_on_triangle(c, p0, p1, p2):
    """Squared 2D distance from c to triangle (p0, p1, p2) and the
    barycentrics (u, v) (weights of p1, p2) of the closest point."""
    e0, e1, q = p1 - p0, p2 - p0, c - p0
    det = e0.x * e1.y - e0.y * e1.x
    ok = dr.abs(det) > 1e-12
    inv = dr.select(ok, dr.rcp(det), 0.0)
    u = (q.x * e1.y - q.y * e1.x) * inv
    v = (e0.x * q.y - e0.y * q.x) * inv
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)

    def seg(a, d):
        s = dr.clip(dr.dot(c - a, d) / dr.maximum(dr.squared_norm(d), 1e-20), 0.0, 1.0)
        return dr.squared_norm(c - (a + s * d)), s

    d01, s01 = seg(p0, e0)            # (u, v) = (s, 0)
    d02, s02 = seg(p0, e1)            # (0, s)
    d12, s12 = seg(p1, p2 - p1)       # (1 - s, s)
    best, bu, bv = d01, s01, mi.Float(0.0)
    m = d02 < best
    best, bu, bv = dr.select(m, d02, best), dr.select(m, 0.0, bu), dr.select(m, s02, bv)
    m = d12 < best
    best, bu, bv = dr.select(m, d12, best), dr.select(m, 1.0 - s12, bu), dr.select(m, s12, bv)
    best = dr.select(inside, 0.0, best)
    bu = dr.select(inside, u, bu)
    bv = dr.select(inside, v, bv)
    return best, bu, bv
