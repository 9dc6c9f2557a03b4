r"""Small sphere lights as "point lights with a size" for VISIBILITY records
(docs/adaptive.md, "Small sphere lights").

A sphere of radius :math:`r` and constant radiance :math:`L`, whose centre is
at distance :math:`d` in direction :math:`\omega_c` from a point :math:`x` with
normal :math:`n`, subtends a cone of half-angle :math:`\alpha`,
:math:`\sin\alpha = r/d`. While the whole sphere is above the horizon
(:math:`n\cdot\omega_c \ge \sin\alpha`) its unoccluded irradiance is exactly

.. math:: E = \pi L \sin^2\alpha \,(n\cdot\omega_c) = \pi L \frac{r^2}{d^2}\,(n\cdot\omega_c),

the irradiance of a point light of intensity :math:`I = \pi r^2 L` at the
centre. A VISIBILITY record therefore lists a small sphere light as it lists a
point light: it keeps only the visible fraction :math:`v` (the running mean of
shadow rays to sampled points on the sphere), and shading evaluates
:math:`I/d^2` at the pixel and at the light's *current* centre, so the cache
follows the light's motion without lag. Across the horizon the formula
(clamped at :math:`n\cdot\omega_c = 0`) is an approximation; lights are only
listed where :math:`\sin\alpha` is below ``max_sin`` (the sphere is small at
the entry).

Sphere lights: Mitsuba ``sphere`` area lights and triangle meshes whose
vertices lie on a sphere (at least 12 vertices, a bounding box whose sides
agree within 10%, all vertices within 10% of the largest distance from its
centre: icospheres, UV spheres), with constant radiance. A
mesh's radius is the area-equivalent :math:`r = \sqrt{A/4\pi}` (keeps the
flux :math:`\pi L A` of the mesh). Rigidly animated meshes
(:class:`slc.scene.scenes.Animated`) are followed by transforming the rest-pose
centre with the scene's current transform (:meth:`SphereLights.refresh`, on
the host, one small upload per frame).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.freeze import device_array
from slc.lib.lights.polygon_lights import PolygonLights
from slc.scene import emitter_sampling
from slc.scene.emitter_table import constant_rgb   # a constant radiance value as RGB, or None

SHELL = 0.9           # a mesh is a sphere when min / max vertex distance from its centre >= SHELL
MIN_VERTICES = 12     # ... and its bounding box is a cube (within SHELL) with at least this many vertices


SPHERE_FLAG, POLYGON_FLAG = 1, 2


class SphereLights:
    """Per-emitter table (index into ``scene.emitters()``) of the area lights a VISIBILITY
    record lists: flag (1 a sphere, 2 a polygon light), centre, radius and radiance of
    the spheres. Parameters: ``scene`` (:class:`slc.scene.scenes.Scene` or ``mi.Scene``),
    ``max_sin`` (0.3): largest :math:`r/d` at which a sphere counts as small at a point;
    ``spheres`` (True): list sphere lights; ``polygons`` (False): list the rectangles and
    small emitter meshes that are not spheres as polygon lights
    (:class:`~slc.lib.lights.polygon_lights.PolygonLights`, listed at any size: their
    irradiance is exact)."""

    def __init__(self, scene, max_sin: float = 0.3, spheres: bool = True, polygons: bool = False):
        self.scene = scene
        sc = getattr(scene, "mi_scene", scene)
        self.max_sin = float(max_sin)
        ems = list(sc.emitters())
        by_emitter = {}
        for sh in sc.shapes():
            if sh.is_emitter():
                by_emitter[id(sh.emitter())] = sh
        anim = {a.shape_id: a for a in getattr(scene, "animated", [])}
        n = len(ems)
        self.flag = np.zeros(n, np.uint32)
        self.c0 = np.zeros((n, 3))
        self.r = np.zeros(n)
        self.L = np.zeros((n, 3))
        self._anim = {}          # emitter index -> (Animated, rest centre)
        for i, e in enumerate(ems):
            if e.class_name() != "AreaLight":
                continue
            params = mi.traverse(e)
            if "radiance.value" not in params.keys():
                continue
            L = constant_rgb(params["radiance.value"])
            sh = e.get_shape()
            sh = by_emitter.get(id(e), sh) if sh is not None else None
            if L is None or sh is None:
                continue
            name = sh.class_name()
            if name == "Sphere":
                b = sh.bbox()
                lo, hi = np.array(b.min, float).ravel(), np.array(b.max, float).ravel()
                c, r = 0.5 * (lo + hi), 0.5 * float(np.min(hi - lo))
            elif sh.is_mesh():
                a = anim.get(sh.id())
                V = np.asarray(a.rest_positions, float) if a is not None else \
                    np.array(sh.vertex_positions_buffer(), float).reshape(-1, 3)
                if len(V) < MIN_VERTICES:
                    continue
                ext = V.max(axis=0) - V.min(axis=0)
                if ext.max() <= 0.0 or ext.min() < SHELL * ext.max():
                    continue            # flat or elongated (a quad's corners are equidistant too)
                c = 0.5 * (V.min(axis=0) + V.max(axis=0))
                dist = np.linalg.norm(V - c, axis=1)
                if dist.min() < SHELL * dist.max():
                    continue
                F = np.array(sh.faces_buffer(), np.int64).reshape(-1, 3)
                A = 0.5 * float(np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                               axis=1).sum())
                r = math.sqrt(A / (4.0 * math.pi))
                if a is not None:
                    self._anim[i] = (a, c)
            else:
                continue
            if r <= 0.0:
                continue
            if spheres:
                self.flag[i], self.c0[i], self.r[i], self.L[i] = SPHERE_FLAG, c, r, L
        self._list_polygons(sc, polygons)
        self.any = bool(self.flag.any())
        # no delta emitter: listed lights are all spheres, and the emitters' own
        # sample_direction (a virtual call traced in every listing loop) is never needed
        self.has_delta = any(bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) for e in ems)
        # every emitter is a delta or a sphere light
        self.listable_only = all(bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) or bool(self.flag[i])
                                 for i, e in enumerate(ems))
        self._time = object()
        self._C = self.c0.copy()
        self._upload(self.c0)
        self._set_moved(np.zeros(n, bool))
        self.refresh()

    def _upload(self, C):
        # width >= 2: a width-1 array would enter kernels as a literal (recompiled when it changes)
        pad = lambda a: np.concatenate([a, a[:1] * 0 if len(a) else np.zeros((1,) + a.shape[1:])])  # noqa: E731
        f, C, r, L = pad(self.flag), pad(C), pad(self.r), pad(self.L)
        # in memory Dr.Jit allocates: the frozen functions that read them replay after a move
        # (slc.core.freeze, "Host data that changes between calls")
        self._flag = device_array(mi.UInt32, f.astype(np.uint32))
        self._c = mi.Point3f(*[device_array(mi.Float, C[:, k].astype(np.float32)) for k in range(3)])
        self._r = device_array(mi.Float, r.astype(np.float32))
        self._L = mi.Color3f(*[device_array(mi.Float, L[:, k].astype(np.float32)) for k in range(3)])

    def _list_polygons(self, sc, polygons: bool) -> None:
        """The polygon lights (emitters not listed as spheres) and, for those on meshes, their
        vertex buffers, whose replacement is a move."""
        self.poly, self.table, self._poly_shapes = None, None, {}
        if not polygons:
            return
        self.table = emitter_sampling.for_scene(sc)
        poly = PolygonLights(self.table, exclude=set(np.flatnonzero(self.flag).tolist()))
        if not poly.any:
            return
        self.poly = poly
        self.flag[poly.flag] = POLYGON_FLAG
        ems = list(sc.emitters())
        for i in np.flatnonzero(poly.flag):
            sh = ems[i].get_shape()
            if sh is not None and sh.is_mesh():
                self._poly_shapes[int(i)] = [sh, sh.vertex_positions_buffer().index]

    def _set_moved(self, moved: np.ndarray) -> None:
        self.moved = moved
        self._moved = device_array(mi.UInt32, np.concatenate([moved, [False]]).astype(np.uint32))

    def refresh(self) -> None:
        """Move the centres of animated sphere lights to the scene's current time, and mark
        the listed lights that moved since the last call (:meth:`moved_at`: spheres whose
        centre changed, polygon lights whose mesh's vertex buffer was replaced)."""
        t = getattr(self.scene, "time", None)
        if t is self._time or (t is not None and t == self._time):
            return
        moved = np.zeros(len(self.flag), bool)
        if self._anim:
            C = self.c0.copy()
            if t is not None:
                for i, (a, c) in self._anim.items():
                    M = np.asarray(a.transform(t), float)
                    C[i] = M[:3, :3] @ c + M[:3, 3]
            moved |= (self.flag == SPHERE_FLAG) & np.any(C != self._C, axis=1)
            self._C = C
            self._upload(C)
        for i, rec in self._poly_shapes.items():
            ix = rec[0].vertex_positions_buffer().index
            moved[i] |= ix != rec[1]
            rec[1] = ix
        self._time = t
        if moved.any() or self.moved.any():
            self._set_moved(moved)

    def moved_at(self, idx: mi.UInt32, active: mi.Bool) -> mi.Bool:
        """Listed lights ``idx`` that moved in this frame (see :meth:`refresh`)."""
        return mi.Bool(active) & (dr.gather(mi.UInt32, self._moved, idx, active) != 0)

    def centre(self, i: int) -> np.ndarray:
        return np.array([self._c[k].numpy()[i] for k in range(3)])

    def light(self, p: mi.Point3f, idx: mi.UInt32, active: mi.Bool, n: mi.Vector3f | None = None,
              poly_active=True):
        """At points ``p``: (listed-light mask, direction, r/d, irradiance per unit cosine
        along the direction, RGB) of emitters ``idx``: for a sphere the direction to its
        centre and the point-light term pi L r^2 / d^2; for a polygon light (with the
        normals ``n``; r/d is 0) the direction of its vector irradiance and its exact term
        (:meth:`PolygonLights.light`), computed only where ``poly_active`` (elsewhere the
        mask is set and the direction and term are 0: the caller has them)."""
        active = mi.Bool(active)
        fl = dr.gather(mi.UInt32, self._flag, idx, active)
        is_s = active & (fl == SPHERE_FLAG)
        c = dr.gather(mi.Point3f, self._c, idx, is_s)
        r = dr.gather(mi.Float, self._r, idx, is_s)
        L = dr.gather(mi.Color3f, self._L, idx, is_s)
        v = c - p
        d2 = dr.squared_norm(v)
        inside = d2 <= r * r
        inv_d = dr.rsqrt(dr.select(d2 > 0.0, d2, 1.0))
        d = v * inv_d
        sin_a = dr.select(inside, 1.0, r * inv_d)
        E = dr.select(is_s & ~inside, L * (math.pi * r * r * inv_d * inv_d), 0.0)
        if self.poly is not None and n is not None:
            is_p = active & (fl == POLYGON_FLAG)
            _, d_p, E_p = self.poly.light(self.table, p, n, idx, is_p & poly_active)
            is_s |= is_p
            d, sin_a, E = dr.select(is_p, d_p, d), dr.select(is_p, 0.0, sin_a), dr.select(is_p, E_p, E)
        return is_s, d, sin_a, E

    def small(self, p: mi.Point3f, idx: mi.UInt32, active: mi.Bool) -> mi.Bool:
        """Lights ``idx`` a record lists at ``p``: spheres small there (r/d below
        ``max_sin``) and polygon lights."""
        is_s, _, sin_a, _ = self.light(p, idx, active)
        small = is_s & (sin_a < self.max_sin)
        if self.poly is not None:
            small |= mi.Bool(active) & (dr.gather(mi.UInt32, self._flag, idx, active) == POLYGON_FLAG)
        return small

    def polygon(self, idx: mi.UInt32, active: mi.Bool) -> mi.Bool:
        """Emitters ``idx`` that are polygon lights."""
        if self.poly is None:
            return dr.zeros(mi.Bool, dr.width(active))
        return mi.Bool(active) & (dr.gather(mi.UInt32, self._flag, idx, active) == POLYGON_FLAG)

    def arrays(self) -> list:
        """The arrays the lookups read (inputs of a frozen function)."""
        out = [self._flag, self._c, self._r, self._L, self._moved]
        if self.poly is not None:
            t = self.table
            out += [self.poly._flag, t._rows, t._seg, t._e_kind]
        return out
