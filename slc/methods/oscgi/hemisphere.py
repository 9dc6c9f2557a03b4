r"""The hemisphere grid of a primary cache entry.

An entry stores incoming radiance over its hemisphere in ``R x R`` texels of the *cosine-weighted
concentric* map: texel ``k = j R + i`` covers the square ``[i/R, (i+1)/R) x [j/R, (j+1)/R)`` of
Mitsuba's ``square_to_cosine_hemisphere`` (Shirley-Chiu concentric mapping, then a lift to the
hemisphere). The map preserves the projected solid angle, so every texel covers exactly
:math:`\pi / R^2` of it:

.. math:: \int_{\Omega_k} \cos\theta\, d\omega = \frac{\pi}{R^2},
          \qquad E = \int_{H^2} L \cos\theta\, d\omega = \frac{\pi}{R^2}\sum_k \bar L_k,

where :math:`\bar L_k` is the cosine-weighted mean radiance of texel k, which a jittered
cosine-distributed ray through the texel estimates without bias. Irradiance (diffuse shading) is
therefore a plain sum of the texels, with no SH truncation; a direction maps back to its texel with
the inverse map (``cosine_hemisphere_to_square``), used for BSDF-sampled (glossy) shading.

Directions are in the entry's frame ``mi.Frame3f(n)`` with n the entry's shading normal: the
frame depends on n alone, so a pixel rebuilds it from the entry's normal.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi


class HemiGrid:
    """``R x R`` cosine-weighted hemisphere texels (``R = res``, 8 as in the journal)."""

    def __init__(self, res: int = 8):
        self.res = int(res)
        self.n = self.res * self.res
        self.texel_weight = math.pi / self.n       # projected solid angle of one texel

    def direction(self, k: mi.UInt32, u: mi.Point2f) -> mi.Vector3f:
        """Local direction of the point ``u`` in [0,1)^2 inside texel ``k`` (cosine-distributed
        over the texel when u is uniform)."""
        R = self.res
        i, j = k % R, k // R
        sq = mi.Point2f((mi.Float(i) + u.x) / R, (mi.Float(j) + u.y) / R)
        return mi.warp.square_to_cosine_hemisphere(sq)

    def texel(self, d_local: mi.Vector3f) -> mi.UInt32:
        """Texel of a local direction in the upper hemisphere (clamped to the grid)."""
        R = self.res
        sq = mi.warp.cosine_hemisphere_to_square(d_local)
        return self.texel_index(mi.Int32(dr.floor(sq.x * R)), mi.Int32(dr.floor(sq.y * R)))

    def texel_index(self, i, j) -> mi.UInt32:
        """Texel of the (clamped) grid coordinates i, j."""
        R = self.res
        return mi.UInt32(dr.clip(j, 0, R - 1) * R + dr.clip(i, 0, R - 1))
