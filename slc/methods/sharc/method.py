"""``sharc``: a world-space radiance hash grid for indirect light shared by every viewer (SHaRC, as
in NVIDIA's RTXGI, on the hash grid of :mod:`slc.core.hashgrid` with a fixed cell size). See
:class:`SHaRC` and ``docs/world-space.md``."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.freeze import FrozenFunction
from slc.core.keys import INVALID
from slc.scene.lights import direct_sample, light_inputs, rng, stream_state
from slc.methods import Method, MethodError, Param, register
from slc.reference.references import indirect_paths
from slc.core.hashgrid import HashGrid, cell_key, find_slot

CELL_BYTES = 4 * 5 + 8 * 3 + 4   # resolved radiance (3), frame count, sample weight; this frame's sum (3), count
RADIANCE_SCALE = float(1 << 20)  # fixed point of the frame's sums (SHaRC: 1e3 in 32 bits; here 64 bits)
STREAM_PICK, STREAM_UPDATE, STREAM_QUERY, STREAM_DIRECT, STREAM_CONTINUE = 11, 12, 13, 14, 15


@dataclass
class Vertex:
    """One vertex of the update paths: its cell key, whether it exists and the radiance it leaves
    towards the vertex before (next-event estimation at it plus the path's tail)."""
    key: mi.UInt64
    ok: mi.Bool
    L: mi.Color3f


def _sampler(state: mi.UInt64, n: int) -> mi.PCG32:
    return mi.PCG32(size=n, initstate=state, initseq=dr.arange(mi.UInt64, n))


def _update_kernel(scene, lights, si, active, state, vertices: int, bounces: int, h: float) -> list:
    """The update paths from the points ``si`` (``active`` valid): per vertex that takes a sample
    (see :class:`SHaRC`), a :class:`Vertex`. ``lights`` declares the emitter table an input."""
    ctx = mi.BSDFContext()
    smp = _sampler(state, dr.width(active))
    active = mi.Bool(active)

    # ---------------- the path: next-event estimation at each vertex, BSDF-sampled bounces ----------------
    keys, oks, D, w = [], [], [], []
    for k in range(vertices):
        bsdf = si.bsdf()
        keys.append(cell_key(si.p, si.sh_frame.n, h))
        oks.append(mi.Bool(active))
        D.append(direct_sample(scene, si, bsdf, mi.Point2f(smp.next_float32(), smp.next_float32()), active, ctx))
        if k + 1 == vertices:
            break
        bs, bw = bsdf.sample(ctx, si, smp.next_float32(), mi.Point2f(smp.next_float32(), smp.next_float32()), active)
        active &= bs.pdf > 0.0
        w.append(dr.select(active, mi.Color3f(bw), 0.0))
        si = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active)
        active &= si.is_valid()

    # ---------------- each vertex's sample: its own NEE plus bounces - 1 more of its tail ----------------
    m = bounces - 1
    out = []
    for k in range(vertices - m):
        L, beta = mi.Color3f(D[k]), mi.Color3f(1.0)
        for j in range(1, m + 1):
            beta = beta * w[k + j - 1]
            L += beta * D[k + j]
        out.append(Vertex(keys[k], oks[k], L))
    dr.eval(out)
    return out


@dataclass
class Query:
    """The first segments of a viewer's query paths (``spp`` per pixel, lane ``pixel * spp + k``):
    per pixel the sum of the cached light ``w_0 R(x_1)`` and the direct light (``output=full``);
    per path the slot of the cell read (``INVALID``: none), and for the paths that go on (``go``)
    their ray to ``x_1`` and throughput ``w_0``."""
    Lc: mi.Color3f
    Ld: mi.Color3f
    slot: mi.UInt32
    go: mi.Bool
    o: mi.Point3f
    d: mi.Vector3f
    w0: mi.Color3f


