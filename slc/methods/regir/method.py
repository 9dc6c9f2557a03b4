"""``regir``: a world-space grid of light reservoirs shared by every viewer (ReGIR, as in NVIDIA's
RTXDI, on a hash grid with a fixed cell size). See :class:`ReGIR` and ``docs/world-space.md``."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.structs import drjit_struct
from slc.scene import emitter_table as et
from slc.scene.gbuffer import per_viewer
from slc.core.keys import INVALID, mixed_rng, stream_key
from slc.scene.lights import SurfaceBSDF, rng, sample_light_reference, sampler as light_table
from slc.methods import Method, MethodError, Param, register
from slc.core.hashgrid import HashGrid, cell_key, key_hash

STREAM_BUILD = 0x6E61B001
LOCAL_KINDS = (et.MESH, et.RECT, et.SPHERE, et.POINT)
SLOT_BYTES = 4 * 11              # y (3), n (3), L_e (3), W, M
REP_BYTES = 4 * 6                # a cell's representative point and normal


@drjit_struct
@dataclass
class Slots:
    """Light reservoirs of the grid, ``slots`` per cell (index ``cell * slots + j``): a point
    ``y`` on a local light, its emitting normal ``n`` (0 for a point light), its radiance ``Le``
    (a point light's intensity), the unbiased contribution weight ``W`` in the light's own
    measure (area, or counting for point lights) and the confidence ``M``."""
    y: mi.Point3f = field(default_factory=mi.Point3f)
    n: mi.Vector3f = field(default_factory=mi.Vector3f)
    Le: mi.Color3f = field(default_factory=mi.Color3f)
    W: mi.Float = field(default_factory=mi.Float)
    M: mi.Float = field(default_factory=mi.Float)


@drjit_struct
@dataclass
class BuildLoop:
    """The state of a reservoir's build (one lane per reservoir): ``i`` the candidates drawn, the
    selected candidate's point ``y``, normal ``n``, radiance ``Le`` and target ``p_sel``, ``w_sum``
    the sum of the resampling weights, ``smp`` the random numbers."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    y: mi.Point3f = field(default_factory=mi.Point3f)
    n: mi.Vector3f = field(default_factory=mi.Vector3f)
    Le: mi.Color3f = field(default_factory=mi.Color3f)
    p_sel: mi.Float = field(default_factory=mi.Float)
    w_sum: mi.Float = field(default_factory=mi.Float)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)


