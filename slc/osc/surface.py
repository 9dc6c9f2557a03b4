"""The surface point of every cache entry (texel = surface point).

An entry's position and normal come from the texel itself, never from the
pixel that asked for it (otherwise two viewers would update one entry from
two points): once per new entry, the triangle of its island that contains
the texel centre (else the nearest one) is found by a brute-force search in
the island's 2D texture space, and its (triangle, barycentrics) are kept per
slot; every frame the active entries' ``SurfaceInteraction3f`` is rebuilt
from them with ``PreliminaryIntersection3f.compute_surface_interaction``.

Analytic shapes (sphere, disk, cylinder): the same 2D search runs over the
island's triangles of the shape's parameter-space grid; the barycentrics
interpolate the triangle's corner (u, v), two Newton steps move (u, v) so
that the real surface point (closed form) projects onto the texel centre,
and the slot keeps (u, v) instead of barycentrics; every frame the entry's
interaction is Mitsuba's ``compute_surface_interaction`` at that point of
the real surface (never on the tessellation).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.freeze import FrozenFunction
from slc.core.structs import drjit_struct
from slc.osc.blocks import extend_array
from slc.osc.layout import CacheLayout

# the layout tables that surface_interaction reads (passed to the frozen function as inputs)
_SI_TABLES = ("d_isl_shape", "d_tri_base")
_SI_ANALYTIC_TABLES = ("d_shape_analytic", "d_shape_kind", "d_shape_xform")

EDGE_INSET = 1e-4     # border entries of analytic shapes stay this far (in u, v) inside the domain
BORDER_INSET = 1e-3   # clamped border entries move this fraction of the way to the triangle's centroid


@drjit_struct
@dataclass
class ClosestLoop:
    """The state of :meth:`TexelPoints.lookup`'s search over an island's triangles (one lane per
    entry): ``i`` the next triangle (``count``: done), ``best_d`` the squared 2D distance to the
    closest triangle so far (0: inside it), ``best_j`` that triangle, ``bu``, ``bv`` the Mitsuba
    barycentrics of its closest point."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    best_d: mi.Float = field(default_factory=mi.Float)
    best_j: mi.UInt32 = field(default_factory=mi.UInt32)
    bu: mi.Float = field(default_factory=mi.Float)
    bv: mi.Float = field(default_factory=mi.Float)


