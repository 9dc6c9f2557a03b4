"""The lights and the target function of ReSTIR (:class:`LightTarget`, held by
:class:`slc.methods.restir.method.ReSTIR` as ``target``): the emitter tables built at set-up (kinds,
local and infinite lights, the shared emitter table), the lights that moved since the previous frame,
the unshadowed contribution f_r L_e G of a stored sample and its target p_hat, the shadow ray towards
it, and the candidates' densities of the three sampling techniques in the sample's own measure."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.lights import sampler as light_table

# Emitter kinds (the measure in which a stored sample lives)
AREA, DELTA_POS, INFINITE = 0, 1, 2


class LightTarget:
    r"""The lights of a scene seen by ReSTIR: the target :math:`\hat p_x(y) = \mathrm{lum}(f_r L_e G)`
    of a stored sample y, the shadow ray towards it and the candidates' densities
    :math:`\sum_t N_t p_t(y)`.

    Parameters: ``scene`` (:class:`slc.scene.scenes.Scene`), ``n_local``, ``n_env``, ``n_bsdf``
    (candidates N_t of the local-light, environment and BSDF techniques). Set-up builds, per emitter
    of ``scene.emitters()``, its kind (``kinds``: AREA, DELTA_POS, INFINITE) and delta flag
    (``is_delta``), the local and infinite lights (``local``, ``infinite``; counts ``L``, ``E``),
    the environment's index (``env_index``, -1 without one), the registry id -> index table
    (``id_to_index``) and the shared emitter table over the local lights (``table``; None without
    local lights)."""

    def __init__(self, scene, n_local: int, n_env: int, n_bsdf: int):
        self.scene = scene
        self.n_local, self.n_env, self.n_bsdf = n_local, n_env, n_bsdf
        self._setup_lights()

    # ------------------------------ Set-up ------------------------------

    def _setup_lights(self):
        sc = self.scene.mi_scene
        ems = sc.emitters()
        self.emitters = sc.emitters_dr()
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
        self.env_index = next((i for i, e in enumerate(ems) if env is not None and e is env), -1)
        self.kinds = mi.UInt32(kinds)
        self.is_delta = mi.Bool(delta)
        self.local = mi.UInt32(local or [0])
        self.infinite = mi.UInt32(inf or [0])
        self.L, self.E = len(local), len(inf)
        # registry id of an EmitterPtr -> index in scene.emitters()
        ids = np.array(dr.reinterpret_array(mi.UInt32, self.emitters), dtype=np.int64)
        table = np.zeros(int(ids.max()) + 1 if len(ids) else 1, dtype=np.uint32)
        table[ids] = np.arange(len(ids), dtype=np.uint32)
        self.id_to_index = mi.UInt32(table)
        self.shaped = [(i, e.get_shape()) for i, e in enumerate(ems) if kinds[i] == AREA and e.get_shape()]
        # local-light candidates from the shared emitter table (None: Mitsuba, uniform choice)
        self.table = light_table(sc, subset=local) if local else None
        self.bboxes = None

    def reset(self) -> None:
        """Forget the area lights' last positions (none has moved before the next frame)."""
        self.bboxes = None

    def moved(self) -> mi.Bool:
        """Per emitter: its shape moved since the previous frame."""
        n = len(self.scene.mi_scene.emitters())
        moved = np.zeros(max(n, 1), dtype=bool)
        if self.scene.dynamic:
            cur = {}
            for i, s in self.shaped:
                b = s.bbox()
                cur[i] = np.array([*b.min, *b.max], float)
            if self.bboxes is not None:
                for i, b in cur.items():
                    moved[i] = not np.allclose(b, self.bboxes.get(i, b), rtol=0, atol=1e-6)
            self.bboxes = cur
        return mi.Bool(moved)

    # --------------------------- Target function ---------------------------

    def direction(self, si, y, light, active):
        """Unit direction from ``si`` to a stored sample, its distance (inf
        for infinite lights) and the emitter kind."""
        kind = dr.gather(mi.UInt32, self.kinds, light, active)
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
        d, dist, kind = self.direction(si, y, light, active)
        em = dr.gather(mi.EmitterPtr, self.emitters, light, active)
        inf = kind == INFINITE
        ok = active & (inf | (dist > 0.0))
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p = dr.select(inf, si.p + d, mi.Point3f(y))
        ds.n = mi.Normal3f(n)
        ds.d = d
        ds.dist = dr.select(inf, dr.inf, dist)
        ds.emitter = em
        ds.delta = dr.gather(mi.Bool, self.is_delta, light, active)
        Le = mi.Color3f(em.eval_direction(si, ds, ok))
        if self.E:
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

    def visible(self, si, d, dist, kind, active):
        """Shadow ray towards a stored sample (to the point, or to infinity)."""
        inf = kind == INFINITE
        ray = si.spawn_ray(d)
        ray_to = si.spawn_ray_to(si.p + d * dist)
        ray.maxt = dr.select(inf, ray.maxt, ray_to.maxt)
        ray.o = dr.select(inf, ray.o, ray_to.o)
        ray.d = dr.select(inf, ray.d, ray_to.d)
        return active & ~self.scene.mi_scene.ray_test(ray, active)

    def pdf_sum(self, si, bsdf, light, kind, d, dist, n, ds, active, p_dir=None, p_bsdf=None):
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
            if self.table is not None:   # only the infinite lights still need Mitsuba's density
                need &= kind == INFINITE
            p_dir = em.pdf_direction(si, ds, need)
        p_dir = dr.select(delta, 0.0, p_dir)
        total = dr.zeros(mi.Float, dr.width(light))
        if self.L and self.n_local:
            if self.table is not None:
                loc = active & (kind != INFINITE)
                p_l = dr.select(delta, self.table.choice_pmf(light, loc),
                                self.table.pdf(si, ds, loc & ~delta, index=light) * to_area)
            else:
                p_l = dr.select(delta, 1.0, p_dir * to_area) / self.L
            total += dr.select(kind != INFINITE, float(self.n_local) * p_l, 0.0)
        if self.E and self.n_env:
            p_e = dr.select(delta, 1.0, p_dir) / self.E
            total += dr.select(kind == INFINITE, float(self.n_env) * p_e, 0.0)
        if self.n_bsdf:
            if p_bsdf is None:
                p_bsdf = bsdf.pdf(ctx, si, si.to_local(d), active & ~delta)
            p_b = p_bsdf * to_area
            hit_able = ~delta & (kind == AREA)
            if self.env_index >= 0:
                hit_able |= ~delta & (light == self.env_index)
            total += dr.select(hit_able, float(self.n_bsdf) * p_b, 0.0)
        return dr.select(active, total, 0.0)
