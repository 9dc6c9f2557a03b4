r"""Uniform sampling of the solid angle a triangle subtends (Arvo 1995).

Seen from a point :math:`x`, a triangle :math:`(p_0, p_0 + e_0, p_0 + e_1)`
covers the spherical triangle with vertices :math:`a, b, c` (unit vectors
from :math:`x`) and solid angle :math:`\Omega = \alpha + \beta + \gamma - \pi`
(the angles at its vertices). :func:`sample_triangle` draws a direction
uniformly in it, :math:`p(\omega) = 1/\Omega`, and returns the point where it
meets the triangle's plane: the light sample :math:`L_e \Omega` has no
:math:`d^2/\cos\theta_y` factor, whose variance dominates area sampling of a
light that is large or close (a rectangle of 120 m seen from 2 m:
about 150 times the squared mean per sample).

Where :math:`\Omega < 3 \cdot 10^{-4}` sr the angle sum is :math:`\pi` to within a
few float32 ulps and the map degenerates; where :math:`\Omega > 6.22` sr
(nearly a hemisphere: the point almost in the triangle's plane) the arcs
degenerate. There ``use`` is false and the caller samples by area, whose
density is nearly constant in solid angle for a small triangle. The test is a
function of :math:`x` and the triangle alone, so a density evaluated later
makes the same choice. The solid angle of the test is Van Oosterom and
Strackee's :math:`\tan(\Omega/2) = |a \cdot (b \times c)| / (1 + a\cdot b + b\cdot c + c\cdot a)`,
stable for small triangles.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

OMEGA_MIN = 3e-4    # sr: below, area sampling (float32 cancellation in the angle sum)
OMEGA_MAX = 6.22    # sr: above, area sampling (a point nearly in the triangle's plane)


def _angle_between(v1: mi.Vector3f, v2: mi.Vector3f) -> mi.Float:
    """Angle between unit vectors, accurate near 0 and pi (no acos of a dot product)."""
    d = dr.dot(v1, v2)
    return dr.select(d < 0.0, math.pi - 2.0 * dr.safe_asin(0.5 * dr.norm(v1 + v2)),
                     2.0 * dr.safe_asin(0.5 * dr.norm(v2 - v1)))


def _orthogonal(v: mi.Vector3f, w: mi.Vector3f) -> mi.Vector3f:
    """The unit part of ``v`` orthogonal to unit ``w`` (Gram-Schmidt)."""
    o = v - dr.dot(v, w) * w
    n2 = dr.squared_norm(o)
    return o * dr.rsqrt(dr.select(n2 > 0.0, n2, 1.0))


def solid_angle(x: mi.Point3f, p0: mi.Point3f, e0: mi.Vector3f, e1: mi.Vector3f) -> mi.Float:
    """Solid angle of the triangle seen from ``x`` (Van Oosterom and Strackee)."""
    a, b, c = dr.normalize(p0 - x), dr.normalize(p0 + e0 - x), dr.normalize(p0 + e1 - x)
    num = dr.abs(dr.dot(a, dr.cross(b, c)))
    den = 1.0 + dr.dot(a, b) + dr.dot(b, c) + dr.dot(c, a)
    return 2.0 * dr.atan2(num, den)


def sample_triangle(x: mi.Point3f, p0: mi.Point3f, e0: mi.Vector3f, e1: mi.Vector3f, u: mi.Point2f,
                    active: mi.Bool):
    """A direction uniform in the triangle's solid angle from ``x``: (point on the
    triangle's plane, solid angle Omega, use, ok). ``use``: the triangle is sampled
    so (``active`` and its solid angle within (OMEGA_MIN, OMEGA_MAX), a function of
    ``x`` and the triangle alone); ``ok``: ``use`` and the sample is a point of the
    plane (false only where rounding breaks the map: such a sample is lost, not
    drawn by area, so that the density stays 1/Omega)."""
    use = mi.Bool(active)
    omega_vs = solid_angle(x, p0, e0, e1)
    use &= (omega_vs > OMEGA_MIN) & (omega_vs < OMEGA_MAX)

    # ------------------------ the spherical triangle's angles and area ------------------------
    a, b, c = dr.normalize(p0 - x), dr.normalize(p0 + e0 - x), dr.normalize(p0 + e1 - x)
    n_ab, n_bc, n_ca = dr.normalize(dr.cross(a, b)), dr.normalize(dr.cross(b, c)), dr.normalize(dr.cross(c, a))
    alpha = _angle_between(n_ab, -n_ca)
    beta = _angle_between(n_bc, -n_ab)
    gamma = _angle_between(n_ca, -n_bc)
    area_pi = alpha + beta + gamma
    omega = area_pi - math.pi
    ok = use & dr.isfinite(omega) & (omega > 0.0)

    # ------------------------ the sub-triangle of area u.x * Omega: its vertex c' ------------------------
    ap_pi = dr.fma(u.x, omega, math.pi)
    s_ap, c_ap = dr.sincos(ap_pi)
    s_al, c_al = dr.sincos(alpha)
    sin_phi = s_ap * c_al - c_ap * s_al
    cos_phi = c_ap * c_al + s_ap * s_al
    k1 = cos_phi + c_al
    k2 = sin_phi - s_al * dr.dot(a, b)
    den = (k2 * sin_phi + k1 * cos_phi) * s_al
    cos_bp = dr.clip((k2 + (k2 * cos_phi - k1 * sin_phi) * c_al) / dr.select(den != 0.0, den, 1.0), -1.0, 1.0)
    sin_bp = dr.safe_sqrt(1.0 - dr.square(cos_bp))
    cp = cos_bp * a + sin_bp * _orthogonal(c, a)

    # ------------------------ along the arc from b to c': the direction ------------------------
    cos_t = 1.0 - u.y * (1.0 - dr.dot(cp, b))
    sin_t = dr.safe_sqrt(1.0 - dr.square(cos_t))
    w = cos_t * b + sin_t * _orthogonal(cp, b)

    # ------------------------ where it meets the triangle's plane ------------------------
    n = dr.cross(e0, e1)
    wn = dr.dot(w, n)
    t = dr.dot(p0 - x, n) / dr.select(wn != 0.0, wn, 1.0)
    ok &= (wn != 0.0) & (t > 0.0) & dr.isfinite(t)
    return dr.fma(w, t, x), omega, use, ok
