"""Analytic shapes' layout grids: a tessellation of a shape's own (u, v) parameter square (numpy set-up).

Analytic shapes (Mitsuba's ``sphere``, ``disk``, ``cylinder``) have no
triangles: :func:`tessellate_analytic` makes a grid in the shape's own
(u, v) parameter space, evaluated on the surface with
the shapes' closed forms (:func:`analytic_point`), used only to build their islands (the
cache's layout); entries are evaluated on the real surface (see
``docs/osc.md``, "Analytic shapes").
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np


# Analytic shapes with a cache layout: class name -> (grid cells along u, along v,
# u periodic, v periodic). Mitsuba's parameterizations: sphere u = phi / 2 pi,
# v = theta / pi; cylinder u = phi / 2 pi, v = z (straight: one row); disk
# u = r, v = phi / 2 pi. 64 cells around: 5.6 degrees per cell, so islands
# (30 degrees) are made of whole cells and a chord is within 0.12 % of the radius.
ANALYTIC_GRIDS = {"Sphere": (64, 32, True, False), "Cylinder": (64, 1, True, False),
                  "Disk": (1, 64, False, True)}
ANALYTIC_KIND = {"Sphere": 0, "Cylinder": 1, "Disk": 2}


@dataclass
class ParamGrid:
    """Tessellation of an analytic shape's (u, v) square in ``nu x nv``
    cells, two triangles each: cell (i, j) holds grid triangles
    ``2 (j nu + i)`` (corners (i, j), (i+1, j), (i, j+1)) and ``+1``
    (corners (i+1, j), (i+1, j+1), (i, j+1)); a parameter point (u, v) lies
    in the second one when ``frac(u nu) + frac(v nv) > 1``. Triangles that
    collapse on the surface (the poles of a sphere, the centre of a disk)
    are dropped; ``grid_tri`` maps every grid triangle to a kept triangle
    (itself, or the other triangle of its cell).

    ``V`` (welded positions), ``F`` (kept triangles), ``corner_param``
    (K, 3, 2) the (u, v) of each kept triangle's corners, ``grid_tri``
    (2 nu nv,) kept-triangle index, ``periodic`` (u, v) flags."""
    nu: int
    nv: int
    V: np.ndarray
    F: np.ndarray
    corner_param: np.ndarray
    grid_tri: np.ndarray
    periodic: tuple


def shape_to_world(shape) -> np.ndarray:
    """4x4 object-to-world matrix of an analytic shape (Mitsuba folds the
    sphere's centre and radius, the cylinder's p0, p1 and radius into it: the
    object-space shapes are the unit sphere, the unit cylinder z in [0, 1] and
    the unit disk)."""
    M = np.array(mi.traverse(shape)["to_world"].matrix, np.float64)
    return M.reshape(4, 4) if M.size == 16 else M[..., 0].reshape(4, 4)


def analytic_point(kind, M, uv):
    """Closed-form surface point of analytic shapes (Dr.Jit, vectorised):
    ``kind`` 0 sphere (u = phi / 2 pi, v = theta / pi), 1 cylinder
    (u = phi / 2 pi, v = z), 2 disk (u = r, v = phi / 2 pi), Mitsuba's own
    parameterizations; ``M`` the object-to-world ``mi.Matrix4f``. Returns
    world (p, dp_du, dp_dv). (``Shape.eval_parameterization`` finds the point
    by tracing a ray and misses on some lanes: 19 of 100k interior points of
    a transformed cylinder, most of its rims.)"""
    u, v = mi.Float(uv.x), mi.Float(uv.y)
    sph, cyl = kind == 0, kind == 1
    phi = dr.two_pi * dr.select(kind == 2, v, u)
    sp, cp = dr.sincos(phi)
    st, ct = dr.sincos(dr.pi * v)
    # object space
    p_s = mi.Vector3f(st * cp, st * sp, ct)
    p_c = mi.Vector3f(cp, sp, v)
    p_d = mi.Vector3f(u * cp, u * sp, 0.0)
    du_s = dr.two_pi * mi.Vector3f(-st * sp, st * cp, 0.0)
    dv_s = dr.pi * mi.Vector3f(ct * cp, ct * sp, -st)
    du_c = dr.two_pi * mi.Vector3f(-sp, cp, 0.0)
    dv_c = mi.Vector3f(0.0, 0.0, 1.0)
    du_d = mi.Vector3f(cp, sp, 0.0)
    dv_d = dr.two_pi * u * mi.Vector3f(-sp, cp, 0.0)
    lp = dr.select(sph, p_s, dr.select(cyl, p_c, p_d))
    ldu = dr.select(sph, du_s, dr.select(cyl, du_c, du_d))
    ldv = dr.select(sph, dv_s, dr.select(cyl, dv_c, dv_d))

    def lin(a):
        return mi.Vector3f(M[0][0] * a.x + M[0][1] * a.y + M[0][2] * a.z,
                           M[1][0] * a.x + M[1][1] * a.y + M[1][2] * a.z,
                           M[2][0] * a.x + M[2][1] * a.y + M[2][2] * a.z)
    p = mi.Point3f(lin(lp) + mi.Vector3f(M[0][3], M[1][3], M[2][3]))
    return p, lin(ldu), lin(ldv)


def tessellate_analytic(shape) -> ParamGrid | None:
    """The parameter-space grid of a Mitsuba analytic shape (world space,
    :func:`analytic_point`), or None when the shape's type has no grid (see
    ``ANALYTIC_GRIDS``)."""
    spec = ANALYTIC_GRIDS.get(shape.class_name())
    if spec is None:
        return None
    nu, nv, pu, pv = spec
    gu, gv = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv)   # (nv+1, nu+1)
    uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
    M = mi.Matrix4f(shape_to_world(shape).astype(np.float32))
    p, _, _ = analytic_point(mi.UInt32(ANALYTIC_KIND[shape.class_name()]), M,
                             mi.Point2f(mi.Float(uv[:, 0].astype(np.float32)), mi.Float(uv[:, 1].astype(np.float32))))
    P = np.array(p, np.float64)
    P = P.T if P.shape[0] == 3 and P.shape[1] != 3 else P
    if not np.isfinite(P).all():
        return None
    # weld coinciding grid vertices (seams, poles, centre) by rounded position
    ext = float(np.linalg.norm(P.max(0) - P.min(0))) or 1.0
    key = np.round(P / (1e-6 * ext)).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    V = P[first]
    vid = lambda i, j: j * (nu + 1) + i                                   # noqa: E731
    ii, jj = np.meshgrid(np.arange(nu), np.arange(nv))
    ii, jj = ii.ravel(), jj.ravel()                                       # cell c = j nu + i
    g0 = np.stack([vid(ii, jj), vid(ii + 1, jj), vid(ii, jj + 1)], axis=1)
    g1 = np.stack([vid(ii + 1, jj), vid(ii + 1, jj + 1), vid(ii, jj + 1)], axis=1)
    G = np.stack([g0, g1], axis=1).reshape(-1, 3)                         # grid triangle 2c + s
    Fw = inv[G]
    keep = (Fw[:, 0] != Fw[:, 1]) & (Fw[:, 1] != Fw[:, 2]) & (Fw[:, 0] != Fw[:, 2])
    kept_idx = np.cumsum(keep) - 1
    other = np.arange(len(G)) ^ 1
    if not np.all(keep | keep[other]):
        return None                                                        # a whole cell collapsed
    grid_tri = np.where(keep, kept_idx, kept_idx[other]).astype(np.int64)
    return ParamGrid(nu=nu, nv=nv, V=V, F=Fw[keep], corner_param=uv[G[keep]], grid_tri=grid_tri,
                     periodic=(pu, pv))
