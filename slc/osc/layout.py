"""The on-surface cache's layout: islands, their texture spaces and levels,
and the virtual block space, as Dr.Jit tables (set up once per scene).

A texel is addressed by (island, level, tx, ty): island-local level-0
coordinates divided by ``2**level``. The texels of one (island, level) are
cut into ``B x B`` virtual blocks, numbered consecutively over all
(island, level) pairs: ``vblock = base[isl, lvl] + (ty >> log2 B) * nbx[isl, lvl] + (tx >> log2 B)``.
Nothing here changes per frame; the block table that maps virtual blocks to
memory is :mod:`.blocks`.

Meshes map a hit to its texel by barycentrics (``gb.prim_index``,
``gb.prim_uv``). Analytic shapes (sphere, disk, cylinder) get islands built
on a tessellation of their (u, v) square (:func:`.analytic.tessellate_analytic`):
a hit's grid triangle comes from its ``si.uv`` directly (no 3D search), its
island is that triangle's, and its texel coordinates are the orthographic
projection of ``si.p`` on the island's plane (the same projection that made
the island's texture space). Other shapes get no entries (one warning).
"""
from __future__ import annotations

import math
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.osc.analytic import ANALYTIC_KIND, ParamGrid, analytic_point, shape_to_world, tessellate_analytic
from slc.osc.islands import DEFAULT_MAX_ANGLE, DEFAULT_MAX_TRIANGLES, MeshIslands, build_mesh_islands

DEFAULT_TARGET_TEXELS = 2 ** 24      # level-0 texels over the whole scene when texel_size is None
MAX_LEVELS = 20


def u32(a) -> mi.UInt32:
    """A Dr.Jit table; never empty (a masked gather from an empty array still
    raises: a scene with nothing cacheable gets one-element tables)."""
    a = np.ascontiguousarray(a, dtype=np.uint32).ravel()
    return mi.UInt32(a if a.size else np.zeros(1, np.uint32))


def f32(a) -> mi.Float:
    a = np.ascontiguousarray(a, dtype=np.float32).ravel()
    return mi.Float(a if a.size else np.zeros(1, np.float32))


