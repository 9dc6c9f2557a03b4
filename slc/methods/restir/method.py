"""ReSTIR DI (RTXDI-style), per viewer: reservoir-based spatiotemporal
importance resampling of direct lighting [Bitterli et al. 2020].

Why one long module: the four stages (initial candidates, temporal and spatial reuse, shading)
share the reservoir type, the target function and the per-viewer state; kept together so that
the estimator reads top to bottom as in the paper.

One reservoir per pixel and viewer. Per frame: resampled importance sampling
of initial candidates (local lights, environment, BSDF), temporal reuse from
the previous frame's reservoirs through the motion vectors, spatial reuse
from neighbouring pixels, and final shading with one shadow ray.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.lights import rng, sampler as light_table
from slc.methods import Method, MethodError, Param, register
from slc.methods.restir.pairwise import spatial_pairwise
from slc.methods.restir.reservoir import Reservoir, Stream, share

# Emitter kinds (the measure in which a stored sample lives)
AREA, DELTA_POS, INFINITE = 0, 1, 2

# Neighbours per pixel are recorded in a 32-bit mask between the two spatial passes
MAX_NEIGHBOURS = 32

# Bytes of one reservoir: y (12), n (12), light index (4), W (4), M (4)
RESERVOIR_BYTES = 36
# Previous-frame surface kept for temporal reuse: position (12), normal (12), depth (4)
PREV_SURFACE_BYTES = 28

PRESETS = {
    "rtxdi": dict(local=8, env=1, bsdf=1),
    "falcor": dict(local=24, env=8, bsdf=1),
}


class ReSTIR(Method):
    r"""ReSTIR DI with temporal and spatial reuse, one set of reservoirs per viewer.

    Estimator (per pixel x, one sample y selected by resampling):

    .. math:: L_o(x) \approx f_r(x, y)\,L_e(y)\,G(x, y)\,V(x, y)\; W,
              \qquad W = \frac{1}{\hat p_x(y)}\,\frac{1}{Z}\sum_i w_i

    with the unshadowed target :math:`\hat p_x(y) = \mathrm{lum}(f_r L_e G)`
    (``G = |cos_y| / d^2`` for area lights, 1 for point lights, whose
    ``L_e`` already holds ``I / d^2``, and for infinite lights).

    Stages (timed as ``initial``, ``temporal``, ``spatial``, ``shade``):

    1. *initial*: RIS over ``local`` local-light candidates (from the
       scene's emitter table over the local lights, :mod:`slc.scene.emitter_sampling`:
       light choice and density from the table; with
       ``SLC_EMITTER_SAMPLING=mitsuba`` a uniform light choice and Mitsuba's
       ``sample_direction`` per light), ``env`` candidates
       of the infinite lights and ``bsdf`` BSDF-sampled rays; resampling
       weights are balance-heuristic MIS weights over the three techniques,
       :math:`w = \hat p(y) / \sum_t N_t p_t(y)`, all densities in the
       sample's own measure (area for area lights, solid angle for
       infinite lights, discrete for point lights). M = 1. With
       ``visibility=1`` the chosen sample's shadow ray zeroes W (RTXDI's
       initial visibility).
    2. *temporal* (``temporal=1``): the previous frame's final reservoir at
       the pixel ``round(x + motion)`` is merged, its M capped at
       ``mcap``; rejected when out of screen, invalid, the relative depth
       difference exceeds ``depth`` or the normals' dot is below ``normal``.
       History samples on area lights that moved since the last frame are
       discarded (no stale samples).
    3. *spatial* (``spatial`` neighbours, 0 disables): neighbours uniform
       in a disk of ``radius`` pixels at 1080p, scaled by height/1080 (at
       least 2 px), same depth/normal tests; pixels whose temporal reuse
       failed take ``max(spatial, boost)`` neighbours (RTXDI's disocclusion
       boost). Two symbolic loops over the per-pixel count (at most 32)
       with the neighbours recorded in a bit mask (as RTXDI).
    4. *shade*: one shadow ray to the final sample.

    Reuse weights ``bias``: ``pairwise`` (default; pairwise MIS, M-weighted,
    see :func:`slc.methods.restir.pairwise.spatial_pairwise`; in the temporal pass the balance
    heuristic of the two reservoirs), ``basic`` (1/Z with Z = sum of the M
    of reservoirs whose surface has :math:`\hat p(y) > 0`, Bitterli et
    al.'s weights, no visibility) or ``off`` (Z = sum of M, biased where
    neighbours differ). ``pairwise`` and ``basic`` are unbiased for the
    unshadowed target; ``basic`` weighs a neighbour's sample by
    :math:`\hat p_c(y) W M`, which grows without bound where the current
    target exceeds the neighbour's (glossy lobes, small bright lights: bright
    blotches), pairwise MIS does not. Ray-traced bias correction is not
    implemented (a shadow-ray test in Z is inconsistent with the unshadowed
    target, see ``docs/restir.md``).

    The defaults are RTXDI's library defaults (``spatial=5`` is the other
    usual setting) except the reuse weights; ``preset=falcor`` sets 24
    local / 8 environment / 1 BSDF candidates.

    Memory: per viewer and pixel two reservoir buffers (history and
    working, 36 bytes each) and the previous surface (28 bytes):
    :meth:`memory_bytes` = 100 B x pixels x viewers. State is keyed by viewer
    index; a change of resolution or viewer count reallocates it.
    Limitations: textured area-light radiance is evaluated at uv = 0;
    point/spot lights are assumed not to move (they cannot in
    :class:`~slc.scene.builder.SceneBuilder` scenes).
    """

    name = "restir"
    params = (
        Param("local", 8, "RIS candidates from local (area and point) lights", lo=0),
        Param("env", 1, "RIS candidates from the environment", lo=0),
        Param("bsdf", 1, "RIS candidates by BSDF sampling", lo=0),
        Param("preset", None, "candidate counts of a preset (overrides local/env/bsdf)",
              choices=tuple(PRESETS), kind=str),
        Param("temporal", 1, "temporal reuse on/off", lo=0, hi=1),
        Param("mcap", 20.0, "temporal M cap", lo=0.0),
        Param("depth", 0.1, "relative depth threshold of reuse", lo=0.0),
        Param("normal", 0.5, "normal threshold of reuse (cosine)", lo=-1.0, hi=1.0),
        Param("spatial", 1, "spatial neighbours", lo=0, hi=MAX_NEIGHBOURS),
        Param("radius", 32.0, "spatial radius in pixels at 1080p (scaled)", lo=0.0),
        Param("boost", 8, "spatial neighbours where history was rejected", lo=0, hi=MAX_NEIGHBOURS),
        Param("bias", "pairwise", "reuse weights: pairwise (pairwise MIS), basic (1/Z over the reservoirs "
              "whose target is non-zero) or off (1/sum M, biased); ray-traced is not implemented",
              choices=("off", "basic", "pairwise")),
        Param("visibility", 1, "final visibility ray on/off", lo=0, hi=1),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        if self.preset is not None:
            self.local, self.env, self.bsdf = (PRESETS[self.preset][k] for k in ("local", "env", "bsdf"))
        self.n_local, self.n_env, self.n_bsdf = self.local, self.env, self.bsdf
        self.depth_thr, self.normal_thr = self.depth, self.normal
        self._setup_lights()
        self.reset()

    def validate(self):
        if self.preset is None and self.local + self.env + self.bsdf == 0:
            raise MethodError("restir: at least one candidate is needed (local + env + bsdf > 0)")

    # ------------------------------ Set-up ------------------------------

    def _setup_lights(self):
        sc = self.scene.mi_scene
        ems = sc.emitters()
        self._emitters = sc.emitters_dr()
        kinds, delta, local, inf = [], [], [], []
        for i, e in enumerate(ems):
            fl = int(e.flags())
            if fl & int(mi.EmitterFlags.Infinite):
                kinds.append(INFINITE)
                inf.append(i)
            elif fl & int(mi.EmitterFlags.DeltaPosition):
                kinds.append(DELTA_POS)
                local.append(i)
            else:
                kinds.append(AREA)
                local.append(i)
            delta.append(bool(fl & (int(mi.EmitterFlags.DeltaPosition) | int(mi.EmitterFlags.DeltaDirection))))
        env = sc.environment()
        self._env_index = next((i for i, e in enumerate(ems) if env is not None and e is env), -1)
        self._kind = mi.UInt32(kinds)
        self._delta = mi.Bool(delta)
        self._local = mi.UInt32(local or [0])
        self._inf = mi.UInt32(inf or [0])
        self._L, self._E = len(local), len(inf)
        # registry id of an EmitterPtr -> index in scene.emitters()
        ids = np.array(dr.reinterpret_array(mi.UInt32, self._emitters), dtype=np.int64)
        table = np.zeros(int(ids.max()) + 1 if len(ids) else 1, dtype=np.uint32)
        table[ids] = np.arange(len(ids), dtype=np.uint32)
        self._id_to_index = mi.UInt32(table)
        self._shaped = [(i, e.get_shape()) for i, e in enumerate(ems) if kinds[i] == AREA and e.get_shape()]
        # local-light candidates from the shared emitter table (None: Mitsuba, uniform choice)
        self._table = light_table(sc, subset=local) if local else None
        self._bboxes = None

    def reset(self):
        self.state: dict[int, tuple] = {}   # viewer -> (Reservoir, previous GBuffer)
        self._shape = None                  # (width, height, viewers) of the allocation
        self._bboxes = None
        self._stats = {}

    def _light_moved(self) -> mi.Bool:
        """Per emitter: its shape moved since the previous frame."""
        n = len(self.scene.mi_scene.emitters())
        moved = np.zeros(max(n, 1), dtype=bool)
        if self.scene.dynamic:
            cur = {}
            for i, s in self._shaped:
                b = s.bbox()
                cur[i] = np.array([*b.min, *b.max], float)
            if self._bboxes is not None:
                for i, b in cur.items():
                    moved[i] = not np.allclose(b, self._bboxes.get(i, b), rtol=0, atol=1e-6)
            self._bboxes = cur
        return mi.Bool(moved)

    # --------------------------- Target function ---------------------------

    def _direction(self, si, y, light, active):
        """Unit direction from ``si`` to a stored sample, its distance (inf
        for infinite lights) and the emitter kind."""
        kind = dr.gather(mi.UInt32, self._kind, light, active)
        inf = kind == INFINITE
        to = mi.Vector3f(y) - si.p
        dist = dr.norm(to)
        d = dr.select(inf, mi.Vector3f(y), to / dr.select(dist > 0.0, dist, 1.0))
        return d, dist, kind

    def evaluate(self, si, bsdf, y, n, light, active, with_pdf: bool = False):
        """Unshadowed contribution f_r L_e G of stored samples at ``si``:
        (colour, p_hat = luminance, world direction, distance, kind,
        DirectionSample3f), plus the BSDF's solid-angle pdf of the direction
        when ``with_pdf`` (one ``eval_pdf`` call instead of two)."""
        ctx = mi.BSDFContext()
        d, dist, kind = self._direction(si, y, light, active)
        em = dr.gather(mi.EmitterPtr, self._emitters, light, active)
        inf = kind == INFINITE
        ok = active & (inf | (dist > 0.0))
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p = dr.select(inf, si.p + d, mi.Point3f(y))
        ds.n = mi.Normal3f(n)
        ds.d = d
        ds.dist = dr.select(inf, dr.inf, dist)
        ds.emitter = em
        ds.delta = dr.gather(mi.Bool, self._delta, light, active)
        Le = mi.Color3f(em.eval_direction(si, ds, ok))
        if self._E:
            # Mitsuba's envmap reads eval_direction's texel from ds.uv (set by its own
            # sampler), not from ds.d: a stored direction is looked up with eval(), wi = -d
            env = ok & inf & ~ds.delta
            se = dr.zeros(mi.SurfaceInteraction3f, dr.width(d))
            se.wi = -d
            se.wavelengths = si.wavelengths
            Le = dr.select(env, mi.Color3f(em.eval(se, env)), Le)
        G = dr.select(kind == AREA, dr.abs(dr.dot(mi.Vector3f(n), d)) / dr.select(ok & ~inf, dr.square(dist), 1.0), 1.0)
        if with_pdf:
            f, p_bsdf = bsdf.eval_pdf(ctx, si, si.to_local(d), ok)
        else:
            f, p_bsdf = bsdf.eval(ctx, si, si.to_local(d), ok), None
        c = dr.select(ok, mi.Color3f(f) * Le * G, 0.0)
        p_hat = dr.maximum(mi.luminance(c), 0.0)
        if with_pdf:
            return c, p_hat, d, dist, kind, ds, dr.select(ok, p_bsdf, 0.0)
        return c, p_hat, d, dist, kind, ds

    def _visible(self, si, d, dist, kind, active):
        """Shadow ray towards a stored sample (to the point, or to infinity)."""
        inf = kind == INFINITE
        ray = si.spawn_ray(d)
        ray_to = si.spawn_ray_to(si.p + d * dist)
        ray.maxt = dr.select(inf, ray.maxt, ray_to.maxt)
        ray.o = dr.select(inf, ray.o, ray_to.o)
        ray.d = dr.select(inf, ray.d, ray_to.d)
        return active & ~self.scene.mi_scene.ray_test(ray, active)

    def _pdf_sum(self, si, bsdf, light, kind, d, dist, n, ds, active, p_dir=None, p_bsdf=None):
        """sum_t N_t p_t(y): candidate densities of the three techniques in the
        sample's measure (area / solid angle / discrete). ``p_dir`` (the
        light's solid-angle pdf, e.g. ``ds.pdf`` of the sampling call) and
        ``p_bsdf`` (from ``eval_pdf``) are computed here when not given."""
        ctx = mi.BSDFContext()
        em = ds.emitter
        delta = ds.delta
        cos_y = dr.abs(dr.dot(mi.Vector3f(n), d))
        to_area = dr.select(kind == AREA, cos_y / dr.select(dist > 0.0, dr.square(dist), 1.0), 1.0)
        if p_dir is None:
            need = active & ~delta
            if self._table is not None:   # only the infinite lights still need Mitsuba's density
                need &= kind == INFINITE
            p_dir = em.pdf_direction(si, ds, need)
        p_dir = dr.select(delta, 0.0, p_dir)
        total = dr.zeros(mi.Float, dr.width(light))
        if self._L and self.n_local:
            if self._table is not None:
                loc = active & (kind != INFINITE)
                p_l = dr.select(delta, self._table.choice_pmf(light, loc),
                                self._table.pdf(si, ds, loc & ~delta, index=light) * to_area)
            else:
                p_l = dr.select(delta, 1.0, p_dir * to_area) / self._L
            total += dr.select(kind != INFINITE, float(self.n_local) * p_l, 0.0)
        if self._E and self.n_env:
            p_e = dr.select(delta, 1.0, p_dir) / self._E
            total += dr.select(kind == INFINITE, float(self.n_env) * p_e, 0.0)
        if self.n_bsdf:
            if p_bsdf is None:
                p_bsdf = bsdf.pdf(ctx, si, si.to_local(d), active & ~delta)
            p_b = p_bsdf * to_area
            hit_able = ~delta & (kind == AREA)
            if self._env_index >= 0:
                hit_able |= ~delta & (light == self._env_index)
            total += dr.select(hit_able, float(self.n_bsdf) * p_b, 0.0)
        return dr.select(active, total, 0.0)

    # ------------------------------ Stage 1: initial ------------------------------

    def initial(self, gb, seed: int) -> tuple[Reservoir, mi.Float]:
        sc = self.scene.mi_scene
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        ctx = mi.BSDFContext()
        sampler = rng(n, seed, stream=11)
        res = Stream(n)
        if self._table is not None:
            self._table.refresh()   # animated emissive meshes

        def add(y, nrm, light, ok, u_sel, p_dir=None):
            _, p_hat, d, dist, kind, ds, p_bsdf = self.evaluate(si, bsdf, y, nrm, light, ok, with_pdf=True)
            denom = self._pdf_sum(si, bsdf, light, kind, d, dist, nrm, ds, ok & (p_hat > 0.0),
                                  p_dir=p_dir, p_bsdf=p_bsdf)
            good = ok & (p_hat > 0.0) & (denom > 0.0)
            w = dr.select(good, p_hat / dr.select(good, denom, 1.0), 0.0)
            res.update(y, nrm, light, p_hat, w, u_sel, good)

        # ---------------- Local-light candidates (symbolic loop) ----------------
        if self._L and self.n_local:
            n_local = dr.opaque(mi.UInt32, self.n_local)
            state = (mi.UInt32(0), res.y, res.n, res.light, res.p_hat, res.w_sum, sampler)

            def cond(i, *_):
                return i < n_local

            def body(i, y_, n_, l_, p_, w_, smp):
                res.y, res.n, res.light, res.p_hat, res.w_sum = y_, n_, l_, p_, w_
                if self._table is not None:
                    u = mi.Point2f(smp.next_float32(), smp.next_float32())
                    ds, _, ok, light = self._table.sample(si, u, active)
                    add(mi.Point3f(ds.p), mi.Vector3f(ds.n), light, ok, smp.next_float32())
                    return i + 1, res.y, res.n, res.light, res.p_hat, res.w_sum, smp
                k = dr.minimum(mi.UInt32(smp.next_float32() * self._L), self._L - 1)
                light = dr.gather(mi.UInt32, self._local, k, active)
                em = dr.gather(mi.EmitterPtr, self._emitters, light, active)
                u = mi.Point2f(smp.next_float32(), smp.next_float32())
                ds, _ = em.sample_direction(si, u, active)
                ok = active & (ds.pdf > 0.0)
                add(mi.Point3f(ds.p), mi.Vector3f(ds.n), light, ok, smp.next_float32(), p_dir=ds.pdf)
                return i + 1, res.y, res.n, res.light, res.p_hat, res.w_sum, smp

            out = dr.while_loop(state=state, cond=cond, body=body,
                                labels=("i", "y", "n", "light", "p_hat", "w_sum", "sampler"))
            _, res.y, res.n, res.light, res.p_hat, res.w_sum, sampler = out

        # ---------------- Environment candidates ----------------
        if self._E and self.n_env:
            for _ in range(self.n_env):
                k = dr.minimum(mi.UInt32(sampler.next_float32() * self._E), self._E - 1)
                light = dr.gather(mi.UInt32, self._inf, k, active)
                em = dr.gather(mi.EmitterPtr, self._emitters, light, active)
                u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
                ds, _ = em.sample_direction(si, u, active)
                ok = active & (ds.pdf > 0.0)
                add(mi.Point3f(ds.d), dr.zeros(mi.Vector3f, n), light, ok, sampler.next_float32(), p_dir=ds.pdf)

        # ---------------- BSDF candidates ----------------
        for _ in range(self.n_bsdf):
            u1 = sampler.next_float32()
            u2 = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            bs, _ = bsdf.sample(ctx, si, u1, u2, active)
            ok = active & (bs.pdf > 0.0)
            wo = si.to_world(bs.wo)
            # position, geometric normal and shape suffice (no UVs, partials, shading frame)
            si2 = sc.ray_intersect(si.spawn_ray(wo), ray_flags=mi.RayFlags.Minimal, coherent=False, active=ok)
            hit = ok & si2.is_valid()
            em = si2.emitter(sc, hit)
            hit_em = hit & (em != None)  # noqa: E711 (EmitterPtr comparison)
            rid = dr.reinterpret_array(mi.UInt32, em)
            light = dr.gather(mi.UInt32, self._id_to_index, rid, hit_em)
            y = dr.select(hit_em, si2.p, mi.Point3f(wo))
            nrm = dr.select(hit_em, mi.Vector3f(si2.n), 0.0)
            if self._env_index >= 0:
                miss = ok & ~si2.is_valid()
                light = dr.select(miss, self._env_index, light)
                cand = hit_em | miss
            else:
                cand = hit_em
            add(y, nrm, light, cand, sampler.next_float32())

        # ---------------- Finalize (M = 1) and initial visibility ----------------
        r = res.finalize(mi.Float(1.0), mi.Float(1.0), active)
        if self.visibility:
            d, dist, kind = self._direction(si, r.y, r.light, active & (r.W > 0.0))
            vis = self._visible(si, d, dist, kind, active & (r.W > 0.0))
            r.W = dr.select(vis, r.W, 0.0)
        return r, res.p_hat

    # ------------------------------ Stage 2: temporal ------------------------------

    def _similar(self, n_a, n_b, depth_a, depth_b):
        """RTXDI's neighbour test: relative depth and normal thresholds."""
        depth_ok = dr.abs(depth_b - depth_a) <= self.depth_thr * dr.maximum(depth_a, 1e-6)
        return depth_ok & (dr.dot(n_a, n_b) >= self.normal_thr)

    def temporal_reuse(self, gb, r: Reservoir, p_cur, prev, moved, seed: int):
        """Merge the previous frame's reservoir; returns (reservoir, reused mask)."""
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        if prev is None:
            return r, dr.zeros(mi.Bool, n), p_cur
        r_prev_all, gb_prev = prev
        W_, H_ = gb.width, gb.height
        sampler = rng(n, seed, stream=12)

        # ---------------- Reprojection (nearest pixel) ----------------
        idx = dr.arange(mi.UInt32, n)
        px = mi.Float(idx % W_) + 0.5 + gb.motion.x
        py = mi.Float(idx // W_) + 0.5 + gb.motion.y
        qx, qy = mi.Int32(dr.floor(px)), mi.Int32(dr.floor(py))
        inb = (qx >= 0) & (qy >= 0) & (qx < W_) & (qy < H_)
        q = mi.UInt32(dr.select(inb, qy * W_ + qx, 0))
        ok = active & inb & dr.gather(mi.Bool, gb_prev.valid, q, active & inb)
        si_p = dr.gather(mi.SurfaceInteraction3f, gb_prev.si, q, ok)
        cam_o = mi.Point3f(*[dr.opaque(mi.Float, float(c)) for c in gb_prev.camera.origin])
        expected = dr.norm(si.p - cam_o)
        ok &= self._similar(si.sh_frame.n, si_p.sh_frame.n, expected, dr.gather(mi.Float, gb_prev.depth, q, ok))
        rp = dr.gather(Reservoir, r_prev_all, q, ok)
        ok &= ~(dr.gather(mi.Bool, moved, rp.light, ok) & (dr.gather(mi.UInt32, self._kind, rp.light, ok) == AREA))
        ok &= rp.M > 0.0
        M_p = dr.select(ok, dr.minimum(rp.M, self.mcap), 0.0)

        # ---------------- Resampling: current + history ----------------
        st = Stream(n)
        M = r.M + M_p
        _, p_here, _, _, _, _ = self.evaluate(si, bsdf, rp.y, rp.n, rp.light, ok & (rp.W > 0.0))
        if self.bias == "pairwise":
            # balance heuristic over the two reservoirs' targets, weighted by their M:
            # m_c(y) = M_c p_c(y) / (M_c p_c(y) + M_p p_p(y)), m_p(y) = 1 - m_c(y)
            bsdf_p = si_p.bsdf()
            _, p_pp, _, _, _, _ = self.evaluate(si_p, bsdf_p, rp.y, rp.n, rp.light, ok & (rp.W > 0.0))
            _, p_pc, _, _, _, _ = self.evaluate(si_p, bsdf_p, r.y, r.n, r.light, ok & (r.W > 0.0))
            m_c = share(r.M * p_cur, dr.select(ok, M_p * p_pc, 0.0))
            m_p = share(M_p * p_pp, r.M * p_here)
            st.update(r.y, r.n, r.light, p_cur, m_c * p_cur * r.W, sampler.next_float32(), active)
            st.update(rp.y, rp.n, rp.light, p_here, m_p * p_here * rp.W, sampler.next_float32(), ok)
            return st.finalize(mi.Float(1.0), M, active), ok, st.p_hat
        st.update(r.y, r.n, r.light, p_cur, p_cur * r.W * r.M, sampler.next_float32(), active)
        st.update(rp.y, rp.n, rp.light, p_here, p_here * rp.W * M_p, sampler.next_float32(), ok)

        # ---------------- Bias correction ----------------
        if self.bias == "off":
            Z = M
        else:
            Z = dr.select(st.p_hat > 0.0, r.M, 0.0)
            bsdf_p = si_p.bsdf()
            # only where a sample was selected (W = 0 otherwise, whatever Z)
            sel = ok & (st.p_hat > 0.0) & (st.w_sum > 0.0)
            _, p_prev, _, _, _, _ = self.evaluate(si_p, bsdf_p, st.y, st.n, st.light, sel)
            Z += dr.select(sel & (p_prev > 0.0), M_p, 0.0)
        return st.finalize(Z, M, active), ok, st.p_hat

    # ------------------------------ Stage 3: spatial ------------------------------

    def neighbour(self, smp, x0, y0, R: float, W_: int, H_: int):
        """Next neighbour of the sequence ``smp``: a pixel uniform in the disk
        of radius ``R`` around (x0, y0), rounded; (index, in-bounds mask).
        The pixel itself does not count as a neighbour."""
        u1, u2 = smp.next_float32(), smp.next_float32()
        rad = R * dr.sqrt(u1)
        phi = 2.0 * math.pi * u2
        qx = x0 + mi.Int32(dr.round(rad * dr.cos(phi)))
        qy = y0 + mi.Int32(dr.round(rad * dr.sin(phi)))
        inb = (qx >= 0) & (qy >= 0) & (qx < W_) & (qy < H_) & ((qx != x0) | (qy != y0))
        return mi.UInt32(dr.select(inb, qy * W_ + qx, 0)), inb

    def spatial_reuse(self, gb, r: Reservoir, p_cur, reused, seed: int):
        """Merge neighbours' reservoirs (read from the temporal output ``r``).

        Two symbolic loops over a per-pixel neighbour count ``k``. With
        ``bias=pairwise`` see :func:`slc.methods.restir.pairwise.spatial_pairwise`. Otherwise the first
        resamples and records the accepted neighbours in a bit mask, the
        second (``bias=basic``) replays the same neighbour sequence up to
        the last accepted one and sums Z over the accepted neighbours whose
        surface has p_hat(y) > 0 for the selected y."""
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        W_, H_ = gb.width, gb.height
        R = max(self.radius * H_ / 1080.0, 2.0)
        x0, y0 = self.pixel_xy(n, W_)

        # ---------------- Per-pixel neighbour count ----------------
        # spatial everywhere; max(spatial, boost) where temporal history was
        # rejected (disocclusion boost); none on invalid pixels.
        k = dr.full(mi.UInt32, self.spatial, n)
        if self.temporal and self.boost > self.spatial:
            k = dr.select(reused, k, self.boost)
        k = dr.select(active, k, 0)
        if self.bias == "pairwise":
            return spatial_pairwise(self, gb, r, p_cur, k, R, seed)

        # ---------------- Pass 1: resampling self + neighbours ----------------
        sel = rng(n, seed, stream=14)
        st = Stream(n)
        st.update(r.y, r.n, r.light, p_cur, p_cur * r.W * r.M, sel.next_float32(), active)
        M = mi.Float(r.M)
        state = (mi.UInt32(0), rng(n, seed, stream=13), sel, st.y, st.n, st.light, st.p_hat, st.w_sum,
                 M, mi.UInt32(0))

        def body(i, smp, sel, y, nrm, light, p_hat, w_sum, M, used):
            st.y, st.n, st.light, st.p_hat, st.w_sum = y, nrm, light, p_hat, w_sum
            q, ok, rq = self.accepted_neighbour(smp, gb, r, R)
            # the target is only needed for a non-zero resampling weight; M counts regardless
            _, p_here, _, _, _, _ = self.evaluate(si, bsdf, rq.y, rq.n, rq.light, ok & (rq.W > 0.0))
            st.update(rq.y, rq.n, rq.light, p_here, p_here * rq.W * rq.M, sel.next_float32(), ok)
            M = M + dr.select(ok, rq.M, 0.0)
            used = used | dr.select(ok, mi.UInt32(1) << i, 0)
            return i + 1, smp, sel, st.y, st.n, st.light, st.p_hat, st.w_sum, M, used

        out = dr.while_loop(state=state, cond=lambda i, *_: i < k, body=body,
                            labels=("i", "smp", "sel", "y", "n", "light", "p_hat", "w_sum", "M", "used"))
        _, _, _, st.y, st.n, st.light, st.p_hat, st.w_sum, M, used = out

        # ---------------- Pass 2: bias correction (replay the neighbours) ----------------
        if self.bias == "off":
            Z = M
        else:
            Z = dr.select(st.p_hat > 0.0, r.M, 0.0)
            # Only up to the last accepted neighbour, only where a sample was selected
            k2 = dr.select(active & (st.p_hat > 0.0) & (st.w_sum > 0.0), 32 - dr.lzcnt(used), 0)
            y_s, n_s, l_s = mi.Point3f(st.y), mi.Vector3f(st.n), mi.UInt32(st.light)

            def body_z(i, smp, Z):
                q, _ = self.neighbour(smp, x0, y0, R, W_, H_)
                ok = ((used >> i) & 1) != 0
                Mq = dr.gather(mi.Float, r.M, q, ok)
                si_q = dr.gather(mi.SurfaceInteraction3f, si, q, ok)
                _, p_q, _, _, _, _ = self.evaluate(si_q, si_q.bsdf(), y_s, n_s, l_s, ok)
                return i + 1, smp, Z + dr.select(ok & (p_q > 0.0), Mq, 0.0)

            _, _, Z = dr.while_loop(state=(mi.UInt32(0), rng(n, seed, stream=13), Z),
                                    cond=lambda i, *_: i < k2, body=body_z, labels=("i", "smp", "Z"))
        return st.finalize(Z, M, active), st.p_hat

    def accepted_neighbour(self, smp, gb, r: Reservoir, R: float):
        """Next neighbour of the sequence ``smp`` (see :meth:`neighbour`) and
        whether it is reused: valid, similar depth and normal, M > 0; (index,
        mask, its reservoir)."""
        W_, H_ = gb.width, gb.height
        n0 = mi.Vector3f(gb.si.sh_frame.n)
        q, ok = self.neighbour(smp, *self.pixel_xy(gb.size, W_), R, W_, H_)
        ok &= dr.gather(mi.Bool, gb.valid, q, ok)
        ok &= self._similar(n0, dr.gather(mi.Vector3f, n0, q, ok), gb.depth, dr.gather(mi.Float, gb.depth, q, ok))
        rq = dr.gather(Reservoir, r, q, ok)
        return q, ok & (rq.M > 0.0), rq

    @staticmethod
    def pixel_xy(n: int, width: int):
        """Pixel coordinates (x, y) of the ``n`` pixels of a ``width``-wide image."""
        idx = dr.arange(mi.UInt32, n)
        return mi.Int32(idx % width), mi.Int32(idx // width)

    # ------------------------------ Stage 4: shade ------------------------------

    def shade(self, gb, r: Reservoir) -> mi.Color3f:
        si, active = gb.si, gb.valid
        ok = active & (r.W > 0.0)
        c, _, d, dist, kind, _ = self.evaluate(si, si.bsdf(), r.y, r.n, r.light, ok)
        vis = self._visible(si, d, dist, kind, ok)
        return dr.select(vis, c * r.W, 0.0)

    # ------------------------------ Frame ------------------------------

    def render(self, ctx, gbuffers, timer):
        shape = (gbuffers[0].width, gbuffers[0].height, len(gbuffers)) if gbuffers else None
        if shape != self._shape:
            self.state = {}
            self._shape = shape
        moved = self._light_moved()
        seeds = [self.seed_for(ctx.frame, v) for v in range(len(gbuffers))]

        with timer.stage("initial") as st:
            init = [self.initial(gb, s) for gb, s in zip(gbuffers, seeds)]
            for r, p in init:
                st.outputs(r, p)
        with timer.stage("temporal") as st:
            temp = []
            for v, (gb, (r, p)) in enumerate(zip(gbuffers, init)):
                if self.temporal and v in self.state:
                    r2, reused, p2 = self.temporal_reuse(gb, r, p, self.state[v], moved, seeds[v])
                else:
                    r2, reused, p2 = r, dr.zeros(mi.Bool, gb.size), p
                temp.append((r2, reused, p2))
                st.outputs(r2, reused, p2)
        with timer.stage("spatial") as st:
            final = []
            for gb, (r, reused, p), s in zip(gbuffers, temp, seeds):
                if self.spatial > 0 or (self.temporal and self.boost > 0):
                    r, p = self.spatial_reuse(gb, r, p, reused, s)
                final.append(r)
                st.outputs(r)
        with timer.stage("shade") as st:
            outs = [self.shade(gb, r) for gb, r in zip(gbuffers, final)]
            st.outputs(*outs)
        for v, (gb, r) in enumerate(zip(gbuffers, final)):
            self.state[v] = (r, gb)
        n_pix = sum(gb.size for gb in gbuffers)
        reused_frac = sum(int(np.count_nonzero(np.array(t[1]))) for t in temp) / max(n_pix, 1)
        self._stats = {"temporal_reuse": reused_frac}
        return outs

    def reservoirs(self, viewer: int = 0) -> dict:
        """The stored (final) reservoirs of a viewer as numpy arrays (for tests)."""
        r, _ = self.state[viewer]
        return {"y": np.array(r.y).T if np.array(r.y).shape[0] == 3 else np.array(r.y),
                "light": np.array(r.light), "W": np.array(r.W), "M": np.array(r.M)}

    def bytes_per_pixel(self) -> int:
        return 2 * RESERVOIR_BYTES + PREV_SURFACE_BYTES

    def memory_bytes(self) -> int:
        if self._shape is None:
            return 0
        w, h, v = self._shape
        return self.bytes_per_pixel() * w * h * v

    def stats(self) -> dict:
        return dict(self._stats)


register("restir", ReSTIR,
         help="ReSTIR DI (RTXDI defaults: 8 local/1 env/1 BSDF candidates, temporal M<=20, 1 spatial "
              "neighbour in 32 px@1080p; pairwise MIS reuse weights, bias=basic for RTXDI's 1/Z); "
              "restir:preset=falcor for 24/8/1")
