"""``sharc``: a world-space radiance hash grid for indirect light shared by every viewer (SHaRC, as
in NVIDIA's RTXGI, on the hash grid of :mod:`slc.regir.grid` with a fixed cell size). See
:class:`SHaRC` and ``docs/world-space.md``."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..keys import INVALID
from ..lights import direct_sample, rng
from ..methods import Method, MethodError, Param, register
from ..references import indirect_paths
from ..regir.grid import HashGrid, cell_key

CELL_BYTES = 4 * 8               # resolved radiance (3), frame count; this frame's sum (3) and count
STREAM_PICK, STREAM_UPDATE, STREAM_QUERY, STREAM_DIRECT = 11, 12, 13, 14


@dataclass
class Vertex:
    """One vertex of the update paths: its cell key, whether it exists and the radiance it leaves
    towards the vertex before (next-event estimation at it plus the path's tail)."""
    key: mi.UInt64
    ok: mi.Bool
    L: mi.Color3f


class SHaRC(Method):
    r"""Spatially hashed radiance cache (SHaRC): outgoing radiance per world-space cell, updated by
    a few paths and read at the first secondary hit of every viewer's paths.

    Grid: a cell is ``floor(p / cell)`` and the octant of the shading normal, in a hash table of
    ``cells`` slots (:mod:`slc.regir.grid`, shared with ``regir``); the cell size is fixed per scene
    (default: 1/32 of the bounding-box diagonal of its geometry), so every viewer maps a point to
    the same cell.

    Update (stage ``update``, once per frame for all viewers): in every ``block`` x ``block`` pixel
    block of each viewer one pixel, drawn anew each frame, traces a path of ``vertices`` vertices
    :math:`x_0` (its G-buffer point), :math:`x_1, \dots` by BSDF sampling, with next-event
    estimation :math:`D_k` (one light sample and shadow ray) at every vertex. With
    :math:`m` = ``bounces`` - 1 the vertex :math:`x_k` (:math:`k + m <` ``vertices``) adds to its
    cell the sample

    .. math:: \hat L(x_k) = D_k + \sum_{j=1}^{m} \Big(\prod_{i=k}^{k+j-1} w_i\Big) D_{k+j},
              \qquad w_i = \frac{f(x_i)\cos\theta_i}{p(\omega_i)},

    an estimate of the radiance :math:`x_k` sends towards :math:`x_{k-1}` after 0 to :math:`m`
    reflections (sums and counts by ``scatter_reduce(add)``: concurrent updates of one cell are
    not lost). Emitters hit by bounce rays are not counted (next-event estimation counts them).

    Resolve (stage ``resolve``, once per frame): a cell that received :math:`n > 0` samples of sum
    :math:`S` this frame blends :math:`R \leftarrow R + (S/n - R)/F` with
    :math:`F = \min(F + 1, \text{frames})` (a running mean over frames, an exponential average
    once the cap is reached); a new cell starts from :math:`F = 0`. Cells that received no sample
    for ``evict`` frames are freed.

    Query (stage ``shade``, per viewer), ``spp`` paths per pixel: one BSDF sample from the G-buffer
    point :math:`x_0` to :math:`x_1`; where the segment is longer than a cell and the cell of
    :math:`x_1` holds a value (:math:`F > 0`), :math:`L \approx w_0 R(x_1)`; elsewhere the path goes
    on as ``pt``'s does: :math:`L \approx w_0 (D_1 + \text{bounces} - 1 \text{ more bounces with
    next-event estimation})`. ``output=full`` adds ``spp`` light samples of direct light at
    :math:`x_0`. Biased (the cell's mean stands for every point of the cell, the blend for the
    frames), consistent as the cell size goes to 0.

    Memory (bounded): the table (16 bytes per cell) and 32 bytes of radiance, frame count and
    this frame's sums per cell.
    """
    name = "sharc"
    output = "full"
    params = (
        Param("cell", None, "cell size in scene units (default: 1/32 of the scene geometry's bounding-box "
                            "diagonal)", lo=1e-4, kind=float),
        Param("block", 5, "one update path per block x block pixels of each viewer, drawn anew each frame "
                          "(SHaRC's 5: 4% of the pixels)", lo=1, hi=64),
        Param("vertices", 4, "vertices of an update path, the G-buffer point included (SHaRC's propagation "
                             "depth 4)", lo=1, hi=8),
        Param("bounces", 2, "indirect bounces (as pt; the reference's)", lo=1, hi=8),
        Param("frames", 32, "cap of a cell's accumulated frame count (SHaRC allows 1-64)", lo=1, hi=1 << 16),
        Param("evict", 8, "frames a cell may go without update samples before it is freed", lo=0),
        Param("cells", 1 << 16, "hash-table capacity in cells (rounded up to a power of two)", lo=32),
        Param("spp", 1, "query paths (and direct light samples) per pixel", lo=1, hi=64),
        Param("output", "full", "direct + indirect, or indirect light only", choices=("full", "indirect")),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        if self.cell is None:
            self.cell = float(np.linalg.norm(np.asarray(scene.bbox_max) - np.asarray(scene.bbox_min))) / 32.0
            self.cell = max(self.cell, 1e-4)
        self.label = None if self.output == "full" else "sharc:output=indirect"
        self._stats, self._hit = {}, None
        self.reset()

    def validate(self):
        if self.bounces > self.vertices:
            raise MethodError(f"sharc: bounces ({self.bounces}) must not exceed vertices ({self.vertices}): "
                              f"a vertex needs bounces - 1 more vertices for its sample")

    def reset(self):
        self.grid = HashGrid(self.cells, self.cell)
        n = self.grid.capacity
        self.rad, self.count = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)       # resolved
        self.acc, self.samples = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)     # this frame
        dr.eval(self.rad, self.count, self.acc, self.samples)
        self._stats, self._hit = {}, None

    # ------------------------------------------------------------------ frame

    def render(self, ctx, gbuffers, timer):
        frame = dr.opaque(mi.UInt32, ctx.frame)
        with timer.stage("update") as st:
            self.grid.evict(frame, self.evict)
            placed = [self.update(gb, ctx.frame, v, frame) for v, gb in enumerate(gbuffers)]
            st.outputs(self.acc, self.samples)
        with timer.stage("resolve") as st:
            resolved = self.resolve(frame)
            st.outputs(self.rad, self.count)
        with timer.stage("shade") as st:
            res = [self.shade(gb, ctx.frame, v, frame) for v, gb in enumerate(gbuffers)]
            outs = [r[0] for r in res]
            st.outputs(*outs)
        self._hit = [(r[1], dr.width(r[1])) for r in res]
        self._stats = {"cells_updated": float(resolved), "cell_overflow": float(self.grid.overflow),
                       "update_paths": float(sum(placed))}
        return outs

    # ------------------------------------------------------------------ update

    def _update_pixels(self, gb, frame: int, v: int) -> mi.UInt32:
        """One pixel per ``block`` x ``block`` block, uniformly drawn per block and frame."""
        B = self.block
        bw, bh = -(-gb.width // B), -(-gb.height // B)
        smp = rng(bw * bh, self.seed_for(frame, v), stream=STREAM_PICK)
        b = dr.arange(mi.UInt32, bw * bh)
        x = (b % bw) * B + mi.UInt32(smp.next_float32() * B)
        y = (b // bw) * B + mi.UInt32(smp.next_float32() * B)
        x = dr.minimum(x, gb.width - 1)
        y = dr.minimum(y, gb.height - 1)
        return y * gb.width + x

    def update(self, gb, frame: int, v: int, frame_id) -> int:
        """Trace one viewer's update paths and add their vertices' samples to their cells;
        returns the number of paths."""
        sc, h, ctx = self.scene.mi_scene, self.cell, mi.BSDFContext()
        idx = self._update_pixels(gb, frame, v)
        n = dr.width(idx)
        si = dr.gather(mi.SurfaceInteraction3f, gb.si, idx)
        active = dr.gather(mi.Bool, gb.valid, idx)
        smp = rng(n, self.seed_for(frame, v), stream=STREAM_UPDATE)

        # ---------------- the path: next-event estimation at each vertex, BSDF-sampled bounces ----------------
        keys, oks, D, w = [], [], [], []
        for k in range(self.vertices):
            bsdf = si.bsdf()
            keys.append(cell_key(si.p, si.sh_frame.n, h))
            oks.append(mi.Bool(active))
            D.append(direct_sample(sc, si, bsdf, mi.Point2f(smp.next_float32(), smp.next_float32()), active, ctx))
            if k + 1 == self.vertices:
                break
            bs, bw = bsdf.sample(ctx, si, smp.next_float32(), mi.Point2f(smp.next_float32(), smp.next_float32()),
                                 active)
            active &= bs.pdf > 0.0
            w.append(dr.select(active, mi.Color3f(bw), 0.0))
            si = sc.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active)
            active &= si.is_valid()

        # ---------------- each vertex's sample: its own NEE plus bounces - 1 more of its tail ----------------
        m = self.bounces - 1
        verts = []
        for k in range(self.vertices - m):
            L, beta = mi.Color3f(D[k]), mi.Color3f(1.0)
            for j in range(1, m + 1):
                beta = beta * w[k + j - 1]
                L += beta * D[k + j]
            verts.append(Vertex(keys[k], oks[k], L))
        key = dr.concat([x.key for x in verts])
        ok = dr.concat([x.ok for x in verts])
        L = mi.Color3f(*[dr.concat([x.L[c] for x in verts]) for c in range(3)])
        slot, _ = self.grid.insert(key, ok, frame_id)
        put = ok & (slot != INVALID)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc, L, slot, put)
        dr.scatter_reduce(dr.ReduceOp.Add, self.samples, mi.Float(1.0), slot, put)
        dr.eval(self.acc, self.samples)
        return n

    # ------------------------------------------------------------------ resolve

    def resolve(self, frame) -> int:
        """Blend this frame's mean into every updated cell; clear the frame's sums."""
        cells = self.grid.touched(frame)
        n_cells = dr.width(cells)
        if n_cells == 0:
            return 0
        S = dr.gather(mi.Color3f, self.acc, cells)
        n = dr.gather(mi.Float, self.samples, cells)
        has = n > 0.0
        alive = dr.gather(mi.UInt32, self.grid.born, cells) != frame
        F_old = dr.select(alive, dr.gather(mi.Float, self.count, cells), 0.0)
        R_old = dr.select(alive, dr.gather(mi.Color3f, self.rad, cells), 0.0)
        F = dr.select(has, dr.minimum(F_old + 1.0, dr.opaque(mi.Float, self.frames)), F_old)
        mean = S / dr.select(has, n, 1.0)
        R = dr.select(has, R_old + (mean - R_old) / dr.maximum(F, 1.0), R_old)
        dr.scatter(self.rad, R, cells)
        dr.scatter(self.count, F, cells)
        dr.scatter(self.acc, mi.Color3f(0.0), cells)
        dr.scatter(self.samples, mi.Float(0.0), cells)
        dr.eval(self.rad, self.count, self.acc, self.samples)
        return n_cells

    # ------------------------------------------------------------------ query

    def shade(self, gb, frame: int, v: int, frame_id):
        """One viewer's light: ``spp`` query paths (the cache at the first secondary hit, else one
        more path segment) and, with ``output=full``, direct light; also the mask of the query
        paths that read the cache (of the last path)."""
        sc, h, ctx = self.scene.mi_scene, self.cell, mi.BSDFContext()
        si0, valid = gb.si, mi.Bool(gb.valid)
        bsdf0 = si0.bsdf()
        smp = rng(gb.size, self.seed_for(frame, v), stream=STREAM_QUERY)
        L = mi.Color3f(0.0)
        cached = dr.zeros(mi.Bool, gb.size)
        for _ in range(self.spp):
            bs, w0 = bsdf0.sample(ctx, si0, smp.next_float32(), mi.Point2f(smp.next_float32(), smp.next_float32()),
                                  valid)
            ok = valid & (bs.pdf > 0.0)
            si = sc.ray_intersect(si0.spawn_ray(si0.to_world(bs.wo)), ok)
            ok &= si.is_valid()
            slot = self.grid.find(cell_key(si.p, si.sh_frame.n, h), ok & (si.t > h), frame_id)
            cached = (slot != INVALID) & (dr.gather(mi.Float, self.count, slot, slot != INVALID) > 0.0)
            Lc = dr.gather(mi.Color3f, self.rad, slot, cached)

            # ---------------- no cached value: the path goes on (NEE at x1, bounces - 1 more) ----------------
            go = ok & ~cached
            Lf = direct_sample(sc, si, si.bsdf(), mi.Point2f(smp.next_float32(), smp.next_float32()), go, ctx)
            if self.bounces > 1:
                Lf += indirect_paths(sc, si, go, smp, 1, self.bounces - 1)
            L += dr.select(ok, mi.Color3f(w0) * dr.select(cached, Lc, Lf), 0.0)
        L = L / float(self.spp)
        if self.output == "full":
            sd = rng(gb.size, self.seed_for(frame, v), stream=STREAM_DIRECT)
            Ld = mi.Color3f(0.0)
            for _ in range(self.spp):
                Ld += direct_sample(sc, si0, bsdf0, mi.Point2f(sd.next_float32(), sd.next_float32()), valid, ctx)
            L = L + Ld / float(self.spp)
        return dr.select(valid, L, 0.0), cached

    # ------------------------------------------------------------------ state

    def memory_bytes(self) -> int:
        return self.grid.memory_bytes() + CELL_BYTES * self.grid.capacity

    def stats(self) -> dict:
        out = dict(self._stats)
        if self._hit:
            out["cache_hits"] = sum(float(dr.count(m)[0]) for m, _ in self._hit) / max(sum(n for _, n in self._hit), 1)
        if self._stats:
            out["cell_load"] = self.grid.load()
        return out


register("sharc", SHaRC, help="SHaRC: a world-space radiance hash grid for indirect light shared by all viewers "
                              "(4% update paths of 4 vertices, 32-frame blend, eviction after 8 frames)")
