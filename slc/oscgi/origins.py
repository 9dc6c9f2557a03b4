r"""Where a primary cache entry's rays start (``origin``, session gi11): the slides' "decoupled
triangle ids" artefact, measured.

``texel`` (default): from the entry's own surface point (the texel centre's point on its own
triangle, found per entry by :meth:`slc.osc.surface.TexelPoints.lookup`; the "decoupled" ids).

``representative``: a deliberately naive origin, the slides' "triangle is a bad representative"
("triangle id resolution not high enough: bad triangle for the cache"): one triangle stands for
the whole island (its first triangle in island order) and each entry's rays start from the
entry's point projected onto that triangle's plane,

.. math:: o = p - ((p - c) \cdot n_c)\, n_c,

c the triangle's centroid and n_c its geometric normal. On a flat island this is the entry's own
point; on a bent one (islands span up to 30 degrees of normal) the origin leaves the surface,
into the air or behind it (inside geometry). Analytic shapes (spheres, disks, cylinders) keep
their own point (their islands' triangles are a parameter grid, not the surface).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..osc.surface import surface_interaction


def representative_points(cache, active: mi.UInt32, p: mi.Point3f) -> mi.Point3f:
    """The naive origins of the entries at slots ``active`` (own points ``p``) of the on-surface
    cache ``cache`` (see the module)."""
    L = cache.layout
    isl = cache.pool.entry_texels(active)[0]
    tri = dr.gather(mi.UInt32, L.d_sorted_tri, dr.gather(mi.UInt32, L.d_isl_start, isl))
    sr = surface_interaction(L, isl, tri, mi.Point2f(1.0 / 3.0, 1.0 / 3.0))
    o = p - dr.dot(p - sr.p, sr.n) * sr.n
    if L.has_analytic:
        ana = dr.gather(mi.Bool, L.d_shape_analytic, dr.gather(mi.UInt32, L.d_isl_shape, isl))
        o = dr.select(ana, p, o)
    o = mi.Point3f(o)
    dr.eval(o)
    return o


def backface_share(n: mi.Vector3f, d: mi.Vector3f, valid: mi.Bool) -> tuple[int, int]:
    """(rays whose hit is the back of a surface, valid hits): a ray that starts inside closed
    geometry (or behind a wall) first meets a surface from behind."""
    back = valid & (dr.dot(n, d) > 0.0)
    return int(dr.count(back)[0]), int(dr.count(valid)[0])
