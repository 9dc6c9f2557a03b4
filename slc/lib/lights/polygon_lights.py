r"""Polygon lights for VISIBILITY records: emitters whose unoccluded irradiance has a
closed form at any point (docs/adaptive.md, "Polygon lights").

A planar polygon of constant radiance :math:`L`, seen from a point :math:`x` with normal
:math:`n`, gives the irradiance of Lambert's formula,

.. math:: E(x) = L\, n \cdot \mathbf F, \qquad
          \mathbf F = \frac12 \sum_{\text{edges } (a, b)} \Theta_{ab}\,
          \frac{\hat a \times \hat b}{\lVert \hat a \times \hat b \rVert},

with :math:`\hat a, \hat b` the unit vectors from :math:`x` to an edge's ends,
:math:`\Theta_{ab}` the angle between them (``atan2(|a x b|, a . b)``: accurate for nearly
equal directions) and the vertices taken clockwise as seen from the emitting side (the
polygon then lies along :math:`\mathbf F`). The polygon is first clipped to the upper
hemisphere of :math:`n`: each edge is cut where it crosses the tangent plane, and the
cut ends are joined by an edge in that plane (a convex polygon crosses it at most twice).
A light made of several triangles (a rectangle is two; a cube twelve) sums its
triangles that face :math:`x`; for a convex light that is exact (no face hides another
from :math:`x`).

A VISIBILITY record lists such a light with a direction and an irradiance per unit
cosine along it, as it lists a point light: :math:`\mathbf d = \mathbf F / \lVert\mathbf F\rVert`
and :math:`L \lVert \mathbf F \rVert`, so that a Lambertian BSDF evaluated along
:math:`\mathbf d` gives exactly :math:`\rho/\pi\, E(x)`; other BSDFs see the light as a
point in the direction of its vector irradiance. The geometry is read from the scene's
emitter table (its rows hold each triangle's corner and edges, and the rectangles'),
which follows moving emitter meshes.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.emitter_table import MESH, RECT, ROW, ROW_E0, ROW_E1, ROW_L, ROW_P0

MAX_TRIANGLES = 16      # largest emitter mesh (in triangles) listed as a polygon light


def _edge(a: mi.Vector3f, b: mi.Vector3f, active: mi.Bool) -> mi.Vector3f:
    """Theta_ab (a x b)/|a x b| for the directions to an edge's ends (0 for a point edge)."""
    ua = a * dr.rsqrt(dr.maximum(dr.squared_norm(a), 1e-30))
    ub = b * dr.rsqrt(dr.maximum(dr.squared_norm(b), 1e-30))
    cr = dr.cross(ua, ub)
    s = dr.norm(cr)
    th = dr.atan2(s, dr.dot(ua, ub))
    return mi.Vector3f(dr.select(active & (s > 0.0), cr * (th / dr.select(s > 0.0, s, 1.0)), 0.0))


def clipped_vector_irradiance(V: list, n: mi.Vector3f, active: mi.Bool) -> mi.Vector3f:
    r""":math:`\frac12 \sum \Theta\, \hat a \times \hat b / |\hat a \times \hat b|` over the edges of the
    polygon ``V`` (vectors from the shading point, in order) clipped to the half space
    ``n . v > 0``; its sign follows the vertices' winding."""
    F = dr.zeros(mi.Vector3f, dr.width(active))
    exit_p = dr.zeros(mi.Vector3f, dr.width(active))
    enter_p = dr.zeros(mi.Vector3f, dr.width(active))
    has_exit, has_enter = mi.Bool(False), mi.Bool(False)
    h = [dr.dot(v, n) for v in V]
    k = len(V)
    for i in range(k):
        a, b, ha, hb = V[i], V[(i + 1) % k], h[i], h[(i + 1) % k]
        ina, inb = ha > 0.0, hb > 0.0
        den = ha - hb
        t = ha / dr.select(den != 0.0, den, 1.0)
        c = dr.fma(b - a, t, a)                       # where the edge meets the tangent plane
        out_, in_ = ina & ~inb, ~ina & inb
        F += _edge(dr.select(in_, c, a), dr.select(out_, c, b), active & (ina | inb))
        exit_p, has_exit = dr.select(out_, c, exit_p), has_exit | out_
        enter_p, has_enter = dr.select(in_, c, enter_p), has_enter | in_
    F += _edge(exit_p, enter_p, active & has_exit & has_enter)
    return mi.Vector3f(0.5 * F)


