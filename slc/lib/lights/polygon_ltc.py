r"""Glossy shading of polygon lights by linearly transformed cosines (docs/adaptive.md, "Glossy
pixels"; Heitz, Dupuy, Hill, Neubelt 2016).

A VISIBILITY record shades a polygon light at a pixel :math:`y` as a point along its vector
irradiance :math:`\mathbf d`: :math:`P = f(\mathbf d) \cos\theta_{\mathbf d}\, w` with
:math:`w` the irradiance per unit cosine along :math:`\mathbf d`, exact for a Lambertian BSDF
and wrong for a lobe narrow against the light. With ``polygon_glossy=ltc`` a pixel whose BSDF
has a GGX lobe of roughness :math:`\alpha` (Mitsuba's ``alpha`` attribute, or ``roughness``
squared) models that lobe as :math:`f_s \cos \approx A\, D_M`, the linearly transformed cosine
:math:`D_M` fitted to Mitsuba's GGX lobe for :math:`(\alpha, \theta_o)` (``tools/fit_ltc.py``,
the table ``ltc_ggx.npz``), and replaces the lobe's point term by its integral over the light:

.. math:: I = P + A\,\Bigl(L \int_{\Omega_L} D_M\, d\omega - D_M(\mathbf d)\, w\Bigr), \qquad
          \int_{\Omega_L} D_M\, d\omega = \frac1\pi\, \hat z \cdot \mathbf F(M^{-1} \Omega_L),

the second integral Lambert's formula over the light's triangles transformed by :math:`M^{-1}`
and clipped to the upper hemisphere (:func:`slc.lib.lights.polygon_lights.vector_irradiance`).
The scale :math:`A` (RGB: Fresnel and albedo) is calibrated at the pixel from one BSDF
evaluation at the LTC's peak direction :math:`\omega^* = M\hat z / |M \hat z|` (the mirror
direction where that is below the horizon): :math:`A = f_g \cos(\omega^*) / D_M(\omega^*)`,
:math:`f_g` the BSDF's glossy components alone (a diffuse base, as roughplastic's, keeps its
point term, exact for a Lambertian lobe). Where the lobe is wide against the light the bracket
vanishes (the integral of :math:`D_M` is its value at the light times the light's solid angle)
and :math:`I = P`; where it is narrow the bracket replaces the point's lobe by the integral.
The entry's visible fraction multiplies :math:`I` as it multiplies :math:`P`. No ray, no
random number.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.lib.lights.polygon_lights import vector_irradiance
from slc.scene.bsdf_table import ALPHA_TEXTURED
from slc.scene.emitter_table import ROW, ROW_L

TABLE = Path(__file__).with_name("ltc_ggx.npz")
NARROW_TAU = 0.1     # a lobe is narrow where its peak density (1/sr) times the light's solid angle exceeds this
MAX_FIT_L1 = 0.1    # the table's L1 error (0 to 2) below which its LTC is used (else the point term)
# the BSDF's glossy components only (the scale A leaves out a diffuse base, as of roughplastic)
GLOSSY_CONTEXT = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.GlossyReflection)


class LtcTable:
    """The fitted table (``tools/fit_ltc.py``): per (sqrt(alpha), sqrt(1 - cos theta)) cell the
    five non-zero entries of M in the view's frame and the fit's L1 error, bilinearly
    interpolated; ``bsdfs``: the scene's :class:`slc.scene.bsdf_table.BSDFTable` (its ``alpha``
    column; None for scenes without one: every pixel's alpha is evaluated)."""

    def __init__(self, bsdfs, path: Path = TABLE):
        self.bsdfs = bsdfs
        d = np.load(path)
        m = np.asarray(d["m"], np.float32)                  # (alphas, views, 5)
        self.na, self.nt = int(m.shape[0]), int(m.shape[1])
        self._m = [mi.Float(np.ascontiguousarray(m[..., k]).ravel()) for k in range(5)]
        self._l1 = mi.Float(np.ascontiguousarray(d["l1"], np.float32).ravel())
        for a in self._m + [self._l1]:
            dr.make_opaque(a)

    def arrays(self) -> list:
        return list(self._m) + [self._l1] + ([self.bsdfs] if self.bsdfs is not None else [])

    def roughness(self, bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Float:
        """The GGX alpha of the pixels' BSDFs (the table's ``alpha`` column; a textured one
        evaluated here: Mitsuba's ``alpha`` attribute, else ``roughness`` squared)."""
        active = mi.Bool(active)
        t = self.bsdfs
        if t is None:
            a, tex = dr.full(mi.Float, ALPHA_TEXTURED, dr.width(active)), active
        else:
            rid = dr.reinterpret_array(mi.UInt32, bsdf)
            active &= rid < t.width
            a = dr.gather(mi.Float, t.alpha, rid, active)
            tex = active & (a == ALPHA_TEXTURED) if t.alpha_textured else None
        if tex is not None:
            at = bsdf.eval_attribute_1("alpha", si, tex)
            r = bsdf.eval_attribute_1("roughness", si, tex)
            a = dr.select(tex, dr.select(at > 0.0, at, r * r), a)
        return dr.select(active, a, 0.0)

    def _lerp(self, arrays: list, alpha: mi.Float, cos_o: mi.Float, active: mi.Bool) -> list:
        u = dr.clip(dr.sqrt(dr.maximum(alpha, 0.0)) * (self.na - 1), 0.0, self.na - 1.0001)
        t = dr.clip(dr.sqrt(dr.maximum(1.0 - cos_o, 0.0)) * self.nt, 0.0, self.nt - 1.0001)
        i0, j0 = mi.UInt32(u), mi.UInt32(t)
        fu, ft = u - mi.Float(i0), t - mi.Float(j0)
        out = []
        for a in arrays:
            def g(i, j):
                return dr.gather(mi.Float, a, i * self.nt + j, active)
            v0 = dr.lerp(g(i0, j0), g(i0, j0 + 1), ft)
            v1 = dr.lerp(g(i0 + 1, j0), g(i0 + 1, j0 + 1), ft)
            out.append(dr.lerp(v0, v1, fu))
        return out

    def fitted(self, alpha: mi.Float, cos_o: mi.Float, active: mi.Bool) -> mi.Bool:
        """Lanes whose lobe the table fits within ``MAX_FIT_L1`` (its L1 error, interpolated)."""
        return mi.Bool(active) & (self._lerp([self._l1], alpha, cos_o, active)[0] < MAX_FIT_L1)

    def matrix(self, alpha: mi.Float, cos_o: mi.Float, active: mi.Bool) -> list:
        """M's entries (m00, m02, m11, m20, m22) at (alpha, cos theta_o)."""
        return self._lerp(self._m, alpha, cos_o, active)


def _inverse(m: list):
    """M^-1 of M = [[m00, 0, m02], [0, m11, 0], [m20, 0, m22]] as the same five entries, and
    its determinant."""
    m00, m02, m11, m20, m22 = m
    det2 = m00 * m22 - m02 * m20
    r = dr.rcp(dr.select(det2 != 0.0, det2, 1.0))
    i11 = dr.rcp(dr.select(m11 != 0.0, m11, 1.0))
    return [m22 * r, -m02 * r, i11, -m20 * r, m00 * r], r * i11


def _apply(mi_: list, v: mi.Vector3f) -> mi.Vector3f:
    i00, i02, i11, i20, i22 = mi_
    return mi.Vector3f(dr.fma(i00, v.x, i02 * v.z), i11 * v.y, dr.fma(i20, v.x, i22 * v.z))


def _density(minv: list, det: mi.Float, v: mi.Vector3f) -> mi.Float:
    """D_M(v) for unit v: the clamped cosine at M^-1 v / |M^-1 v| times the Jacobian."""
    lo = _apply(minv, v)
    n2 = dr.squared_norm(lo)
    inv_n = dr.rsqrt(dr.maximum(n2, 1e-30))
    return dr.maximum(lo.z * inv_n, 0.0) * (1.0 / math.pi) * dr.abs(det) * inv_n * inv_n * inv_n


def _to_view(cphi: mi.Float, sphi: mi.Float, v: mi.Vector3f) -> mi.Vector3f:
    """A local-frame direction in the view's frame (x towards the view's tangential direction)."""
    return mi.Vector3f(cphi * v.x + sphi * v.y, cphi * v.y - sphi * v.x, v.z)


@dataclass
class LobeFit:
    """A pixel's GGX lobe as an LTC (:func:`lobe_fit`): the view's frame (``cphi``, ``sphi``: x
    towards the view's tangential direction), M^-1's entries ``minv``, its determinant ``det``
    and the scale ``A`` (RGB)."""
    cphi: mi.Float
    sphi: mi.Float
    minv: list
    det: mi.Float
    A: mi.Color3f

    def to_view(self, v: mi.Vector3f) -> mi.Vector3f:
        """A local-frame direction in the view's frame."""
        return _to_view(self.cphi, self.sphi, v)

    def density(self, v_local: mi.Vector3f) -> mi.Float:
        return _density(self.minv, self.det, self.to_view(v_local))


def lobe_fit(ltc: LtcTable, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, active: mi.Bool,
             alpha: mi.Float) -> LobeFit:
    """The LTC of the pixels' GGX lobes (roughness ``alpha``) and its scale A, calibrated at the
    LTC's peak direction by the BSDF's glossy components alone (a context whose type mask
    leaves the diffuse ones out; see the module)."""
    wi = si.wi
    m = mi.Bool(active) & (alpha > 0.0) & (wi.z > 0.0)
    st = dr.sqrt(dr.maximum(wi.x * wi.x + wi.y * wi.y, 0.0))
    ok_t = st > 1e-7
    cphi = dr.select(ok_t, wi.x / dr.select(ok_t, st, 1.0), 1.0)
    sphi = dr.select(ok_t, wi.y / dr.select(ok_t, st, 1.0), 0.0)
    M = ltc.matrix(alpha, wi.z, m)
    minv, det = _inverse(M)
    # the LTC's peak, M z (in the view's frame, turned back to the local frame); the mirror
    # direction where that lies below the horizon
    pk = dr.normalize(mi.Vector3f(M[1], 0.0, M[4]))
    w_star = mi.Vector3f(cphi * pk.x, sphi * pk.x, pk.z)
    w_star = dr.select(w_star.z > 1e-3, w_star, mi.Vector3f(-wi.x, -wi.y, wi.z))
    f_star = mi.Color3f(bsdf.eval(GLOSSY_CONTEXT, si, w_star, m))
    D_star = _density(minv, det, _to_view(cphi, sphi, w_star))
    A = dr.select(m & (D_star > 0.0), dr.maximum(f_star, 0.0) / dr.select(D_star > 0.0, D_star, 1.0), 0.0)
    return LobeFit(cphi=cphi, sphi=sphi, minv=minv, det=det, A=A)


def narrow(table, si: mi.SurfaceInteraction3f, alpha: mi.Float, idx: mi.UInt32, w: mi.Color3f,
           active: mi.Bool) -> mi.Bool:
    """Lanes of ``active`` (polygon lights ``idx`` with irradiance per unit cosine ``w`` along
    their vector irradiance) whose GGX lobe (roughness ``alpha``) is narrow against the light:
    its peak density 1/(4 pi alpha^2 cos theta_o) times the light's solid angle (about
    ``|F| = w / L``) above ``NARROW_TAU``; elsewhere the point term is as good."""
    m = mi.Bool(active) & (alpha > 0.0) & (si.wi.z > 0.0)
    off = mi.UInt32(dr.gather(mi.Point2f, table._seg, idx, m).x)
    L0 = mi.Color3f(*[dr.gather(mi.Float, table._rows, off * ROW + ROW_L + k, m) for k in range(3)])
    omega = mi.luminance(w) / dr.maximum(mi.luminance(L0), 1e-30)
    return m & (omega > NARROW_TAU * 4.0 * math.pi * alpha * alpha * si.wi.z)


def ltc_term(ltc: LtcTable, table, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, alpha: mi.Float,
             idx: mi.UInt32, d: mi.Vector3f, w: mi.Color3f, P: mi.Color3f, active: mi.Bool,
             rects: bool = True) -> mi.Color3f:
    """:math:`I` (see the module) of polygon lights ``idx`` (direction ``d`` of their vector
    irradiance, irradiance per unit cosine ``w`` along it, point term ``P``) at pixels ``si``
    whose GGX lobes (roughness ``alpha``, fitted by the table) are narrow against them
    (:func:`narrow`), on lanes ``active``; ``P`` elsewhere. ``rects``: the scene has rectangle
    lights (else every polygon is a triangle: three corners). The test, the lobe's fit and the
    integral run in a branch of their own (a loop of one pass): a packet of pixels with no
    active lane skips them."""
    def cond(todo, I):
        return todo

    def body(todo, I):
        m = narrow(table, si, alpha, idx, w, todo)
        fit = lobe_fit(ltc, si, bsdf, m, alpha)
        F, L = vector_irradiance(table, si.p, idx, m, rects, mi.Vector3f(0.0, 0.0, 1.0),
                                 warp=lambda v: _apply(fit.minv, fit.to_view(si.to_local(v))))
        integral = dr.maximum(-F.z, 0.0) * (1.0 / math.pi)       # clockwise from the emitting side
        I_m = P + fit.A * (L * integral - fit.density(si.to_local(d)) * w)
        return mi.Bool(False), mi.Color3f(dr.select(m, dr.maximum(I_m, 0.0), I))

    _, I = dr.while_loop(state=(mi.Bool(active), mi.Color3f(P)), cond=cond, body=body, labels=("todo", "I"))
    return I
