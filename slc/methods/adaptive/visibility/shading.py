r"""Shading of VISIBILITY records (:mod:`slc.methods.adaptive.visibility`): at a pixel :math:`y`,
no ray,

.. math:: L_o(y) = \sum_{i \le K} f_r(y, \omega_i, \omega_o) \frac{I_i(\omega_i)}{d_i^2}\, v_i
          \;+\; f_r(y, n, \omega_o)\, E_r ,

each listed light's unoccluded term exact at the pixel (:func:`~slc.methods.adaptive.visibility.light_at`),
its visible fraction :math:`v_i` and the residual :math:`E_r` from the entry. A polygon light
at a pixel whose glossy lobe is narrow against it gets the lobe's integral over the light
(``polygon_glossy=ltc``, :mod:`slc.methods.adaptive.polygon_ltc`) or sampled terms
(``sample``, :mod:`slc.methods.adaptive.polygon_glossy`) in place of the point's.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.adaptive.polygon_glossy import GLOSSY, VIS_WHOLE, polygon_term
from slc.methods.adaptive.polygon_ltc import ltc_term
from slc.methods.adaptive.visibility import EMPTY, has_delta, light_at, slot, unpack, used_slots


def shade(scene: mi.Scene, rec, si, bsdf, active, K: int, sph=None, env=None, rng=None, S: int = 0,
          ltc=None) -> mi.Color3f:
    """L_o of the pixels ``si`` from their VISIBILITY records (see the module). With ``rng``
    (and polygon lights), a glossy pixel's polygon lights get ``S`` sample pairs of their
    unshadowed term each (:func:`slc.methods.adaptive.polygon_glossy.glossy_term`); with ``ltc``
    (a :class:`~slc.methods.adaptive.polygon_ltc.LtcTable`), a GGX pixel's polygon lights get
    their lobe's integral (:func:`slc.methods.adaptive.polygon_ltc.ltc_term`)."""
    em_dr, dl = scene.emitters_dr(), has_delta(scene)
    r = unpack(rec, K, env is not None)
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
    z = mi.Vector3f(0.0, 0.0, 1.0)

    # ----------------------- the listed lights (slots 0 to n_used - 1), then the residual
    # (iteration n_used: the BSDF along the normal times E): one BSDF call site for both
    def cond(i, L, *g):
        return (i <= n_used) & active

    def body(i, L, *g):
        res = i == n_used
        ii, vi = slot(idx, i), slot(vis, i)
        m = active & ~res & (ii != EMPTY) & (vi > 0.0)
        d, w = light_at(em_dr, si, ii, m, sph, env, dl)
        w, vi, m_f = dr.select(res, r.E, w), dr.select(res, 1.0, vi), m | (active & res)
        t = mi.Color3f(bsdf.eval(ctx, si, dr.select(res, z, si.to_local(d)), m_f)) * w
        if use_ltc:                      # a narrow GGX lobe and a wholly visible polygon light: its integral
            whole = sph.polygon(ii, m & ltc_px) & (vi >= VIS_WHOLE)
            t = ltc_term(ltc, sph.table, si, bsdf, alpha, ii, d, w, t, whole, sph.poly.rects)
        t *= vi
        if glossy:                       # a lobe narrow against the light: sampled (polygon_glossy)
            t_s, used, rng_ = polygon_term(sph.table, scene, si, bsdf, ii, sph.polygon(ii, m & gl_px), d, w, vi,
                                           g[-1], S)
            t, g = dr.select(used, t_s, t), tuple(g[:-1]) + (rng_,)
        return (i + 1, L + dr.select(m_f, t, 0.0)) + tuple(g)

    state = (mi.UInt32(0), dr.zeros(mi.Color3f, dr.width(active))) + ((rng,) if glossy else ())
    _, L, *g = dr.while_loop(state=state, cond=cond, body=body)
    if env is not None:        # the unlisted regions, each at its own direction
        L += dr.select(active, env.unlisted_radiance(si, bsdf, idx, r.vu, active), 0.0)
    return L