def _query_kernel(scene, lights, si0, valid, keys, rad, count, s_q, s_d, buckets: int, h: float, spp: int,
                  full: bool) -> Query:
    """The first segment of the query paths of :class:`SHaRC` from the points ``si0`` (``valid``),
    the table ``keys`` (``buckets`` buckets) and the cells' resolved ``rad`` / ``count``."""
    ctx = mi.BSDFContext()
    n = dr.width(valid)
    bsdf0 = si0.bsdf()
    smp = _sampler(s_q, n)
    pix = dr.arange(mi.UInt32, n) * spp
    q = Query(mi.Color3f(0.0), mi.Color3f(0.0), dr.full(mi.UInt32, INVALID, n * spp), dr.zeros(mi.Bool, n * spp),
              dr.zeros(mi.Point3f, n * spp), dr.zeros(mi.Vector3f, n * spp), dr.zeros(mi.Color3f, n * spp))
    slots, go, o, d, w0s = q.slot, q.go, q.o, q.d, q.w0

    def body(k, Lc, smp):
        bs, w0 = bsdf0.sample(ctx, si0, smp.next_float32(), mi.Point2f(smp.next_float32(), smp.next_float32()), valid)
        ok = valid & (bs.pdf > 0.0)
        ray = si0.spawn_ray(si0.to_world(bs.wo))
        si = scene.ray_intersect(ray, ok)
        ok &= si.is_valid()
        slot = find_slot(keys, buckets, cell_key(si.p, si.sh_frame.n, h), ok & (si.t > h))
        cached = ok & (slot != INVALID) & (dr.gather(mi.Float, count, slot, slot != INVALID) > 0.0)
        Lc += dr.select(cached, mi.Color3f(w0) * dr.gather(mi.Color3f, rad, slot, cached), 0.0)
        at = pix + k
        dr.scatter(slots, dr.select(cached, slot, INVALID), at)
        dr.scatter(go, ok & ~cached, at)
        dr.scatter(o, ray.o, at)
        dr.scatter(d, ray.d, at)
        dr.scatter(w0s, mi.Color3f(w0), at)
        return k + 1, Lc, smp

    n_spp = dr.opaque(mi.UInt32, spp)
    _, q.Lc, smp = dr.while_loop((mi.UInt32(0), q.Lc, smp), lambda k, *_: k < n_spp, body, labels=("k", "Lc", "smp"))
    if full:
        sd = _sampler(s_d, n)

        def direct(k, Ld, sd):
            u = mi.Point2f(sd.next_float32(), sd.next_float32())
            return k + 1, Ld + direct_sample(scene, si0, bsdf0, u, valid, ctx), sd

        _, q.Ld, _ = dr.while_loop((mi.UInt32(0), q.Ld, sd), lambda k, *_: k < n_spp, direct, labels=("k", "Ld", "sd"))
    dr.eval(q)
    return q


def _continue_kernel(scene, lights, o, d, state, bounces: int) -> mi.Color3f:
    """The query paths that found no cached value go on from ``x_1`` (the hit of the rays ``o``,
    ``d``): next-event estimation there and ``bounces`` - 1 more bounces with next-event
    estimation, as ``pt``'s paths."""
    ctx = mi.BSDFContext()
    n = dr.width(o)
    smp = _sampler(state, n)
    si = scene.ray_intersect(mi.Ray3f(o, d))
    ok = si.is_valid()
    L = direct_sample(scene, si, si.bsdf(), mi.Point2f(smp.next_float32(), smp.next_float32()), ok, ctx)
    if bounces > 1:
        L += indirect_paths(scene, si, ok, smp, 1, bounces - 1)
    L = dr.select(ok, L, 0.0)
    dr.eval(L)
    return L


@dataclass
class Resolved:
    """The frame's cache after its update and resolve stages, for shading: the frame index
    (opaque), the cells resolved and the update paths traced; shading appends, per viewer, the
    mask of the query paths that read the cache (``hit``)."""
    frame_id: mi.UInt32
    cells: object
    update_paths: object
    hit: list = field(default_factory=list)

