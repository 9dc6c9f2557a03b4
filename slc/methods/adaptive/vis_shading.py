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
from slc.methods.adaptive.polygon_ltc import ltc_correction, narrow
from slc.methods.adaptive.visibility import EMPTY, has_delta, light_at, slot, unpack


def shade(scene: mi.Scene, rec, si, bsdf, active, K: int, sph=None, env=None, rng=None, S: int = 0,
          ltc=None) -> mi.Color3f:
    """L_o of the pixels ``si`` from their VISIBILITY records (see the module). With ``rng``
    (and polygon lights), a glossy pixel's polygon lights get ``S`` sample pairs of their
    unshadowed term each (:func:`slc.methods.adaptive.polygon_glossy.glossy_term`); with ``ltc``
    (a :class:`~slc.methods.adaptive.polygon_ltc.LtcTable`), a GGX pixel's polygon lights get
    their lobe's integral (:func:`slc.methods.adaptive.polygon_ltc.ltc_correction`)."""
    em_dr, dl = scene.emitters_dr(), has_delta(scene)
    r = unpack(rec, K, env is not None)
    idx, vis = r.idx, r.vis
    ctx = mi.BSDFContext()
    active = mi.Bool(active)
    poly = sph is not None and sph.poly is not None
    glossy = rng is not None and S > 0 and poly
    gl_px = active & ((mi.UInt32(bsdf.flags()) & GLOSSY) != 0) if glossy else None
    use_ltc = ltc is not None and poly
    if use_ltc:
        ltc_px = active & ((mi.UInt32(bsdf.flags()) & GLOSSY) != 0)
        alpha = ltc.roughness(bsdf, si, ltc_px)
        ltc_px = ltc.fitted(alpha, si.wi.z, ltc_px & (alpha > 0.0))

    def cond(i, L, *g):
        return (i < K) & active

    def body(i, L, *g):                  # one emitter and one BSDF call site (see update)
        ii, vi = slot(idx, i), slot(vis, i)
        m = active & (ii != EMPTY) & (vi > 0.0)
        d, w = light_at(em_dr, si, ii, m, sph, env, dl)
        t = mi.Color3f(bsdf.eval(ctx, si, si.to_local(d), m)) * w * vi
        if use_ltc:                      # the slots whose GGX lobe is narrow against a whole polygon light
            nb = narrow(sph.table, si, alpha, ii, w, sph.polygon(ii, m & ltc_px) & (vi >= VIS_WHOLE))
            g = (g[0] | dr.select(nb, mi.UInt32(1) << i, 0),) + tuple(g[1:])
        if glossy:                       # a lobe narrow against the light: sampled (polygon_glossy)
            t_s, used, rng_ = polygon_term(sph.table, scene, si, bsdf, ii, sph.polygon(ii, m & gl_px), d, w, vi,
                                           g[-1], S)
            t, g = dr.select(used, t_s, t), tuple(g[:-1]) + (rng_,)
        return (i + 1, L + dr.select(m, t, 0.0)) + tuple(g)

    state = (mi.UInt32(0), dr.zeros(mi.Color3f, dr.width(active))) + ((mi.UInt32(0),) if use_ltc else ()) + \
        ((rng,) if glossy else ())
    _, L, *g = dr.while_loop(state=state, cond=cond, body=body)
    if use_ltc:
        # a narrow GGX lobe: its integral over a wholly visible polygon light instead of the
        # point's (polygon_glossy=ltc), in a loop of its own over the slots marked above (the
        # point terms' loop stays as small as without it; lanes with no mark run no pass)
        def cond_l(bits, L):
            return active & (bits != 0)

        def body_l(bits, L):
            on = active & (bits != 0)
            i = dr.tzcnt(bits)
            ii, vi = slot(idx, i), slot(vis, i)
            dI = ltc_correction(ltc, sph.table, si, bsdf, alpha, ii, on, sph, sph.poly.rects)
            return bits & (bits - 1), L + dr.select(on, dI * vi, 0.0)

        _, L = dr.while_loop(state=(mi.UInt32(g[0]), L), cond=cond_l, body=body_l)
    fn = bsdf.eval(ctx, si, mi.Vector3f(0.0, 0.0, 1.0), active)
    L += dr.select(active, mi.Color3f(fn) * r.E, 0.0)
    if env is not None:        # the unlisted regions, each at its own direction
        L += dr.select(active, env.unlisted_radiance(si, bsdf, idx, r.vu, active), 0.0)
    return L