class TexelPoints:
    """Per slot: the global triangle and Mitsuba barycentrics of the entry's
    surface point (analytic shapes: the shape's (u, v) instead of
    barycentrics; 12 bytes), for a pool of ``capacity`` slots."""

    def __init__(self, layout: CacheLayout, capacity: int):
        self.layout = layout
        self.slot_tri = dr.zeros(mi.UInt32, capacity)
        self.slot_b = dr.zeros(mi.Point2f, capacity)

    def resize(self, capacity: int) -> None:
        if dr.width(self.slot_tri) >= capacity:
            return
        self.slot_tri = extend_array(self.slot_tri, 0, capacity, mi.UInt32)
        self.slot_b = mi.Point2f(extend_array(self.slot_b.x, 0, capacity, mi.Float),
                                 extend_array(self.slot_b.y, 0, capacity, mi.Float))

    def place(self, slots, isl, lvl, tx, ty) -> None:
        """Find and keep the surface point of new entries (texel centres)."""
        size = mi.Float(mi.UInt32(1) << lvl)
        c = mi.Point2f((mi.Float(tx) + 0.5) * size, (mi.Float(ty) + 0.5) * size)
        tri, b = self.lookup(isl, c)
        if self.layout.has_analytic:
            b = self.analytic_params(isl, tri, b, c)
        dr.scatter(self.slot_tri, tri, slots)
        dr.scatter(self.slot_b, b, slots)

    def interactions(self, slots, isl, frozen: "EntryInteractions | None" = None) -> mi.SurfaceInteraction3f:
        """The surface interaction of every slot (its own point, ``wi`` along the
        normal); with ``frozen`` (an :class:`EntryInteractions`) traced once and
        replayed: the same values, without tracing Mitsuba's per-shape
        ``compute_surface_interaction`` every frame."""
        if frozen is not None:
            L = self.layout
            names = _SI_TABLES + (_SI_ANALYTIC_TABLES if L.has_analytic else ())
            return frozen(L.mi_scene, bool(L.has_analytic), tuple(getattr(L, k) for k in names), self.slot_tri,
                          self.slot_b, mi.UInt32(slots), mi.UInt32(isl))
        tri = dr.gather(mi.UInt32, self.slot_tri, slots)
        b = dr.gather(mi.Point2f, self.slot_b, slots)
        return self.surface_interaction(isl, tri, b)

    def lookup(self, isl, c):
        """Triangle of island ``isl`` containing the 2D point ``c`` (island
        level-0 texel coordinates), else the nearest one; returns the global
        triangle and Mitsuba barycentrics (u, v) of the closest point. Brute
        force over the island's triangles (<= max_triangles) in a symbolic
        loop; the first triangle in island order wins ties, so the answer
        does not depend on who asked."""
        L = self.layout
        start = dr.gather(mi.UInt32, L.d_isl_start, isl)
        count = dr.gather(mi.UInt32, L.d_isl_count, isl)
        n = dr.width(isl)
        i = dr.zeros(mi.UInt32, n)
        best_d = dr.full(mi.Float, dr.inf, n)
        best_j = mi.UInt32(start)
        bu, bv = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        uv = L.d_sorted_uv

        def cond(st: ClosestLoop):
            return st.i < count

        def body(st: ClosestLoop):
            j = start + st.i
            p0 = dr.gather(mi.Point2f, uv, j * 3 + 0)
            p1 = dr.gather(mi.Point2f, uv, j * 3 + 1)
            p2 = dr.gather(mi.Point2f, uv, j * 3 + 2)
            d2, u, v = _closest_on_triangle(c, p0, p1, p2)
            better = d2 < st.best_d
            st.best_d = dr.select(better, d2, st.best_d)
            st.best_j = dr.select(better, j, st.best_j)
            st.bu = dr.select(better, u, st.bu)
            st.bv = dr.select(better, v, st.bv)
            st.i = dr.select(st.best_d <= 0.0, count, st.i + 1)   # inside: done
            return (st,)

        st, = dr.while_loop((ClosestLoop(i, best_d, best_j, bu, bv),), cond, body)
        best_d, best_j, bu, bv = st.best_d, st.best_j, st.bu, st.bv
        tri = dr.gather(mi.UInt32, L.d_sorted_tri, best_j)
        # a centre outside every triangle is clamped onto an edge; move it a
        # little towards the centroid, so that an entry never sits exactly on an
        # edge where another surface meets it (room corners: its shadow rays
        # started on the wall's plane and were blocked at t = 0)
        out = best_d > 0.0
        bu = dr.select(out, bu * (1.0 - BORDER_INSET) + BORDER_INSET / 3.0, bu)
        bv = dr.select(out, bv * (1.0 - BORDER_INSET) + BORDER_INSET / 3.0, bv)
        return tri, mi.Point2f(bu, bv)

    def analytic_params(self, isl, tri, b, c, steps: int = 2):
        """For entries of analytic shapes: the (u, v) parameters whose surface
        point projects onto the texel centre ``c`` (island level-0 texel
        coordinates). Start: the grid triangle's corner (u, v) interpolated
        with the barycentrics ``b``; then ``steps`` Newton steps on
        ``project(p(u, v)) = c`` with the Jacobian from ``dp_du``, ``dp_dv``
        (each step at most one grid cell; skipped where it is singular, e.g. a
        pole). Non-periodic parameters stay in [EDGE_INSET, 1 - EDGE_INSET]: an
        entry exactly on a rim that touches another surface (a cylinder standing
        on a floor) had every shadow ray blocked by that surface at t = 0.
        Mesh entries keep ``b``."""
        L = self.layout
        shape_idx = dr.gather(mi.UInt32, L.d_isl_shape, isl)
        ana = dr.gather(mi.Bool, L.d_shape_analytic, shape_idx)
        c0 = dr.gather(mi.Point2f, L.d_tri_param, tri * 3 + 0, ana)
        c1 = dr.gather(mi.Point2f, L.d_tri_param, tri * 3 + 1, ana)
        c2 = dr.gather(mi.Point2f, L.d_tri_param, tri * 3 + 2, ana)
        uv = c0 * (1.0 - b.x - b.y) + c1 * b.x + c2 * b.y
        nu = mi.Float(dr.gather(mi.UInt32, L.d_grid_dims, shape_idx * 2 + 0, ana))
        nv = mi.Float(dr.gather(mi.UInt32, L.d_grid_dims, shape_idx * 2 + 1, ana))
        pu = dr.gather(mi.Bool, L.d_grid_periodic, shape_idx * 2 + 0, ana)
        pv = dr.gather(mi.Bool, L.d_grid_periodic, shape_idx * 2 + 1, ana)
        a0 = dr.gather(mi.Vector3f, L.d_isl_axes, isl * 2 + 0, ana)
        a1 = dr.gather(mi.Vector3f, L.d_isl_axes, isl * 2 + 1, ana)
        inv_ts = 1.0 / L.texel_size
        for _ in range(steps):
            p, dp_du, dp_dv = L.analytic_point(shape_idx, uv, ana)
            r = c - L.project(isl, p, ana)
            j00, j01 = dr.dot(a0, dp_du) * inv_ts, dr.dot(a0, dp_dv) * inv_ts
            j10, j11 = dr.dot(a1, dp_du) * inv_ts, dr.dot(a1, dp_dv) * inv_ts
            det = j00 * j11 - j01 * j10
            scale = dr.maximum(dr.maximum(dr.abs(j00), dr.abs(j01)), dr.maximum(dr.abs(j10), dr.abs(j11)))
            ok = ana & (dr.abs(det) > 1e-6 * scale * scale) & dr.isfinite(det)
            inv = dr.select(ok, dr.rcp(det), 0.0)
            du = dr.clip((j11 * r.x - j01 * r.y) * inv, -1.0 / nu, 1.0 / nu)
            dv = dr.clip((j00 * r.y - j10 * r.x) * inv, -1.0 / nv, 1.0 / nv)
            u, v = uv.x + du, uv.y + dv
            u = dr.select(pu, u, dr.clip(u, EDGE_INSET, 1.0 - EDGE_INSET))
            v = dr.select(pv, v, dr.clip(v, EDGE_INSET, 1.0 - EDGE_INSET))
            uv = dr.select(ok, mi.Point2f(u, v), uv)
        return dr.select(ana, uv, b)

    def surface_interaction(self, isl, tri, b) -> mi.SurfaceInteraction3f:
        return surface_interaction(self.layout, isl, tri, b)