def vector_irradiance(table, p: mi.Point3f, idx: mi.UInt32, active: mi.Bool, rects: bool, n: mi.Vector3f,
                      warp=None):
    """(F, L): :func:`clipped_vector_irradiance` summed over the triangles of light ``idx`` (its
    rows of the emitter table; a rectangle's one row) that face ``p``, clipped to the half space
    of ``n``, and the light's radiance. ``warp``: a map applied
    to the vectors from ``p`` to the corners before the formula (the LTC's ``M^-1`` in
    :mod:`slc.lib.lights.polygon_ltc`). ``rects``: the scene has rectangle lights (else
    every polygon is a triangle: three corners, no zero-length fourth edge, whose fused cross
    product is a rounding error, not 0). The sum runs clockwise from the emitting side."""
    seg = dr.gather(mi.Point2f, table._seg, idx, active)
    off, cnt = mi.UInt32(seg.x), mi.UInt32(seg.y)
    rect = active & (dr.gather(mi.UInt32, table._e_kind, idx, active) == RECT)

    def cond(t, F, L):
        return active & (t < cnt)

    def body(t, F, L):
        m = active & (t < cnt)
        r = off + t
        get = lambda c: dr.gather(mi.Float, table._rows, r * ROW + c, m)   # noqa: E731
        p0 = mi.Point3f(get(ROW_P0), get(ROW_P0 + 1), get(ROW_P0 + 2))
        e0 = mi.Vector3f(get(ROW_E0), get(ROW_E0 + 1), get(ROW_E0 + 2))
        e1 = mi.Vector3f(get(ROW_E1), get(ROW_E1 + 1), get(ROW_E1 + 2))
        Lt = mi.Color3f(get(ROW_L), get(ROW_L + 1), get(ROW_L + 2))
        # the emitting side is +e0 x e1 (as the sampler's one-sided density): seen from
        # there, p0, p0 + e0, (p0 + e0 + e1,) p0 + e1 run clockwise
        front = m & (dr.dot(p - p0, dr.cross(e0, e1)) > 0.0)
        a = mi.Vector3f(p0 - p)
        if rects:
            V = [a, a + e0, mi.Vector3f(dr.select(rect, a + e0 + e1, a + e1)), a + e1]
        else:
            V = [a, a + e0, a + e1]
        # the formula in a branch of its own (a loop of one pass): a packet of points that all
        # see the triangle's back, as half of a closed mesh's, skips it
        def b_cond(todo, F):
            return todo

        def b_body(todo, F):
            Vw = [warp(v) for v in V] if warp is not None else V
            Ft = clipped_vector_irradiance(Vw, n, todo)
            return mi.Bool(False), mi.Vector3f(F + dr.select(todo, Ft, 0.0))

        _, F = dr.while_loop(state=(mi.Bool(front), mi.Vector3f(F)), cond=b_cond, body=b_body, labels=("todo", "F"))
        return t + 1, mi.Vector3f(F), mi.Color3f(dr.select(m, Lt, L))

    N = dr.width(active)
    _, F, L = dr.while_loop(state=(mi.UInt32(0), dr.zeros(mi.Vector3f, N), dr.zeros(mi.Color3f, N)),
                            cond=cond, body=body, labels=("t", "F", "L"))
    return F, L


class PolygonLights:
    """The polygon lights of a scene: rectangles and emitter meshes of at most
    MAX_TRIANGLES triangles with constant radiance, as the emitter table ``table``
    (:class:`slc.scene.emitter_sampling.EmitterSampler` over every emitter) holds them.
    ``exclude``: emitter indices not to list (the sphere lights). ``flag[i]`` is true for
    the listed emitters (index into ``scene.emitters()``)."""

    def __init__(self, table, exclude=()):
        if list(table.subset) != list(range(len(table.emitters))):
            raise ValueError("PolygonLights needs an emitter table over every emitter")
        n = len(table.emitters)
        seg = np.array(table._seg).reshape(-1, 2)
        kind = np.array(table._e_kind)
        self.flag = np.zeros(n, bool)
        for i in range(n):
            if i in exclude:
                continue
            if kind[i] == RECT or (kind[i] == MESH and 0 < seg[i, 1] <= MAX_TRIANGLES):
                self.flag[i] = True
        self.any = bool(self.flag.any())
        self.rects = bool((self.flag & (kind[:n] == RECT)).any())    # (vector_irradiance)
        f = np.concatenate([self.flag, [False]]).astype(np.uint32)   # width >= 2 (see SphereLights)
        self._flag = mi.UInt32(f)
        dr.make_opaque(self._flag)

    def light(self, table, p: mi.Point3f, n: mi.Vector3f, idx: mi.UInt32, active: mi.Bool):
        """At points ``p`` with normals ``n``: (polygon mask, direction d of the vector
        irradiance, irradiance per unit cosine along d, RGB) of emitters ``idx``: the light's
        exact unoccluded irradiance is ``E cos(n, d)``, 0 below the horizon or behind it."""
        active = mi.Bool(active)
        is_p = active & (dr.gather(mi.UInt32, self._flag, idx, active) != 0)
        F, L = vector_irradiance(table, p, idx, is_p, self.rects, n)
        F = -F                      # clockwise from the emitting side: the sum points away from it
        f = dr.norm(F)
        ok = is_p & (f > 0.0) & (dr.dot(F, n) > 0.0)
        d = F / dr.select(ok, f, 1.0)
        return is_p, dr.select(ok, d, n), dr.select(ok, L * f, 0.0)
