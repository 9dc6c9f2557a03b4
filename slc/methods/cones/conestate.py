"""The inputs every part of the cone shading reads: the cones of the shaded pixels' entries,
gathered from the packed storage and unpacked by :func:`cone_state` into a :class:`ConeState`
(per cone the axis in world space, the half-angle, the radiance and the quantities the closed
forms and the quadrature share: live, Dirac, solid angle, density), and :class:`ShadeOptions`,
the choices of a :class:`slc.methods.cones.shading.ConeShading` (part of a frozen recording's
key). See docs/cones.md for what a cone's radiance means."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.methods.cones.packing import gather_words, unpack

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
    :class:`slc.methods.cones.shading.ConeShading`:
    ``max_cones``, ``adaptive``, ``rotate``, ``horizon``, ``principled`` and ``conductor``
    (closed forms on), ``glossy_half``, ``compact``."""
    max_cones: int
    adaptive: bool = True
    rotate: bool = True
    horizon: bool = True
    principled: bool = True
    conductor: bool = False
    glossy_half: bool = False
    compact: bool = False


def cone_state(storage, slot, active, texel_frame, entry_frames, K):
    """The cones of each pixel's entry, read from ``storage`` (:class:`ConeState`)."""
    if entry_frames is not None:
        texel_frame = dr.gather(mi.Frame3f, entry_frames, texel_frame, active)
    D, A, L, C, n = unpack(gather_words(storage, slot, K, active), K)
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