class _Tables:
    """What :func:`surface_interaction` reads of a layout, from the frozen
    function's inputs."""

    def __init__(self, names, arrays, mi_scene, has_analytic):
        self.__dict__.update(zip(names, arrays))
        self.mi_scene, self.has_analytic = mi_scene, has_analytic

    def analytic_point(self, sidx, uv, active=True):
        return CacheLayout.analytic_point(self, sidx, uv, active)


class EntryInteractions(FrozenFunction):
    """:meth:`TexelPoints.interactions` traced once and replayed (``dr.freeze``):
    rebuilding the active entries' ``SurfaceInteraction3f`` calls every cached
    shape's ``compute_surface_interaction`` (a virtual call), whose tracing was
    most of the cache's per-frame host time. Inputs (:func:`_interactions_kernel`):
    the Mitsuba scene, whether analytic shapes are cached, the layout tables it
    reads, the per-slot surface points and the frame's active slots and islands
    (their number may change between calls without a new recording). The kernel
    is a module function without closure, so that nothing of the cache is held in
    a reference cycle; the recording policy is :class:`slc.core.freeze.FrozenFunction`'s."""

    def __init__(self, freeze: bool = True, max_recordings: int = 4):
        # per-lane: slots, isl (a pure function: padded lanes are cut from the output)
        super().__init__(_interactions_kernel, freeze, max_recordings, lanes=(5, 6))

    def __del__(self):
        # free the recordings with their owner (refcount), not whenever the garbage
        # collector gets to them: freeing a recording while another frozen function
        # records aborts the process
        if self.frozen:
            self.kernel.clear()


