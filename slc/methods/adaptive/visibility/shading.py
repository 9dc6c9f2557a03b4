r"""Shading of VISIBILITY records (:mod:`slc.methods.adaptive.visibility`): at a pixel :math:`y`,
no ray,

.. math:: L_o(y) = \sum_{i \le K} f_r(y, \omega_i, \omega_o) \frac{I_i(\omega_i)}{d_i^2}\, v_i
          \;+\; f_r(y, n, \omega_o)\, E_r ,

each listed light's unoccluded term exact at the pixel (:func:`~slc.methods.adaptive.visibility.lights.light_at`),
its visible fraction :math:`v_i` and the residual :math:`E_r` from the entry. A polygon light
at a pixel whose glossy lobe is narrow against it gets the lobe's integral over the light
(``polygon_glossy=ltc``, :mod:`slc.lib.lights.polygon_ltc`) or sampled terms
(``sample``, :mod:`slc.lib.lights.polygon_glossy`) in place of the point's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.structs import drjit_struct
from slc.lib.lights.polygon_glossy import GLOSSY, VIS_WHOLE, polygon_term
from slc.lib.lights.polygon_ltc import ltc_term
from slc.methods.adaptive.visibility.lights import has_delta, light_at
from slc.methods.adaptive.visibility.record import EMPTY, slot, unpack, used_slots
from slc.lib.sh.shading import diffuse_only
from slc.scene.bsdf_table import side_normal

ALBEDO_SAMPLES = 16     # BSDF samples of a non-diffuse pixel's directional albedo and sky (the residual's shading)
R3 = 1.2207440846057596     # plastic constant of the 3-D Roberts sequence (as the cones' quadrature)


@drjit_struct
@dataclass
class AlbedoLoop:
    """The state of :func:`albedo`'s sample loop (one lane per pixel): ``i`` the BSDF samples
    drawn, ``A`` the sum of their weights, ``Ls`` the sum of their weights times the sky's
    radiance."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    A: mi.Color3f = field(default_factory=mi.Color3f)
    Ls: mi.Color3f = field(default_factory=mi.Color3f)