class CacheLayout:
    """Islands, levels and the virtual block space of a scene's meshes and
    analytic shapes.

    Parameters: ``block_size`` (texels per block edge, a power of two),
    ``bias`` (mip bias), ``texel_size`` (world size of a level-0 texel;
    default ``sqrt(total cached area / 2**24)``), ``max_angle`` and
    ``max_triangles`` (island bounds, degrees and triangles)."""

    def __init__(self, mi_scene, block_size: int = 8, bias: float = 1.0, texel_size: float | None = None,
                 max_angle: float = DEFAULT_MAX_ANGLE, max_triangles: int = DEFAULT_MAX_TRIANGLES):
        B = int(block_size)
        if B < 1 or B & (B - 1):
            raise ValueError(f"block_size must be a power of two, got {block_size}")
        self.mi_scene = mi_scene
        self.block_size, self.block_shift, self.block_texels = B, B.bit_length() - 1, B * B
        self.bias = float(bias)
        self.max_angle, self.max_triangles = float(max_angle), int(max_triangles)
        self._build_islands(texel_size)
        self._build_tables()

    # ------------------------------------------------------------------ set-up
    def _surfaces(self):
        """(shape index, V, F, ParamGrid or None) of every cacheable shape:
        meshes, and analytic shapes through their parameter-space grid. Other
        shapes are named in one warning."""
        out, skipped = [], []
        for k, sh in enumerate(self.mi_scene.shapes()):
            if sh.is_mesh():
                V = np.array(sh.vertex_positions_buffer(), np.float32).reshape(-1, 3)
                F = np.array(sh.faces_buffer(), np.uint32).reshape(-1, 3)
                if len(F):
                    out.append((k, V, F, None))
                continue
            grid = tessellate_analytic(sh)
            if grid is None:
                skipped.append(f"{sh.id() or k} ({sh.class_name()})")
                continue
            out.append((k, grid.V.astype(np.float32), grid.F.astype(np.uint32), grid))
        if skipped:
            warnings.warn(f"on-surface cache: no entries for {len(skipped)} shape(s) of unsupported type, "
                          f"their pixels stay black: {', '.join(skipped)}", stacklevel=3)
        return out

    def _build_islands(self, texel_size):
        surfaces = self._surfaces()
        self.n_shapes = len(self.mi_scene.shapes())
        area = 0.0
        for _, V, F, _ in surfaces:
            V64 = V.astype(np.float64)
            c = np.cross(V64[F[:, 1]] - V64[F[:, 0]], V64[F[:, 2]] - V64[F[:, 0]])
            area += 0.5 * float(np.linalg.norm(c, axis=1).sum())
        self.total_area = area
        if texel_size is None:
            texel_size = math.sqrt(max(area, 1e-12) / DEFAULT_TARGET_TEXELS)
        self.texel_size = float(texel_size)
        self.islands: list[MeshIslands] = []
        self.mesh_data = {}
        self.grids: dict[int, ParamGrid] = {}
        for k, V, F, grid in surfaces:
            isl = build_mesh_islands(V, F, self.texel_size, shape_index=k,
                                     max_angle=self.max_angle, max_triangles=self.max_triangles)
            self.islands.append(isl)
            self.mesh_data[k] = (V, F)
            if grid is not None:
                self.grids[k] = grid
        self.has_analytic = bool(self.grids)

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
        # island-sorted triangles for the texel -> triangle lookup (.surface)
        order = np.argsort(tri_island, kind="stable")
        counts = np.bincount(tri_island, minlength=ni) if ni else np.zeros(0, np.int64)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if ni else np.zeros(0, np.int64)
        # Dr.Jit tables
        self.d_tri_base = u32(tri_base)
        self.d_has_cache = mi.Bool(has_cache.tolist() if self.n_shapes else [False])
        self.d_tri_island = u32(tri_island)
        self.d_tri_uv = f32(tri_uv.ravel())            # 6 floats per triangle
        self.d_isl_shape = u32(isl_shape)
        self.d_isl_maxl = u32(maxl)
        self.d_isl_start = u32(starts)
        self.d_isl_count = u32(counts)
        self.d_sorted_tri = u32(order)
        self.d_sorted_uv = f32(tri_uv[order].ravel())
        self.d_lvl_base = u32(base)
        self.d_lvl_nbx = u32(nbx.ravel())
        self.d_lvl_w = u32(w.ravel())
        self.d_lvl_h = u32(h.ravel())
        self.d_isl_dims = u32(dims.ravel())
        if self.has_analytic:
            self._build_analytic_tables(nt, ni)

    def _build_analytic_tables(self, nt, ni):
        """Per shape: analytic flag, grid size, periodic flags and the base of
        its grid-triangle map; per triangle the (u, v) of its corners (zero for
        mesh triangles); per island its plane (2 axes, origin) to project hits."""
        ns = self.n_shapes
        analytic = np.zeros(ns, bool)
        grid_dims = np.ones((ns, 2), np.int64)
        periodic = np.zeros((ns, 2), bool)
        gbase = np.zeros(ns, np.int64)
        kind = np.zeros(ns, np.int64)
        xform = np.tile(np.eye(4), (ns, 1, 1))
        shapes = self.mi_scene.shapes()
        gmap, ng = [], 0
        tri_param = np.zeros((nt, 6))
        axes = np.zeros((ni, 2, 3))
        origin = np.zeros((ni, 2))
        for m in self.islands:
            k = m.shape_index
            i0 = self.island_base[k]
            axes[i0:i0 + m.n_islands] = m.axes
            origin[i0:i0 + m.n_islands] = m.origin
            g = self.grids.get(k)
            if g is None:
                continue
            analytic[k] = True
            kind[k] = ANALYTIC_KIND[shapes[k].class_name()]
            xform[k] = shape_to_world(shapes[k])
            grid_dims[k] = (g.nu, g.nv)
            periodic[k] = g.periodic
            gbase[k] = ng
            gmap.append(g.grid_tri)
            ng += len(g.grid_tri)
            t0 = int(self._np_tri_base[k])
            tri_param[t0:t0 + len(g.F)] = g.corner_param.reshape(-1, 6)
        self.d_shape_analytic = mi.Bool(analytic.tolist())
        self.d_shape_kind = u32(kind)
        self.d_shape_xform = f32(xform.ravel())          # 16 floats per shape, row-major
        self.d_grid_dims = u32(grid_dims.ravel())
        self.d_grid_periodic = mi.Bool(periodic.ravel().tolist())
        self.d_grid_base = u32(gbase)
        self.d_grid_tri = u32(np.concatenate(gmap))
        self.d_tri_param = f32(tri_param.ravel())
        self.d_isl_axes = f32(axes.ravel())
        self.d_isl_origin = f32(origin.ravel())

    # ------------------------------------------------------------------ addressing
    def vblock(self, key, tx, ty, active=True) -> mi.UInt32:
        """Virtual block of texel (tx, ty) of the (island, level) ``key = isl * levels + lvl``."""
        sh = self.block_shift
        return dr.gather(mi.UInt32, self.d_lvl_base, key, active) + \
            (ty >> sh) * dr.gather(mi.UInt32, self.d_lvl_nbx, key, active) + (tx >> sh)

    def within(self, tx, ty) -> mi.UInt32:
        """Texel index inside its block."""
        B, sh = self.block_size, self.block_shift
        return ((ty & (B - 1)) << sh) | (tx & (B - 1))

    def key_extent(self, key, active=True):
        """Texel width and height (Int32) of the (island, level) ``key``."""
        return (mi.Int32(dr.gather(mi.UInt32, self.d_lvl_w, key, active)),
                mi.Int32(dr.gather(mi.UInt32, self.d_lvl_h, key, active)))

    def pixel_coords(self, gb):
        """Per pixel: (valid, island, island-local level-0 coordinates, level,
        the island-level key ``isl * levels + lvl``)."""
        sidx = mi.UInt32(gb.shape_index)
        valid = mi.Bool(gb.valid) & (sidx < self.n_shapes)
        if self.n_islands == 0:          # nothing cacheable: every pixel invalid
            valid &= False
        valid &= dr.gather(mi.Bool, self.d_has_cache, sidx, valid)
        tri = dr.gather(mi.UInt32, self.d_tri_base, sidx, valid) + mi.UInt32(gb.prim_index)
        if self.has_analytic:
            ana = valid & dr.gather(mi.Bool, self.d_shape_analytic, sidx, valid)
            tri = dr.select(ana, self.grid_triangle(sidx, gb.si.uv, ana), tri)
        isl = dr.gather(mi.UInt32, self.d_tri_island, tri, valid)
        uv = self.bary_uv(tri, gb.prim_uv, valid)
        if self.has_analytic:
            uv = dr.select(ana, self.project(isl, gb.si.p, ana), uv)
        lvl = self.level_of(gb.footprint, isl, valid)
        return valid, isl, uv, lvl, isl * self.levels + lvl

    def pixel_texels(self, gb):
        """Per pixel: (valid, virtual block, texel in block, level)."""
        valid, isl, uv, lvl, k = self.pixel_coords(gb)
        wl, hl = self.key_extent(k, valid)
        scale = dr.rcp(mi.Float(mi.UInt32(1) << lvl))
        tx = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.x * scale)), 0, wl - 1))
        ty = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.y * scale)), 0, hl - 1))
        return valid, self.vblock(k, tx, ty, valid), self.within(tx, ty), lvl

    def bary_uv(self, tri, prim_uv, active):
        """Island-local level-0 texel coordinates of a hit: Mitsuba's
        barycentrics p = (1-u-v) p0 + u p1 + v p2."""
        c0 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 0, active)
        c1 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 1, active)
        c2 = dr.gather(mi.Point2f, self.d_tri_uv, tri * 3 + 2, active)
        u, v = prim_uv.x, prim_uv.y
        return c0 * (1.0 - u - v) + c1 * u + c2 * v

    def grid_triangle(self, sidx, uv, active) -> mi.UInt32:
        """Global triangle of an analytic shape's grid holding the parameter
        point ``uv`` (the cell from ``floor(uv * (nu, nv))``, the side of its
        diagonal from the fractions; collapsed triangles map to their cell's other one)."""
        nu = dr.gather(mi.UInt32, self.d_grid_dims, sidx * 2 + 0, active)
        nv = dr.gather(mi.UInt32, self.d_grid_dims, sidx * 2 + 1, active)
        fu = dr.clip(mi.Float(uv.x), 0.0, 1.0) * mi.Float(nu)
        fv = dr.clip(mi.Float(uv.y), 0.0, 1.0) * mi.Float(nv)
        ci = dr.minimum(mi.UInt32(dr.floor(fu)), nu - 1)
        cj = dr.minimum(mi.UInt32(dr.floor(fv)), nv - 1)
        second = (fu - mi.Float(ci)) + (fv - mi.Float(cj)) > 1.0
        g = 2 * (cj * nu + ci) + dr.select(second, 1, 0)
        local = dr.gather(mi.UInt32, self.d_grid_tri, dr.gather(mi.UInt32, self.d_grid_base, sidx, active) + g,
                          active)
        return dr.gather(mi.UInt32, self.d_tri_base, sidx, active) + local

    def project(self, isl, p, active=True) -> mi.Point2f:
        """Island-local level-0 texel coordinates of a world point: the
        orthographic projection on the island's plane that built its texture space."""
        a0 = dr.gather(mi.Vector3f, self.d_isl_axes, isl * 2 + 0, active)
        a1 = dr.gather(mi.Vector3f, self.d_isl_axes, isl * 2 + 1, active)
        o = dr.gather(mi.Point2f, self.d_isl_origin, isl, active)
        inv = 1.0 / self.texel_size
        return mi.Point2f((dr.dot(a0, mi.Vector3f(p)) - o.x) * inv, (dr.dot(a1, mi.Vector3f(p)) - o.y) * inv)

    def analytic_point(self, sidx, uv, active=True):
        """World (p, dp_du, dp_dv) of parameter points of analytic shapes
        (closed forms, :func:`.analytic.analytic_point`)."""
        rows = [[dr.gather(mi.Float, self.d_shape_xform, sidx * 16 + (4 * r + c), active) for c in range(4)]
                for r in range(3)]
        return analytic_point(dr.gather(mi.UInt32, self.d_shape_kind, sidx, active), rows, uv)

    def level_of(self, footprint, isl, active=True) -> mi.UInt32:
        """Mip level clamp(round(log2(footprint * bias / texel_size)), 0, island top level)."""
        r = mi.Float(footprint) * (self.bias / self.texel_size)
        lf = dr.round(dr.log2(dr.maximum(r, 1e-30)))
        maxl = dr.gather(mi.UInt32, self.d_isl_maxl, isl, active)
        return dr.minimum(mi.UInt32(dr.clip(lf, 0.0, float(self.max_level))), maxl)

    def block_of(self, vb):
        """(island-level key, block x, block y) of virtual blocks: a binary
        search in the per-(island, level) bases."""
        n_tab = len(self._np_lvl_base)
        k = mi.UInt32(dr.binary_search(0, n_tab, lambda i: dr.gather(mi.UInt32, self.d_lvl_base, i) <= vb)) - 1
        local = vb - dr.gather(mi.UInt32, self.d_lvl_base, k)
        # max(.., 1): masked-off SIMD lanes of a gather read 0, and an integer
        # division by 0 in any lane raises SIGFPE on the LLVM backend
        nbx = dr.maximum(dr.gather(mi.UInt32, self.d_lvl_nbx, k), 1)
        by = local // nbx
        return k, local - by * nbx, by


__all__ = ["CacheLayout", "INVALID", "u32", "f32", "DEFAULT_TARGET_TEXELS", "MAX_LEVELS"]