def _interactions_kernel(mi_scene, has_analytic, tables, slot_tri, slot_b, slots, isl):
    """The interactions of ``slots`` (island ``isl``) from the per-slot surface
    points; ``tables`` the layout's arrays named in ``_SI_TABLES`` (and
    ``_SI_ANALYTIC_TABLES`` when ``has_analytic``). Reads no array's width."""
    names = _SI_TABLES + (_SI_ANALYTIC_TABLES if has_analytic else ())
    L = _Tables(names, tables, mi_scene, has_analytic)
    tri = dr.gather(mi.UInt32, slot_tri, slots)
    b = dr.gather(mi.Point2f, slot_b, slots)
    return surface_interaction(L, isl, tri, b)


def surface_interaction(L, isl, tri, b) -> mi.SurfaceInteraction3f:
    """The interaction at (triangle, barycentrics) or, for analytic shapes,
    (u, v) of every lane (see the module); ``L`` a layout (or :class:`_Tables`)."""
    # nothing reads an array's width (the frozen function replays for any number of lanes)
    shape_idx = dr.gather(mi.UInt32, L.d_isl_shape, isl)
    pi = dr.zeros(mi.PreliminaryIntersection3f)
    pi.t = mi.Float(1.0)
    pi.valid = mi.Bool(True)
    pi.prim_uv = mi.Point2f(b)
    pi.prim_index = tri - dr.gather(mi.UInt32, L.d_tri_base, shape_idx)
    pi.shape_index = shape_idx
    pi.shape = dr.gather(mi.ShapePtr, L.mi_scene.shapes_dr(), shape_idx)
    ray = mi.Ray3f(mi.Point3f(0.0), mi.Vector3f(0.0, 0.0, 1.0))
    if L.has_analytic:
        # analytic shapes: a ray that starts on the closed-form point (t = 0)
        # and Mitsuba's own compute_surface_interaction (which reprojects p
        # onto the surface and sets uv, frames, derivatives); the disk reads
        # its object-space (x, y) from prim_uv
        ana = dr.gather(mi.Bool, L.d_shape_analytic, shape_idx)
        p, dp_du, dp_dv = L.analytic_point(shape_idx, b, ana)
        kind = dr.gather(mi.UInt32, L.d_shape_kind, shape_idx, ana)
        sphi, cphi = dr.sincos(dr.two_pi * b.y)
        disk = ana & (kind == 2)
        pi.prim_uv = dr.select(disk, mi.Point2f(b.x * cphi, b.x * sphi), pi.prim_uv)
        pi.t = dr.select(ana, 0.0, pi.t)
        n = dr.normalize(dr.cross(dp_du, dp_dv))
        ray = mi.Ray3f(dr.select(ana, p, ray.o), dr.select(ana, -n, ray.d))
    si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)     # "viewer" along the shading normal
    return si


def _closest_on_triangle(c, p0, p1, p2):
    """Squared 2D distance from c to triangle (p0, p1, p2) and the
    barycentrics (u, v) (weights of p1, p2) of the closest point."""
    e0, e1, q = p1 - p0, p2 - p0, c - p0
    det = e0.x * e1.y - e0.y * e1.x
    ok = dr.abs(det) > 1e-12
    inv = dr.select(ok, dr.rcp(det), 0.0)
    u = (q.x * e1.y - q.y * e1.x) * inv
    v = (e0.x * q.y - e0.y * q.x) * inv
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)

    def seg(a, d):
        s = dr.clip(dr.dot(c - a, d) / dr.maximum(dr.squared_norm(d), 1e-20), 0.0, 1.0)
        return dr.squared_norm(c - (a + s * d)), s

    d01, s01 = seg(p0, e0)            # (u, v) = (s, 0)
    d02, s02 = seg(p0, e1)            # (0, s)
    d12, s12 = seg(p1, p2 - p1)       # (1 - s, s)
    best, bu, bv = d01, s01, mi.Float(0.0)
    m = d02 < best
    best, bu, bv = dr.select(m, d02, best), dr.select(m, 0.0, bu), dr.select(m, s02, bv)
    m = d12 < best
    best, bu, bv = dr.select(m, d12, best), dr.select(m, 1.0 - s12, bu), dr.select(m, s12, bv)
    best = dr.select(inside, 0.0, best)
    bu = dr.select(inside, u, bu)
    bv = dr.select(inside, v, bv)
    return best, bu, bv