@drjit_struct
@dataclass
class SlotLoop:
    """The state of :func:`shade`'s loop over a record's slots (one lane per pixel): ``i`` the
    slot, ``L`` the radiance summed so far, ``rng`` the random numbers of the sampled glossy
    terms (None without them)."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    L: mi.Color3f = field(default_factory=mi.Color3f)
    rng: mi.PCG32 | None = None


def albedo(bsdf, si, ctx, active, rng, n: int, sky=None):
    r"""The pixels' directional albedo of reflection :math:`A(\omega_o) = \int f_r \cos\theta\,
    d\omega` over the hemisphere of :math:`\omega_o` (transmission left out: the residual is
    the light of the pixel's side), the mean weight of ``n`` BSDF samples (exact for a
    Lambertian lobe; a GGX sample's weight is F G1, nearly constant over the lobe), and with
    ``sky`` (a function of world directions: the sky's radiance) the same samples' estimate of
    the unoccluded sky's reflected radiance :math:`\int f_r \cos\theta\, L_s\, d\omega`
    (0 without). The samples follow a rank-1 (R3) sequence rotated per pixel by ``rng``
    (stratified: a smooth integrand's error falls faster than with independent samples)."""
    o = [rng.next_float32() for _ in range(3)]

    def frac(x):
        return x - dr.floor(x)

    def cond(st: AlbedoLoop):
        return (st.i < n) & active

    def body(st: AlbedoLoop):
        k = mi.Float(st.i)
        u1 = frac(o[0] + k * (1.0 / R3))
        u2 = mi.Point2f(frac(o[1] + k * (1.0 / R3 ** 2)), frac(o[2] + k * (1.0 / R3 ** 3)))
        bs, w = bsdf.sample(ctx, si, u1, u2, active)
        refl = active & (bs.pdf > 0.0) & (mi.Frame3f.cos_theta(bs.wo) * mi.Frame3f.cos_theta(si.wi) > 0.0)
        if sky is not None:
            st.Ls = st.Ls + dr.select(refl, mi.Color3f(w) * sky(si.to_world(bs.wo), refl), 0.0)
        st.i, st.A = st.i + 1, st.A + dr.select(refl, mi.Color3f(w), 0.0)
        return (st,)

    z = dr.zeros(mi.Color3f, dr.width(active))
    st, = dr.while_loop(state=(AlbedoLoop(mi.UInt32(0), z, mi.Color3f(z)),), cond=cond, body=body,
                        labels=("albedo",))
    return st.A * (1.0 / n), st.Ls * (1.0 / n)


def visible(scene: mi.Scene, si, d: mi.Vector3f, dist: mi.Float, active: mi.Bool) -> mi.Bool:
    """A shadow ray from the pixels ``si`` along ``d`` to the distance ``dist`` (inf: a light at
    infinity): the light seen."""
    ray = si.spawn_ray(d)
    ray.maxt = dr.select(dr.isfinite(dist), dist * (1.0 - mi.math.ShadowEpsilon), ray.maxt)
    return mi.Bool(active) & ~scene.ray_test(ray, active)


def uniform_residual(si, bsdf, ctx, active, E_res, vs, env, emitters_dr, rng) -> mi.Color3f:
    """The residual ``E_res`` of non-diffuse pixels as uniform radiance over their hemisphere,
    ``A E_res/pi`` (:func:`albedo`), and with ``env`` (a sky) the same BSDF samples of the
    sky's map radiance times the entry's visible fraction ``vs``."""
    g_px = mi.Bool(active) & ((dr.max(E_res) > 0.0) | ((env is not None) & (vs > 0.0)))
    sky_fn = (lambda d, m: env.sky_map_radiance(emitters_dr, d, m)) if env is not None else None   # noqa: E731
    A, Ls = albedo(bsdf, si, ctx, g_px, rng, ALBEDO_SAMPLES, sky_fn)
    return dr.select(g_px, E_res * A * (1.0 / math.pi) + Ls * vs, 0.0)


def shade(scene: mi.Scene, rec, si, bsdf, active, K: int, sph=None, env=None, rng=None, S: int = 0,
          ltc=None, back: bool = False, rng_a=None) -> mi.Color3f:
    """L_o of the pixels ``si`` from their VISIBILITY records (see the module). With ``rng``
    (and polygon lights), a glossy pixel's polygon lights get ``S`` sample pairs of their
    unshadowed term each (:func:`slc.lib.lights.polygon_glossy.glossy_term`); with ``ltc``
    (a :class:`~slc.lib.lights.polygon_ltc.LtcTable`), a GGX pixel's polygon lights get
    their lobe's integral (:func:`slc.lib.lights.polygon_ltc.ltc_term`). ``back``: the
    records keep the residual behind the surface (two-sided BSDFs in the scene): a pixel is
    shaded on its own side (the normal turned towards its viewer, the residual of that side).
    The residual is light of unknown direction: a diffuse-only pixel takes it along the
    normal (exact: ``rho/pi E``), another pixel as uniform radiance ``E/pi`` over its
    hemisphere, ``A E/pi`` with ``A`` its directional albedo from ``ALBEDO_SAMPLES`` BSDF
    samples (random numbers ``rng_a``; the
    BSDF along the normal, which is exact for a Lambertian lobe, is off by orders of magnitude
    for a narrow lobe seen near the normal). The sky (``env.has_sky``): its exact irradiance
    times the entry's visible fraction ``v_s`` with the residual of a diffuse-only pixel; for
    another pixel the same BSDF samples of the map's radiance outside its kept regions, times
    ``v_s`` (its SH radiance, smooth, measured worse on narrow lobes: skylit's chrome spheres'
    per-pixel error 0.56 against 0.33, preview_export's steel cube 0.74 against 0.31)."""
    em_dr, dl = scene.emitters_dr(), has_delta(scene)
    r = unpack(rec, K, env is not None, back)
    idx, vis = r.idx, r.vis
    ctx = mi.BSDFContext()
    active = mi.Bool(active)
    poly = sph is not None and sph.poly is not None
    glossy = rng is not None and S > 0 and poly
    use_ltc = ltc is not None and poly
    gl_px = active & ((mi.UInt32(bsdf.flags()) & GLOSSY) != 0) if glossy or use_ltc else None
    if use_ltc:                          # the pixels' GGX lobes as LTCs (polygon_glossy=ltc)
        alpha = ltc.roughness(bsdf, si, gl_px)
        ltc_px = ltc.fitted(alpha, si.wi.z, gl_px & (alpha > 0.0))

    n_used = used_slots(idx)
    diff = diffuse_only(bsdf) if rng_a is not None else mi.Bool(True)
    z = mi.Vector3f(0.0, 0.0, 1.0)
    n_px, E_res = None, r.E
    if back:                             # the pixel's side: its normal and residual
        n_px = side_normal(si)
        z = mi.Vector3f(0.0, 0.0, dr.mulsign(1.0, si.wi.z))
        E_res = dr.select(si.wi.z < 0.0, r.Eb, r.E)
    sky = env is not None and env.has_sky
    if sky:                              # a diffuse pixel takes the sky's irradiance with the residual
        E_res = E_res + dr.select(diff, env.sky_irradiance(si.sh_frame.n if n_px is None else n_px, active & diff)
                                  * r.vs, 0.0)

    # ----------------------- the listed lights (slots 0 to n_used - 1), then the residual of a
    # diffuse-only pixel (iteration n_used: the BSDF along the normal times E): one BSDF call site
    def cond(st: SlotLoop):
        return (st.i <= n_used) & active

    def body(st: SlotLoop):
        i = st.i
        res = i == n_used
        ii, vi = slot(idx, i), slot(vis, i)
        m = active & ~res & (ii != EMPTY) & (vi > 0.0)
        d, w, dist, hard = light_at(em_dr, si, ii, m, sph, env, dl, n=n_px, reach=True)
        w, vi, m_f = dr.select(res, E_res, w), dr.select(res, 1.0, vi), m | (active & res & diff)
        t = mi.Color3f(bsdf.eval(ctx, si, dr.select(res, z, si.to_local(d)), m_f)) * w
        if use_ltc:                      # a narrow GGX lobe and a wholly visible polygon light: its integral
            whole = sph.polygon(ii, m & ltc_px) & (vi >= VIS_WHOLE)
            t = ltc_term(ltc, sph.table, si, bsdf, alpha, ii, d, w, t, whole, sph.poly.rects)
        # a light with hard shadow edges, one of which crosses the entry (a visible fraction strictly
        # between 0 and 1, measured over the entry's footprint): its visibility traced at the pixel
        edge = m & (vi < 1.0) & hard
        t *= dr.select(edge, dr.select(visible(scene, si, d, dist, edge), 1.0, 0.0), vi)
        if glossy:                       # a lobe narrow against the light: sampled (polygon_glossy)
            t_s, used, st.rng = polygon_term(sph.table, scene, si, bsdf, ii, sph.polygon(ii, m & gl_px), d, w, vi,
                                             st.rng, S)
            t = dr.select(used, t_s, t)
        st.i, st.L = i + 1, st.L + dr.select(m_f, t, 0.0)
        return (st,)

    L = dr.while_loop(state=(SlotLoop(mi.UInt32(0), dr.zeros(mi.Color3f, dr.width(active)), rng if glossy else None),),
                      cond=cond, body=body)[0].L
    # ----------------------- the residual of the other pixels: its irradiance as uniform radiance
    if rng_a is not None:
        L += uniform_residual(si, bsdf, ctx, active & ~diff, E_res, r.vs, env if sky else None, em_dr, rng_a)
    if env is not None:        # the unlisted regions, each at its own direction
        L += dr.select(active, env.unlisted_radiance(si, bsdf, idx, r.vu, active, n_px), 0.0)
    return L
