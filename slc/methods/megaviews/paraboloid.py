r"""Dual paraboloid omnidirectional maps [BAS02], one parameterisation for all views.

The front paraboloid looks down +x, the back one down -x, in world
orientation for every view (Sec. 3.1: the globally consistent
parameterisation is what makes shared rendering possible). A unit
direction ``d`` maps to

.. math:: (u, w) = \frac{(d_y, d_z)}{1 + |d_x|} \in [-1, 1]^2,

face 0 if ``d_x >= 0`` else face 1. The mapping is conformal with
:math:`d\rho/d\alpha = 1/(1+\cos\alpha)` (``alpha`` the angle to the face
axis), which gives the projected size of a bounding sphere (Fig. 6).

A map of resolution ``R`` holds a mip pyramid (for multi-pixel filling,
Sec. 3.2): level ``m`` has 2 faces of ``(R >> m)^2`` texels; texel ``(f, x,
y)`` of level ``m`` lives at ``offset(m) + (f * Rm + y) * Rm + x``. Depth is
the distance to the map's centre of projection; empty texels hold
:data:`EMPTY` (finite, so no Inf reaches anything).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

EMPTY = 1e30


class Layout:
    """Texel layout of one dual-paraboloid map pyramid of resolution ``R``."""

    def __init__(self, R: int):
        R = int(R)
        if R < 1 or R & (R - 1):
            raise ValueError(f"map resolution must be a power of two, got {R}")
        self.R = R
        self.levels = int(round(math.log2(R))) + 1
        self.res = [R >> m for m in range(self.levels)]
        self.offset = [0]
        for r in self.res:
            self.offset.append(self.offset[-1] + 2 * r * r)
        self.texels = self.offset[-1]        # per map, all levels
        self.base = 2 * R * R                # level 0 only

    def index(self, level, face, tx, ty, Rm):
        return level + (face * Rm + ty) * Rm + tx


def face_uv(v: mi.Vector3f):
    """(face, u, w) of a (not necessarily unit) direction."""
    L = dr.norm(v)
    ax = dr.abs(v.x)
    den = dr.maximum(L + ax, 1e-20)
    face = dr.select(v.x >= 0.0, mi.UInt32(0), mi.UInt32(1))
    return face, v.y / den, v.z / den


def texel(v: mi.Vector3f, Rm):
    """(face, tx, ty) of direction ``v`` at a level of resolution ``Rm``
    (a Python int or a UInt32 array)."""
    face, u, w = face_uv(v)
    Rf = mi.Float(Rm)
    tx = mi.UInt32(dr.clip(dr.floor((u + 1.0) * 0.5 * Rf), 0.0, Rf - 1.0))
    ty = mi.UInt32(dr.clip(dr.floor((w + 1.0) * 0.5 * Rf), 0.0, Rf - 1.0))
    return face, tx, ty


def direction(face: mi.UInt32, tx: mi.UInt32, ty: mi.UInt32, Rm: int) -> mi.Vector3f:
    """Unit direction through the centre of a texel (inverse mapping)."""
    u = (mi.Float(tx) + 0.5) / Rm * 2.0 - 1.0
    w = (mi.Float(ty) + 0.5) / Rm * 2.0 - 1.0
    r2 = u * u + w * w
    inv = 1.0 / (1.0 + r2)
    x = (1.0 - r2) * inv
    x = dr.select(face == 0, x, -x)
    return mi.Vector3f(x, 2.0 * u * inv, 2.0 * w * inv)


def projected_size(vs: mi.Vector3f, r_s: mi.Float, r_v: mi.Float, R) -> mi.Float:
    r"""Conservative projected diameter in texels (level 0) of a sphere of
    radius ``r_s`` at offset ``vs`` from a view-node centre, over every view
    within ``r_v`` of that centre (Fig. 6): the distance is shortened by
    ``r_v`` (Fig. 7b), the half angle is ``delta = asin(r_s / d')`` and the
    mapping's scale is taken at the far edge of the sphere,
    ``size = delta * R / (1 + cos(min(alpha + delta, pi/2)))``.
    Returns a large value when the view bound reaches the sphere."""
    L = dr.norm(vs)
    d = L - r_v
    near = d <= r_s * 1.0001
    delta = dr.asin(dr.clip(r_s / dr.maximum(d, 1e-20), 0.0, 1.0))
    alpha = dr.atan2(dr.sqrt(vs.y * vs.y + vs.z * vs.z), dr.abs(vs.x))
    a = dr.minimum(alpha + delta, 0.5 * math.pi)
    size = delta * mi.Float(R) / (1.0 + dr.cos(a))
    return dr.select(near, 1e9, size)
