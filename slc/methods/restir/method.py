"""ReSTIR DI (RTXDI-style), per viewer: reservoir-based spatiotemporal
importance resampling of direct lighting [Bitterli et al. 2020].

One reservoir per pixel and viewer. Per frame: resampled importance sampling
of initial candidates (local lights, environment, BSDF), temporal reuse from
the previous frame's reservoirs through the motion vectors, spatial reuse
from neighbouring pixels, and final shading with one shadow ray.

This module holds the method, its initial candidates, shading and frame; the parts it holds are
the light set-up and target function (``target``, :mod:`slc.methods.restir.target`) and the
temporal and spatial reuse (``reuse``, :mod:`slc.methods.restir.reuse`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.structs import drjit_struct
from slc.scene.lights import rng
from slc.methods import Method, MethodError, Param, register
from slc.methods.restir.reservoir import Reservoir, Stream
from slc.methods.restir.reuse import Reuse
from slc.methods.restir.target import LightTarget

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


@drjit_struct
@dataclass
class CandidateLoop:
    """The state of the local-light candidate loop (one lane per pixel): ``i`` the candidates
    drawn, ``res`` the reservoir being filled, ``smp`` the random numbers."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    res: Stream = field(default_factory=Stream)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)


@dataclass
class Passes:
    """What the reservoir passes of a frame leave for shading and the next frame, per viewer:
    the final reservoirs and the pixels whose temporal reuse took a previous reservoir."""
    final: list
    reused: list

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
        self.target = LightTarget(scene, self.n_local, self.n_env, self.n_bsdf)
        self.reuse = Reuse(self.target, temporal=self.temporal, mcap=self.mcap, depth_thr=self.depth_thr,
                           normal_thr=self.normal_thr, spatial=self.spatial, radius=self.radius,
                           boost=self.boost, bias=self.bias)
        self.reset()

    def validate(self):
        if self.preset is None and self.local + self.env + self.bsdf == 0:
            raise MethodError("restir: at least one candidate is needed (local + env + bsdf > 0)")

    def reset(self):
        self.state: dict[int, tuple] = {}   # viewer -> (Reservoir, previous GBuffer)
        self._shape = None                  # (width, height, viewers) of the allocation
        self.target.reset()
        self._stats = {}

    # ------------------------------ Stage 1: initial ------------------------------

    def initial(self, gb, seed: int) -> tuple[Reservoir, mi.Float]:
        """One function because its candidate stages (local lights, environment, BSDF) feed one
        reservoir stream through the shared ``add``; its stages are marked by banner comments.

        The initial candidates of the G-buffer ``gb``'s pixels resampled into one reservoir per
        pixel (M = 1), with initial visibility: (reservoir, target value of the kept candidate)."""
        # ---------------- Set-up; ``add``: a candidate's resampling weight into a stream ----------------
        sc = self.scene.mi_scene
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        ctx = mi.BSDFContext()
        sampler = rng(n, seed, stream=11)
        res = Stream(n)
        if self.target.table is not None:
            self.target.table.refresh()   # animated emissive meshes

        def add(into, y, nrm, light, ok, u_sel, p_dir=None):
            _, p_hat, d, dist, kind, ds, p_bsdf = self.target.evaluate(si, bsdf, y, nrm, light, ok, with_pdf=True)
            denom = self.target.pdf_sum(si, bsdf, light, kind, d, dist, nrm, ds, ok & (p_hat > 0.0),
                                        p_dir=p_dir, p_bsdf=p_bsdf)
            good = ok & (p_hat > 0.0) & (denom > 0.0)
            w = dr.select(good, p_hat / dr.select(good, denom, 1.0), 0.0)
            into.update(y, nrm, light, p_hat, w, u_sel, good)

        # ---------------- Local-light candidates (symbolic loop) ----------------
        if self.target.L and self.n_local:
            n_local = dr.opaque(mi.UInt32, self.n_local)

            def cond(s: CandidateLoop):
                return s.i < n_local

            def body(s: CandidateLoop):
                smp = s.smp
                if self.target.table is not None:
                    u = mi.Point2f(smp.next_float32(), smp.next_float32())
                    ds, _, ok, light = self.target.table.sample(si, u, active)
                    add(s.res, mi.Point3f(ds.p), mi.Vector3f(ds.n), light, ok, smp.next_float32())
                else:
                    k = dr.minimum(mi.UInt32(smp.next_float32() * self.target.L), self.target.L - 1)
                    light = dr.gather(mi.UInt32, self.target.local, k, active)
                    em = dr.gather(mi.EmitterPtr, self.target.emitters, light, active)
                    u = mi.Point2f(smp.next_float32(), smp.next_float32())
                    ds, _ = em.sample_direction(si, u, active)
                    ok = active & (ds.pdf > 0.0)
                    add(s.res, mi.Point3f(ds.p), mi.Vector3f(ds.n), light, ok, smp.next_float32(), p_dir=ds.pdf)
                s.i = s.i + 1
                return (s,)

            s, = dr.while_loop(state=(CandidateLoop(mi.UInt32(0), res, sampler),), cond=cond, body=body,
                               labels=("candidates",))
            res, sampler = s.res, s.smp

        # ---------------- Environment candidates ----------------
        if self.target.E and self.n_env:
            for _ in range(self.n_env):
                k = dr.minimum(mi.UInt32(sampler.next_float32() * self.target.E), self.target.E - 1)
                light = dr.gather(mi.UInt32, self.target.infinite, k, active)
                em = dr.gather(mi.EmitterPtr, self.target.emitters, light, active)
                u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
                ds, _ = em.sample_direction(si, u, active)
                ok = active & (ds.pdf > 0.0)
                add(res, mi.Point3f(ds.d), dr.zeros(mi.Vector3f, n), light, ok, sampler.next_float32(), p_dir=ds.pdf)

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
            light = dr.gather(mi.UInt32, self.target.id_to_index, rid, hit_em)
            y = dr.select(hit_em, si2.p, mi.Point3f(wo))
            nrm = dr.select(hit_em, mi.Vector3f(si2.n), 0.0)
            if self.target.env_index >= 0:
                miss = ok & ~si2.is_valid()
                light = dr.select(miss, self.target.env_index, light)
                cand = hit_em | miss
            else:
                cand = hit_em
            add(res, y, nrm, light, cand, sampler.next_float32())

        # ---------------- Finalize (M = 1) and initial visibility ----------------
        r = res.finalize(mi.Float(1.0), mi.Float(1.0), active)
        if self.visibility:
            d, dist, kind = self.target.direction(si, r.y, r.light, active & (r.W > 0.0))
            vis = self.target.visible(si, d, dist, kind, active & (r.W > 0.0))
            r.W = dr.select(vis, r.W, 0.0)
        return r, res.p_hat


    # ------------------------------ Stage 4: shade ------------------------------

    def shade(self, ctx, fr: "Passes", v: int, gb) -> mi.Color3f:
        r = fr.final[v]
        si, active = gb.si, gb.valid
        ok = active & (r.W > 0.0)
        c, _, d, dist, kind, _ = self.target.evaluate(si, si.bsdf(), r.y, r.n, r.light, ok)
        vis = self.target.visible(si, d, dist, kind, ok)
        return dr.select(vis, c * r.W, 0.0)

    # ------------------------------ Stages 2-3: reuse, by the parts ------------------------------

    def _light_moved(self) -> mi.Bool:
        """Per emitter: its shape moved since the previous frame (:meth:`LightTarget.moved`)."""
        return self.target.moved()

    def temporal_reuse(self, gb, r: Reservoir, p_cur, prev, moved, seed: int):
        """Stage 2 (:meth:`Reuse.temporal_reuse`): (reservoir, reused mask, target value)."""
        return self.reuse.temporal_reuse(gb, r, p_cur, prev, moved, seed)

    def spatial_reuse(self, gb, r: Reservoir, p_cur, reused, seed: int):
        """Stage 3 (:meth:`Reuse.spatial_reuse`): (reservoir, target value)."""
        return self.reuse.spatial_reuse(gb, r, p_cur, reused, seed)

    # ------------------------------ Frame ------------------------------

    def update_frame(self, ctx, gbuffers, timer) -> "Passes":
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
        return Passes(final=final, reused=[t[1] for t in temp])

    def finish(self, ctx, fr: "Passes", gbuffers, outs, timer):
        for v, (gb, r) in enumerate(zip(gbuffers, fr.final)):
            self.state[v] = (r, gb)
        n_pix = sum(gb.size for gb in gbuffers)
        reused_frac = sum(int(np.count_nonzero(np.array(m))) for m in fr.reused) / max(n_pix, 1)
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