class SHaRC(Method):
    r"""Spatially hashed radiance cache (SHaRC): outgoing radiance per world-space cell, updated by
    a few paths and read at the first secondary hit of every viewer's paths.

    Grid: a cell is ``floor(p / cell)`` and the octant of the shading normal, in a hash table of
    ``cells`` slots (:mod:`slc.core.hashgrid`, shared with ``regir``); the cell size is fixed per scene
    (default: 1/12 of the bounding-box diagonal of its geometry), so every viewer maps a point to
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
    reflections. Sums (fixed point, 2^20 per unit, 64-bit integers: SHaRC's premultiplied
    integer sums) and counts are added with ``scatter_reduce(add)``: concurrent updates of one cell
    are not lost, and integer sums do not depend on their order (deterministic). Emitters hit by
    bounce rays are not counted (next-event estimation counts them).

    Resolve (stage ``resolve``, once per frame): a cell that received :math:`n > 0` samples of sum
    :math:`S` this frame becomes :math:`R \leftarrow (R N k + S) / (N k + n)`,
    :math:`N \leftarrow N k + n`, with :math:`k = 1` while its frame count :math:`F` (frames with
    samples, capped at ``frames``) is below the cap and :math:`k = 1 - 1/\text{frames}` once it is
    reached: a mean weighted by samples that becomes an exponential average over about ``frames``
    frames. A new cell starts from :math:`N = F = 0`. Cells neither updated nor read by a query for
    ``evict`` frames are freed.

    Query (stage ``shade``, per viewer), ``spp`` paths per pixel: one BSDF sample from the G-buffer
    point :math:`x_0` to :math:`x_1`; where the segment is longer than a cell and the cell of
    :math:`x_1` holds a value (:math:`F > 0`), :math:`L \approx w_0 R(x_1)`; the other paths are
    gathered and go on as ``pt``'s do: :math:`L \approx w_0 (D_1 + \text{bounces} - 1 \text{
    more bounces with next-event estimation})`. ``output=full`` adds ``spp`` light samples of
    direct light at :math:`x_0`. Biased (the cell's mean stands for every point of the cell, the
    average for the frames), consistent as the cell size goes to 0.

    Memory (bounded): the table (16 bytes per cell) and 48 bytes per cell for the resolved
    radiance, frame count and sample weight and the frame's sums and counts.
    """
    name = "sharc"
    output = "full"
    params = (
        Param("cell", None, "cell size in scene units (default: 1/12 of the scene geometry's bounding-box "
                            "diagonal; measured on cornell)", lo=1e-4, kind=float),
        Param("block", 8, "one update path per block x block pixels of each viewer, drawn anew each frame "
                          "(SHaRC recommends 5: 4% of the pixels; 8 measured better at equal time)", lo=1, hi=64),
        Param("vertices", 4, "vertices of an update path, the G-buffer point included (SHaRC's propagation "
                             "depth 4)", lo=1, hi=8),
        Param("bounces", 2, "indirect bounces (as pt; the reference's)", lo=1, hi=8),
        Param("frames", 32, "cap of a cell's accumulated frame count (SHaRC allows 1-64)", lo=1, hi=1 << 16),
        Param("evict", 8, "frames a cell may go neither updated nor read before it is freed", lo=0),
        Param("cells", 1 << 16, "hash-table capacity in cells (rounded up to a power of two)", lo=32),
        Param("spp", 10, "query paths (and direct light samples) per pixel (10 measured at equal time with pt10)",
              lo=1, hi=256),
        Param("output", "full", "direct + indirect, or indirect light only", choices=("full", "indirect")),
        Param("freeze", True, "trace the update and query kernels once and replay them (dr.freeze)"),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        if self.cell is None:
            self.cell = float(np.linalg.norm(np.asarray(scene.bbox_max) - np.asarray(scene.bbox_min))) / 12.0
            self.cell = max(self.cell, 1e-4)
        self.label = None if self.output == "full" else "sharc:output=indirect"
        self._stats, self._hit = {}, None
        self._update_k = FrozenFunction(_update_kernel, bool(self.freeze))
        self._query_k = FrozenFunction(_query_kernel, bool(self.freeze))
        self._continue_k = FrozenFunction(_continue_kernel, bool(self.freeze), lanes=(2, 3),
                                          narrow=(2,))
        self.reset()

    def validate(self):
        if self.bounces > self.vertices:
            raise MethodError(f"sharc: bounces ({self.bounces}) must not exceed vertices ({self.vertices}): "
                              f"a vertex needs bounces - 1 more vertices for its sample")

    def reset(self):
        self.grid = HashGrid(self.cells, self.cell)
        n = self.grid.capacity
        self.rad, self.count = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)       # resolved: R, F
        self.weight = dr.zeros(mi.Float, n)                                          # resolved: N
        self.acc = dr.zeros(mi.UInt64, 3 * n)                                        # this frame: sums (fixed point)
        self.samples = dr.zeros(mi.UInt32, n)                                        # and sample counts
        dr.eval(self.rad, self.count, self.weight, self.acc, self.samples)
        self._stats, self._hit = {}, None

    # ------------------------------------------------------------------ frame

    def update_frame(self, ctx, gbuffers, timer) -> "Resolved":
        frame = dr.opaque(mi.UInt32, ctx.frame)
        with timer.stage("update") as st:
            self.grid.evict(frame, self.evict)
            ups = [self.update(gb, ctx.frame, v, frame) for v, gb in enumerate(gbuffers)]
            st.outputs(*[u[1] for u in ups])             # the update paths' samples (check mode)
        with timer.stage("resolve") as st:
            resolved = self.resolve(frame)
            st.outputs(self.rad, self.count)
        return Resolved(frame_id=frame, cells=resolved, update_paths=sum(u[0] for u in ups))

    def finish(self, ctx, fr: "Resolved", gbuffers, outs, timer):
        self._hit = [(m, dr.width(m)) for m in fr.hit]
        self._stats = {"cells_updated": float(fr.cells), "cell_overflow": float(self.grid.overflow),
                       "update_paths": float(fr.update_paths)}
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

    def update(self, gb, frame: int, v: int, frame_id) -> tuple:
        """Trace one viewer's update paths and add their vertices' samples to their cells;
        returns the number of paths and the samples."""
        sc = self.scene.mi_scene
        idx = self._update_pixels(gb, frame, v)
        si = dr.gather(mi.SurfaceInteraction3f, gb.si, idx)
        active = dr.gather(mi.Bool, gb.valid, idx)
        verts = self._update_k(sc, light_inputs(sc), si, active,
                               stream_state(self.seed_for(frame, v), STREAM_UPDATE), int(self.vertices),
                               int(self.bounces), float(self.cell))
        key = dr.concat([x.key for x in verts])
        ok = dr.concat([x.ok for x in verts])
        L = mi.Color3f(*[dr.concat([x.L[c] for x in verts]) for c in range(3)])
        slot, _ = self.grid.insert(key, ok, frame_id)
        put = ok & (slot != INVALID)
        # integer sums: associative, so that the order of concurrent updates does not change them
        for c in range(3):
            fixed = mi.UInt64(dr.round(dr.maximum(L[c], 0.0) * RADIANCE_SCALE))
            dr.scatter_reduce(dr.ReduceOp.Add, self.acc, fixed, slot * 3 + c, put)
        dr.scatter_reduce(dr.ReduceOp.Add, self.samples, mi.UInt32(1), slot, put)
        dr.eval(self.acc, self.samples)
        return dr.width(idx), L

    # ------------------------------------------------------------------ resolve

    def resolve(self, frame) -> int:
        """Merge this frame's samples into every updated cell (a mean weighted by samples over
        about the last ``frames`` frames); clear the frame's sums."""
        cells = self.grid.touched(frame)
        n_cells = dr.width(cells)
        if n_cells == 0:
            return 0
        S = mi.Color3f(*[mi.Float(dr.gather(mi.UInt64, self.acc, cells * 3 + c)) for c in range(3)]) / RADIANCE_SCALE
        n = mi.Float(dr.gather(mi.UInt32, self.samples, cells))
        has = n > 0.0
        alive = dr.gather(mi.UInt32, self.grid.born, cells) != frame
        F_old = dr.select(alive, dr.gather(mi.Float, self.count, cells), 0.0)
        N_old = dr.select(alive, dr.gather(mi.Float, self.weight, cells), 0.0)
        R_old = dr.select(alive, dr.gather(mi.Color3f, self.rad, cells), 0.0)
        cap = dr.opaque(mi.Float, self.frames)
        keep = dr.select(F_old >= cap, (cap - 1.0) / cap, 1.0)          # the oldest frame's share fades
        N = N_old * keep + n
        R = dr.select(has, (R_old * (N_old * keep) + S) / dr.select(N > 0.0, N, 1.0), R_old)
        dr.scatter(self.rad, R, cells)
        dr.scatter(self.weight, dr.select(has, N, N_old), cells)
        dr.scatter(self.count, dr.select(has, dr.minimum(F_old + 1.0, cap), F_old), cells)
        for c in range(3):
            dr.scatter(self.acc, mi.UInt64(0), cells * 3 + c)
        dr.scatter(self.samples, mi.UInt32(0), cells)
        dr.eval(self.rad, self.weight, self.count, self.acc, self.samples)
        return n_cells

    # ------------------------------------------------------------------ query

    def shade(self, ctx, fr: "Resolved", v: int, gb) -> mi.Color3f:
        """One viewer's light: the first segments of the query paths (:func:`_query_kernel`), then
        the paths without a cached value, gathered, go on (:func:`_continue_kernel`); the cells
        read stay alive. The mask of the query paths that read the cache is kept in ``fr.hit``."""
        frame_id = fr.frame_id
        sc, seed, spp = self.scene.mi_scene, self.seed_for(ctx.frame, v), int(self.spp)
        lights = light_inputs(sc)
        q = self._query_k(sc, lights, gb.si, mi.Bool(gb.valid), self.grid.keys, self.rad, self.count,
                          stream_state(seed, STREAM_QUERY), stream_state(seed, STREAM_DIRECT),
                          int(self.grid.buckets), float(self.cell), spp, self.output == "full")
        self.grid.mark_used(q.slot, frame_id)
        lanes = dr.compress(q.go)
        Lf = dr.zeros(mi.Color3f, gb.size * spp)
        if dr.width(lanes) > 0:
            o, d = dr.gather(mi.Point3f, q.o, lanes), dr.gather(mi.Vector3f, q.d, lanes)
            Lt = self._continue_k(sc, lights, o, d, stream_state(seed, STREAM_CONTINUE), int(self.bounces))
            dr.scatter(Lf, dr.gather(mi.Color3f, q.w0, lanes) * Lt, lanes)
        pix = dr.arange(mi.UInt32, gb.size) * spp
        L = mi.Color3f(q.Lc)
        for k in range(spp):
            L += dr.gather(mi.Color3f, Lf, pix + k)
        L = dr.select(mi.Bool(gb.valid), (L + q.Ld) / float(spp), 0.0)
        dr.eval(L, self.grid.used)
        fr.hit.append(q.slot != INVALID)
        return L

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
                              "(one update path of 4 vertices per 8x8 pixels, 32-frame blend, eviction after 8 unused "
                              "frames, 10 query paths per pixel)")