@drjit_struct
@dataclass
class TapLoop:
    """The state of a pixel sample's slot taps (one lane per pixel): ``i`` the taps drawn, the
    selected sample's point ``y_sel`` and ratio ``r_sel`` (``f L_e G`` over its target), ``w_sum``
    the sum of the resampling weights, ``smp`` the random numbers."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    y_sel: mi.Point3f = field(default_factory=mi.Point3f)
    r_sel: mi.Color3f = field(default_factory=mi.Color3f)
    w_sum: mi.Float = field(default_factory=mi.Float)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)


def light_term(x: mi.Point3f, y: mi.Point3f, n: mi.Vector3f, Le: mi.Color3f, active: mi.Bool):
    """``L_e G`` of a stored light sample seen from ``x`` in the sample's own measure:
    ``L_e cos_y / d^2`` on area lights (0 behind the emitting side), ``I / d^2`` for a point light
    (``n`` = 0); also the unit direction and the squared distance."""
    to = y - x
    d2 = dr.squared_norm(to)
    ok = mi.Bool(active) & (d2 > 0.0)
    inv_d = dr.rsqrt(dr.select(ok, d2, 1.0))
    d = to * inv_d
    point = dr.squared_norm(n) == 0.0
    cos_y = dr.select(point, 1.0, -dr.dot(d, n))
    ok &= cos_y > 0.0
    return dr.select(ok, Le * (cos_y * dr.square(inv_d)), 0.0), d, ok


def cell_target(rp: mi.Point3f, rn: mi.Vector3f, y: mi.Point3f, n: mi.Vector3f, Le: mi.Color3f,
                floor, active: mi.Bool) -> mi.Float:
    """The build target of a cell, ``lum(L_e G) max(cos_r, floor)`` at its representative point
    ``rp`` with normal ``rn`` (no BSDF, no visibility)."""
    t, d, ok = light_term(rp, y, n, Le, active)
    return dr.select(ok, mi.luminance(t) * dr.maximum(dr.dot(d, rn), floor), 0.0)


@dataclass
class Cells:
    """The frame's cells for shading: per viewer the slot of each pixel's cell
    (:meth:`ReGIR.find_cells`), and how many cells the build stage filled."""
    slot: list
    built: object

class ReGIR(Method):
    r"""Reservoir-based grid importance sampling of direct light (ReGIR), one grid shared by all
    viewers.

    Grid: a cell is ``floor(p / cell)`` and the octant of the shading normal, in a hash table of
    ``cells`` slots (:mod:`slc.core.hashgrid`). A pixel looks up the cell of its point jittered by a
    uniform offset in a box ``jitter`` cells wide; the cells looked up by any viewer's pixels in a
    frame are built once for all viewers (stage ``build``).

    Build: a cell's representative point :math:`c` and normal :math:`n_c` are those of the first
    pixel (lowest lane of all viewers' pixels) that placed it in the table; they stay while the
    cell lives. Each of its ``slots`` reservoirs takes ``build`` candidates :math:`x_i` from the
    scene's emitter table at :math:`c` (:mod:`slc.scene.emitter_sampling`) and keeps one by resampled
    importance sampling with the target :math:`\hat p_c(x) = \mathrm{lum}(L_e(x) G(c, x))
    \max(n_c \cdot \omega_{c \to x}, \kappa)\, v(c, x)` (``cosine`` = :math:`\kappa`; no BSDF;
    :math:`v = 1` where :math:`c` sees :math:`x` and ``occluded`` elsewhere, one shadow ray per
    candidate, so that every light keeps a non-zero target), giving it the weight
    :math:`W = \frac{1}{\hat p_c(y)} \frac{1}{B}\sum_i \hat p_c(x_i) / p(x_i)`. Only local lights
    (meshes, rectangles, spheres and point lights of the table) enter the grid. With
    ``temporal=1`` a slot then merges its previous reservoir (same cell, same target) with
    weights :math:`M_i / \sum M`, M the number of frames merged (capped at ``mcap``, counted
    whatever the samples were, so that the weights do not depend on them; persistent world-space
    reservoirs); history is dropped when a light moved.

    Shading (stage ``shade``, per viewer), ``samples`` times per pixel with fresh candidates
    (averaged): ``taps`` slots of the pixel's cell drawn uniformly and ``table`` emitter-table
    samples at the pixel are resampled with the full target
    :math:`\hat p_x(y) = \mathrm{lum}(f(x, y) L_e(y) G(x, y))` (the BSDF value includes the
    cosine) and one shadow ray is traced to the chosen sample:

    .. math:: L_o(x) \approx \frac{f L_e G V(y)}{\hat p_x(y)} \sum_k m_k(y_k)\, \hat p_x(y_k)\, W_k

    with :math:`W_k` a slot's weight or :math:`1/p(y_k)` for a table sample. The resampling MIS
    weights partition the lights: a point :math:`y` the cell's build can produce
    (:math:`\hat p_c(y) > 0`, a local light) gets :math:`(1 - \alpha)/\text{taps}` per slot tap
    and :math:`\alpha/\text{table}` per table sample (``defensive`` = :math:`\alpha`); any other
    point (environment and other Mitsuba-sampled emitters, the back of a light seen from the
    cell centre, a pixel whose cell did not fit in the table) gets :math:`1/\text{table}` per
    table sample. Every light thus keeps a non-zero probability and the estimate is unbiased.

    Memory (bounded): the table (16 bytes per cell), the representative point and normal (24
    bytes per cell), ``slots`` reservoirs of 44 bytes per cell, and a cell index per pixel.
    """
    name = "regir"
    params = (
        Param("cell", 2.0, "cell size in metres (RTXDI's default: 1; 2 measured best at equal time)", lo=1e-3),
        Param("slots", 128, "light reservoirs per cell (RTXDI: 512 lights per cell)", lo=1, hi=4096),
        Param("build", 8, "RIS candidates per reservoir at build time (RTXDI's default 8)", lo=1),
        Param("taps", 8, "reservoirs of its cell a pixel resamples per sample", lo=0),
        Param("table", 1, "emitter-table samples a pixel adds to its resampling", lo=1),
        Param("samples", 8, "resampled samples (and shadow rays) per pixel, averaged", lo=1),
        Param("defensive", 0.0, "MIS share of the table samples on lights the grid covers", lo=0.0, hi=1.0),
        Param("cosine", 1.0, "floor of the receiver cosine in the build target (1: no cosine)", lo=0.0, hi=1.0),
        Param("occluded", 1.0, "factor of the build target where the representative point does not see the "
                                "candidate (one shadow ray per candidate; 1: no rays)", lo=1e-3, hi=1.0),
        Param("jitter", 1.0, "width of the cell-lookup jitter box in cells (RTXDI's default 1)", lo=0.0),
        Param("temporal", 1, "merge each reservoir with its previous frame's (0/1; 1 measured best at equal time)", lo=0, hi=1),
        Param("mcap", 20.0, "confidence cap M of the temporal merge", lo=1.0),
        Param("cells", 8192, "hash-table capacity in cells (rounded up to a power of two)", lo=32),
        Param("evict", 8, "frames a cell may stay unused before it is freed", lo=0),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self._table = light_table(scene.mi_scene)
        self._stats, self._pixels, self._poses = {}, 0, None
        self.reset()

    def validate(self):
        if self.taps == 0 and self.defensive < 1.0:
            raise MethodError("regir: taps=0 needs defensive=1 (the table samples then cover every light)")

    def reset(self):
        self.grid = HashGrid(self.cells, self.cell)
        self.store = dr.zeros(Slots, self.grid.capacity * self.slots)
        self.rep_p = dr.zeros(mi.Point3f, self.grid.capacity)       # representative point per cell
        self.rep_n = dr.zeros(mi.Vector3f, self.grid.capacity)      # and its normal
        self._poses, self._stats = None, {}

    # ------------------------------------------------------------------ frame

    def update_frame(self, ctx, gbuffers, timer) -> "Cells":
        frame = dr.opaque(mi.UInt32, ctx.frame)
        history = self.temporal and not self._lights_moved()
        with timer.stage("cells") as st:
            cell = self.find_cells(ctx, gbuffers, frame)
            st.outputs(*cell)
        with timer.stage("build") as st:
            built = self.build_cells(ctx, frame, history)
            st.outputs(self.store)
        return Cells(slot=cell, built=built)

    def finish(self, ctx, fr: "Cells", gbuffers, outs, timer):
        self._pixels = sum(gb.size for gb in gbuffers)
        self._stats = {"cells_built": float(fr.built), "cell_load": self.grid.load(),
                       "cell_overflow": float(self.grid.overflow)}
        return outs

    def _lights_moved(self) -> bool:
        """Whether a light's shape moved since the last frame (dynamic scenes only)."""
        if not self.scene.dynamic:
            return False
        poses = [np.array([*e.get_shape().bbox().min, *e.get_shape().bbox().max], float)
                 for e in self.scene.mi_scene.emitters() if e.get_shape() is not None]
        moved = self._poses is not None and any(not np.allclose(a, b, rtol=0, atol=1e-6)
                                                for a, b in zip(poses, self._poses))
        self._poses = poses
        return moved

    # ------------------------------------------------------------------ cells

    def find_cells(self, ctx, gbuffers, frame) -> list:
        """Per viewer, the slot of each pixel's jittered cell (``INVALID``: no cell); all
        viewers' pixels are placed in the table at once."""
        self.grid.evict(frame, self.evict)
        sizes = [gb.size for gb in gbuffers]
        offsets = [sum(sizes[:v]) for v in range(len(sizes))]
        total = sum(sizes)
        keys, valid = dr.empty(mi.UInt64, total), dr.empty(mi.Bool, total)
        pts, nrm = dr.empty(mi.Point3f, total), dr.empty(mi.Vector3f, total)
        for v, (gb, off) in enumerate(zip(gbuffers, offsets)):
            smp = rng(gb.size, self.seed_for(ctx.frame, v), stream=2)
            jit = mi.Vector3f(smp.next_float32(), smp.next_float32(), smp.next_float32()) - 0.5
            p = gb.si.p + jit * (self.jitter * self.cell)
            at = dr.arange(mi.UInt32, gb.size) + dr.opaque(mi.UInt32, off)
            dr.scatter(keys, cell_key(p, gb.si.sh_frame.n, self.cell), at)
            dr.scatter(valid, mi.Bool(gb.valid), at)
            dr.scatter(pts, gb.si.p, at)
            dr.scatter(nrm, mi.Vector3f(gb.si.n), at)
        slot, new = self.grid.insert(keys, valid, frame)

        # ---------------- a new cell's representative: its lowest lane ----------------
        lane = dr.arange(mi.UInt32, total)
        first = dr.full(mi.UInt32, INVALID, self.grid.capacity)
        dr.scatter_reduce(dr.ReduceOp.Min, first, lane, slot, new)
        win = new & (dr.gather(mi.UInt32, first, slot, new) == lane)
        dr.scatter(self.rep_p, pts, slot, win)
        dr.scatter(self.rep_n, nrm, slot, win)
        dr.eval(self.rep_p, self.rep_n)
        return per_viewer(slot, sizes, offsets) if len(gbuffers) > 1 else [slot]

    # ------------------------------------------------------------------ build

    def build_cells(self, ctx, frame, history: bool) -> int:
        """RIS of every reservoir of the cells used this frame; returns the number of cells."""
        cells = self.grid.touched(frame)
        n_cells = dr.width(cells)
        if n_cells == 0 or self._table is None:
            return n_cells
        S = self.slots
        lane = dr.arange(mi.UInt32, n_cells * S)
        cell = dr.gather(mi.UInt32, cells, lane // S)
        j = lane % S
        key = dr.gather(mi.UInt64, self.grid.keys, cell)
        c = dr.gather(mi.Point3f, self.rep_p, cell)
        cn = dr.gather(mi.Vector3f, self.rep_n, cell)
        h1 = key_hash(key)[1]
        smp = mixed_rng(mi.sample_tea_32(h1, j, 4)[0], stream_key(self.seed, ctx.frame, STREAM_BUILD))
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p, si.n = c, cn
        active = dr.full(mi.Bool, True, n_cells * S)
        floor = dr.opaque(mi.Float, self.cosine)

        # ---------------- B candidates from the emitter table at the cell centre ----------------
        def body(st: BuildLoop):
            smp = st.smp
            u = mi.Point2f(smp.next_float32(), smp.next_float32())
            ds, w, ok, em = self._table.sample(si, u, active)
            kind = self._table.kind(em, ok)
            ok &= (kind == et.MESH) | (kind == et.RECT) | (kind == et.SPHERE) | (kind == et.POINT)
            point = ok & (kind == et.POINT)
            Le_c = w * ds.pdf * dr.select(point, dr.square(ds.dist), 1.0)     # radiance, or intensity
            nc = dr.select(point, 0.0, mi.Vector3f(ds.n))
            p_hat = cell_target(c, cn, ds.p, nc, Le_c, floor, ok)
            p_hat = self._shadowed(si, ds.p, p_hat)
            wi = mi.luminance(w)                                # p_hat / p: the same ratio in any measure
            wi = dr.select(ok & (p_hat > 0.0) & (wi > 0.0) & dr.isfinite(wi), wi, 0.0)
            st.w_sum += wi
            take = (wi > 0.0) & (smp.next_float32() * st.w_sum < wi)
            st.y = dr.select(take, ds.p, st.y)
            st.n = dr.select(take, nc, st.n)
            st.Le = dr.select(take, Le_c, st.Le)
            st.p_sel = dr.select(take, p_hat, st.p_sel)
            st.i = st.i + 1
            return (st,)

        n_build = dr.opaque(mi.UInt32, self.build)
        state = BuildLoop(mi.UInt32(0), mi.Point3f(0.0), mi.Vector3f(0.0), mi.Color3f(0.0), mi.Float(0.0),
                          mi.Float(0.0), smp)
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
            st, = dr.while_loop(state=(state,), cond=lambda st: st.i < n_build, body=body, labels=("build",))
        y, n, Le, p_sel, w_sum, smp = st.y, st.n, st.Le, st.p_sel, st.w_sum, st.smp
        ok = (p_sel > 0.0) & (w_sum > 0.0)
        W = dr.select(ok, w_sum / dr.select(ok, float(self.build) * p_sel, 1.0), 0.0)
        M = mi.Float(1.0)
        at = cell * S + j

        # ---------------- temporal merge with the slot's previous reservoir ----------------
        if history:
            old = dr.gather(Slots, self.store, at)
            # M counts the frames merged, whatever the samples were (an empty reservoir included), so
            # that the weights M_i / sum M do not depend on the samples they weigh
            alive = dr.gather(mi.UInt32, self.grid.born, cell) != frame
            M_old = dr.select(alive, dr.minimum(old.M, dr.opaque(mi.Float, self.mcap)), 0.0)
            use = alive & (old.W > 0.0)
            p_old = self._shadowed(si, old.y, cell_target(c, cn, old.y, old.n, old.Le, floor, use))
            inv = dr.rcp(1.0 + M_old)
            w_new = dr.select(ok, p_sel * W * inv, 0.0)
            w_old = dr.select(use & (p_old > 0.0), p_old * old.W * M_old * inv, 0.0)
            total = w_new + w_old
            take = (w_old > 0.0) & (smp.next_float32() * total < w_old)
            y, n, Le = dr.select(take, old.y, y), dr.select(take, old.n, n), dr.select(take, old.Le, Le)
            p_sel = dr.select(take, p_old, p_sel)
            ok = (p_sel > 0.0) & (total > 0.0)
            W = dr.select(ok, total / dr.select(ok, p_sel, 1.0), 0.0)
            M = 1.0 + M_old
        dr.scatter(self.store, Slots(y, n, Le, W, M), at)
        return n_cells

    def _pixel_sample(self, si, u, active):
        """A light sample at the pixel: (DirectionSample3f, L_e / p, mask, local light of the
        table, point light); the scene's own sampling where no emitter is in the table (the grid
        is then empty and every sample comes from here)."""
        if self._table is None:
            ds, w, ok = sample_light_reference(self.scene.mi_scene, si, u, active)
            return ds, w, ok, mi.Bool(False), mi.Bool(False)
        ds, w, ok, em = self._table.sample(si, u, active)
        kind = self._table.kind(em, ok)
        local = (kind == et.MESH) | (kind == et.RECT) | (kind == et.SPHERE) | (kind == et.POINT)
        return ds, w, ok, local, kind == et.POINT

    def _shadowed(self, si, y, p_hat):
        """The build target times ``occluded`` where the segment from the cell's representative
        point to ``y`` is blocked (one shadow ray per candidate; none with ``occluded=1``)."""
        if self.occluded >= 1.0:
            return p_hat
        test = p_hat > 0.0
        blocked = self.scene.mi_scene.ray_test(si.spawn_ray_to(y), test)
        return dr.select(test & blocked, p_hat * dr.opaque(mi.Float, self.occluded), p_hat)

    # ------------------------------------------------------------------ shading

    def shade(self, ctx, fr: "Cells", v: int, gb) -> mi.Color3f:
        """One viewer's direct light: ``samples`` times a resampling of slot taps and table
        samples with one shadow ray, averaged."""
        slot, frame = fr.slot[v], ctx.frame
        sc = self.scene.mi_scene
        si, active = gb.si, mi.Bool(gb.valid)
        bsdf = SurfaceBSDF(sc, si, active, mi.BSDFContext())
        has_cell = active & (slot != INVALID)
        c = dr.gather(mi.Point3f, self.rep_p, slot, has_cell)
        cn = dr.gather(mi.Vector3f, self.rep_n, slot, has_cell)
        alpha = self.defensive if self.taps > 0 else 1.0
        m_tap = dr.opaque(mi.Float, (1.0 - alpha) / max(self.taps, 1))
        S = dr.opaque(mi.UInt32, self.slots)
        Sf = dr.opaque(mi.Float, float(self.slots))
        n_taps = dr.opaque(mi.UInt32, self.taps)
        inv_b = 1.0 / self.table
        floor = dr.opaque(mi.Float, self.cosine)

        # ---------------- slot taps of the pixel's cell ----------------
        def tap(st: TapLoop):
            smp = st.smp
            j = dr.minimum(mi.UInt32(smp.next_float32() * Sf), S - 1)
            s = dr.gather(Slots, self.store, slot * S + j, has_cell)
            t, d, ok = light_term(si.p, s.y, s.n, s.Le, has_cell & (s.W > 0.0))
            col = bsdf.eval(si.to_local(d), ok) * t
            p_hat = mi.luminance(col)
            w = dr.select(ok & (p_hat > 0.0), m_tap * p_hat * s.W, 0.0)
            w = dr.select(dr.isfinite(w), w, 0.0)
            st.w_sum += w
            take = (w > 0.0) & (smp.next_float32() * st.w_sum < w)
            st.y_sel = dr.select(take, s.y, st.y_sel)
            st.r_sel = dr.select(take, col / dr.select(take, p_hat, 1.0), st.r_sel)
            st.i = st.i + 1
            return (st,)

        def sample(k, L, smp):
            state = TapLoop(mi.UInt32(0), mi.Point3f(0.0), mi.Color3f(0.0), mi.Float(0.0), smp)
            st, = dr.while_loop(state=(state,), cond=lambda st: st.i < n_taps, body=tap, labels=("taps",))
            y_sel, r_sel, w_sum, smp = st.y_sel, st.r_sel, st.w_sum, st.smp

            # ---------------- emitter-table samples at the pixel ----------------
            for _ in range(self.table):
                u = mi.Point2f(smp.next_float32(), smp.next_float32())
                ds, w, ok, local, point = self._pixel_sample(si, u, active)
                Le = w * ds.pdf * dr.select(point, dr.square(ds.dist), 1.0)
                covered = cell_target(c, cn, ds.p, dr.select(point, 0.0, mi.Vector3f(ds.n)), Le, floor,
                                      ok & local & has_cell) > 0.0
                m = dr.select(covered, alpha * inv_b, inv_b)
                col = bsdf.eval(si.to_local(ds.d), ok) * w          # f L_e / p: p_hat / p in colour
                p_ratio = mi.luminance(col)
                wb = dr.select(ok & (p_ratio > 0.0) & dr.isfinite(p_ratio), m * p_ratio, 0.0)
                w_sum += wb
                take = (wb > 0.0) & (smp.next_float32() * w_sum < wb)
                y_sel = dr.select(take, ds.p, y_sel)
                r_sel = dr.select(take, col / dr.select(take, p_ratio, 1.0), r_sel)

            # ---------------- one shadow ray to the chosen sample ----------------
            hit = active & (w_sum > 0.0)
            hit &= ~sc.ray_test(si.spawn_ray_to(y_sel), hit)
            return k + 1, L + dr.select(hit, r_sel * w_sum, 0.0), smp

        smp = rng(gb.size, self.seed_for(frame, v), stream=3)
        n_samples = dr.opaque(mi.UInt32, self.samples)
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
            _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), smp), cond=lambda k, *_: k < n_samples,
                                    body=sample, labels=("k", "L", "smp"))
        return L / float(self.samples)

    # ------------------------------------------------------------------ state

    def memory_bytes(self) -> int:
        return (self.grid.memory_bytes() + (REP_BYTES + SLOT_BYTES * self.slots) * self.grid.capacity
                + 4 * self._pixels)

    def stats(self) -> dict:
        return dict(self._stats)


register("regir", ReGIR, help="ReGIR: a world-space hash grid of light reservoirs shared by all viewers "
                              "(cell 2 m, 128 reservoirs per cell, 8 build candidates, jitter 1 cell, "
                              "temporal merge, 8 samples of 8 taps per pixel)")
