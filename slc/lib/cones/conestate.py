"""The inputs every part of the cone shading reads: the cones of the shaded pixels' entries,
gathered from the packed storage and unpacked by :func:`cone_state` into a :class:`ConeState`
(per cone the axis in world space, the half-angle, the radiance and the quantities the closed
forms and the quadrature share: live, Dirac, solid angle, density), and :class:`ShadeOptions`,
the choices of a :class:`slc.lib.cones.shading.ConeShading` (part of a frozen recording's
key). See docs/cones.md for what a cone's radiance means."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.lib.cones.packing import gather_words, unpack

ALPHA_DELTA = 1e-3                    # rad; narrower cones are Dirac cones (as in ConeParams.alpha_delta)


@dataclass
class ConeState:
    r"""The cones of the pixels' entries, as the shading reads them (docs/cones.md). Per cone
    ``c`` (lists of ``K`` arrays, one lane per pixel): ``axis`` (:math:`d_c`, world),
    ``alpha`` (:math:`\alpha_c` [rad]), ``L`` (:math:`L_c`), ``live`` (the cone exists:
    ``c < n``), ``h`` (:math:`1 - \cos\alpha_c`), ``dirac`` (a live cone narrower than
    ``ALPHA_DELTA``), ``dense`` (a live cone with a density), ``inv_omega``
    (:math:`1/\Omega_c`, 0 for Dirac cones), ``sin_alpha``, ``cos_alpha``. Per pixel: ``n``
    (the number of cones) and ``zero`` (a zero of the pixels' width). ``K`` the number of
    cone slots."""
    K: int
    axis: list
    alpha: list
    L: list
    n: mi.UInt32
    zero: mi.Float
    live: list
    h: list
    dirac: list
    dense: list
    inv_omega: list
    sin_alpha: list
    cos_alpha: list


@dataclass(frozen=True)
class ShadeOptions:
    """The shading's choices (part of a frozen recording's key), see
    :class:`slc.lib.cones.shading.ConeShading`:
    ``max_cones``, ``adaptive``, ``rotate``, ``horizon``, ``principled`` and ``conductor``
    (closed forms on), ``glossy_half``, ``compact``, ``front_only`` (:func:`cone_state`)."""
    max_cones: int
    adaptive: bool = True
    rotate: bool = True
    horizon: bool = True
    principled: bool = True
    conductor: bool = False
    glossy_half: bool = False
    compact: bool = False
    front_only: bool = False


SMALL_CAP = 0.04                      # rad; narrower caps take the planar fraction in above_fraction


def above_fraction(cos_d, alpha):
    r"""The fraction :math:`\Omega^+ / \Omega` of a cap (half-angle :math:`\alpha`, axis at angle
    :math:`d` from the normal, ``cos_d``) that lies above the horizon: exactly 1 for a cap wholly
    above it, 0 wholly below. The intersection of two caps (Tovchigrechko and Vakser 2001), one
    the hemisphere: :math:`\Omega^+ = 2 [\pi - \arccos(\cos d / \sin\alpha) - \cos\alpha
    \arccos(-\cot\alpha \cot d)]`, written with :math:`r = \sqrt{\sin^2\alpha - \cos^2 d}`
    (0 where the horizon misses the rim) as :math:`2 [\pi - \mathrm{atan2}(r, \cos d) - \cos\alpha\,
    \mathrm{atan2}(r, -\cos d \cos\alpha)]`, which keeps float32 accurate where the horizon
    touches the rim. For caps narrower than ``SMALL_CAP`` that difference cancels (error about
    1.5e-7 / alpha^2 of the cap), and they take the planar disc's segment,
    :math:`1 - (\mathrm{atan2}(r, \cos d) - r \cos d / \sin^2\alpha) / \pi` (error about
    0.05 alpha^2): within 2e-4 of the cap either way (``tests/test_cones_horizon.py``)."""
    sin_a, cos_a = dr.sincos(alpha)
    sin_d = dr.safe_sqrt(1.0 - dr.square(cos_d))
    r = dr.safe_sqrt((sin_a - cos_d) * (sin_a + cos_d))
    om = 4.0 * math.pi * dr.square(dr.sin(0.5 * alpha))
    at = dr.atan2(r, cos_d)
    sphere = 2.0 * (math.pi - at - cos_a * dr.atan2(r, -cos_d * cos_a)) * dr.rcp(dr.maximum(om, 1e-30))
    plane = 1.0 - (at - r * cos_d * dr.rcp(dr.maximum(dr.square(sin_a), 1e-30))) * (1.0 / math.pi)
    frac = dr.clip(dr.select(alpha < SMALL_CAP, plane, sphere), 0.0, 1.0)
    # wholly above: d + alpha < pi/2; wholly below: d - alpha >= pi/2 (both only for alpha < pi/2)
    narrow = alpha < 0.5 * math.pi
    above = narrow & ((cos_d * cos_a - sin_d * sin_a) > 0.0)
    below = narrow & ((cos_d * cos_a + sin_d * sin_a) <= 0.0)
    return dr.select(above, 1.0, dr.select(below, 0.0, frac))


def cap_cosine_integral(cos_d, sin_d, sin_a, cos_a):
    r"""The integral of :math:`\max(\cos\theta, 0)` over a cap of half-angle :math:`\alpha <
    \pi/2` whose axis lies at angle :math:`d` from the normal (Snyder 1996):
    :math:`(\cos d \arccos y - x \sin d \sqrt{1 - y^2}) \sin^2\alpha + \arctan(\sin d \sqrt{1 -
    y^2} / x)`, :math:`x = \cot\alpha`, :math:`y = -x \cos d / \sin d` (clipped to [-1, 1]:
    :math:`\pi \sin^2\alpha \cos d` wholly above the horizon, 0 wholly below)."""
    x = cos_a * dr.rcp(dr.maximum(sin_a, 1e-30))
    y = dr.clip(-x * cos_d * dr.rcp(dr.maximum(sin_d, 1e-30)), -1.0, 1.0)
    sy = sin_d * dr.safe_sqrt(1.0 - dr.square(y))
    return dr.maximum((cos_d * dr.acos(y) - x * sy) * dr.square(sin_a) + dr.atan2(sy, x), 0.0)


def above_mean_cosine(cos_d, alpha):
    r"""The mean of :math:`\cos\theta` over the part of a cap (half-angle :math:`\alpha`, axis at
    angle :math:`d` from the normal, ``cos_d``) above the horizon, :math:`\int_c \max(\cos\theta,
    0)\, d\omega / \Omega_c^+`: :math:`\cos d\, (1 + \cos\alpha) / 2` for a cap wholly above it,
    0 for one wholly below. Across the horizon the integral is Snyder's (a cap wider than a
    hemisphere by its complement, :math:`\pi - \int_{\bar c}`) over :math:`\Omega_c^+`
    (:func:`above_fraction`); a cap narrower than ``SMALL_CAP`` takes its planar disc's
    segment above the horizon (centre at height :math:`\cos d`, radius :math:`\sin\alpha`),
    whose mean height is :math:`\cos d + \tfrac{2}{3} (a^2 - \cos^2 d)^{3/2} / A_{seg}`."""
    sin_a, cos_a = dr.sincos(alpha)
    sin_d = dr.safe_sqrt(1.0 - dr.square(cos_d))
    wide = alpha > 0.5 * math.pi
    # a cap wider than a hemisphere: pi minus the integral over its complement (axis -d, pi - alpha)
    cd, ca = dr.select(wide, -cos_d, cos_d), dr.select(wide, -cos_a, cos_a)
    part = cap_cosine_integral(cd, sin_d, sin_a, ca)
    integral = dr.select(wide, dr.maximum(math.pi - part, 0.0), part)
    om_plus = 4.0 * math.pi * dr.square(dr.sin(0.5 * alpha)) * above_fraction(cos_d, alpha)
    sphere = integral * dr.rcp(dr.maximum(om_plus, 1e-30))
    # small caps: the planar segment above the chord at -cos_d from the disc's centre
    a2 = dr.square(sin_a)
    r2 = dr.maximum(a2 - dr.square(cos_d), 0.0)
    seg = a2 * dr.acos(dr.clip(-cos_d * dr.rsqrt(dr.maximum(a2, 1e-30)), -1.0, 1.0)) + cos_d * dr.sqrt(r2)
    plane = cos_d + (2.0 / 3.0) * r2 * dr.sqrt(r2) * dr.rcp(dr.maximum(seg, 1e-30))
    mean = dr.select(alpha < SMALL_CAP, plane, sphere)
    above = ~wide & ((cos_d * cos_a - sin_d * sin_a) > 0.0)
    below = ~wide & ((cos_d * cos_a + sin_d * sin_a) <= 0.0)
    return dr.select(above, cos_d * 0.5 * (1.0 + cos_a), dr.select(below, 0.0, dr.maximum(mean, 0.0)))


def cone_state(storage, slot, active, texel_frame, entry_frames, K, front_only: bool = False):
    """The cones of each pixel's entry, read from ``storage`` (:class:`ConeState`). With
    ``front_only`` (the update took samples above the entry's horizon only) a cone's ``L_c``
    is its radiance integrated over the part of the cone above the entry's horizon, and is
    returned as ``L_c Omega_c / Omega_c^+`` (:func:`above_fraction`) for cones across the horizon:
    the density ``L / Omega_c`` the shading spreads over the cone is then ``L_c / Omega_c^+``
    above the horizon (below it no light reaches the pixel)."""
    if entry_frames is not None:
        texel_frame = dr.gather(mi.Frame3f, entry_frames, texel_frame, active)
    D, A, L, C, n = unpack(gather_words(storage, slot, K, active), K)
    if front_only:
        for i in range(K):
            # (Dirac cones and caps wholly below keep L_c: they have no part of a cap to spread it over)
            up = above_fraction(D[i].z, A[i])
            L[i] = dr.select((A[i] >= ALPHA_DELTA) & (up > 0.0), L[i] * dr.rcp(dr.maximum(up, 1e-30)), L[i])
    Dw = [dr.normalize(texel_frame.to_world(D[i])) for i in range(K)]
    zero = dr.select(active, mi.Float(0.0), mi.Float(0.0))     # a zero of the pixels' width

    # ------------------- the cones: live, Dirac, solid angle, density -------------------
    live = [active & (n > i) for i in range(K)]
    h = [2.0 * dr.square(dr.sin(0.5 * A[i])) for i in range(K)]           # 1 - cos(alpha_c)
    delta = [live[i] & (A[i] < ALPHA_DELTA) for i in range(K)]
    area = [live[i] & ~delta[i] for i in range(K)]                        # cones with a density
    inv_om = [dr.select(area[i], dr.rcp(dr.maximum(2.0 * math.pi * h[i], 1e-30)), 0.0) for i in range(K)]
    return ConeState(K, axis=Dw, alpha=A, L=L, n=n, zero=zero, live=live, h=h, dirac=delta, dense=area,
                     inv_omega=inv_om, sin_alpha=[dr.sin(a) for a in A], cos_alpha=[dr.cos(a) for a in A])
