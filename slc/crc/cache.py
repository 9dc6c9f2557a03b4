"""Compressed Radiance Caching (Vardis, Papaioannou and Gkaravelis 2014) on
a uniform grid: diffuse indirect illumination from an SH radiance field
stored in YCoCg with fewer bands for chrominance."""
from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi

from ..keys import STREAM_CRC, keyed_rng
from ..methods import Method, Param
from ..sh.project import irradiance, project
from ..sh.ycocg import ENCODINGS
from ..sh.ycocg import encoding as get_encoding
from . import volume
from .grid import GEOMETRY_FACTOR, Grid
from .march import march, visible

# Random streams of the stages (offsets of STREAM_CRC; keys: light path or cell index)
_LIGHTS, _FIRST_BOUNCE, _SECONDARY = 11, 12, 20


def front_normal(si: mi.SurfaceInteraction3f) -> mi.Vector3f:
    """Shading normal (the side ``si.wi`` comes from)."""
    n = mi.Vector3f(si.sh_frame.n)
    return dr.select(si.wi.z < 0.0, -n, n)


class CRCCache(Method):
    r"""Grid radiance cache with chrominance-compressed SH (CRC).

    Per frame:

    1. *Occupancy*: cache points (cell centres) exist only in occupied
       cells. With one bounce, the depth occupancy volume (the cells of the
       viewers' G-buffer points, every ``depth_stride``-th pixel); with more,
       the cells that hold geometry voxels. Both dilated by one cell, so that
       the trilinear stencil of every shaded point (offset by half a cell
       along its normal) only reads occupied cells.
    2. *Lights* (the RSM of the paper): ``vpls`` light paths from the
       emitters (``scene.sample_emitter_ray``); each first hit X_k with
       normal n_k, diffuse albedo rho_k and sample flux Phi_k is a virtual
       point light of intensity Phi_k rho_k cos / pi.
    3. *First bounce*: at each occupied cell, ``samples`` VPLs k drawn
       uniformly, received at the cell centre jittered by ``jitter`` cells:

       .. math:: \lambda_{lm}(P) = \frac{1}{n_s}\sum_k
                 \frac{\Phi_k \rho_k \max(0, n_k\cdot(-\omega_k))}
                      {\pi \max(|X_k-P|^2, d_{min}^2)} V(X_k, P)\, Y_{lm}(\omega_k)

       projected in the encoding's colour space (YCoCg with fewer chroma
       bands, or RGB). V by ray marching in the geometry volume
       (``visibility="march"``) or by Mitsuba shadow rays (``"rays"``).
    4. *Secondary bounces* (``bounces`` > 1): from each occupied cell,
       ``secondary_rays`` uniform directions are marched up to
       ``secondary_distance`` cells; at the hit X, a virtual diffuse surface
       facing P reflects L = rho E(X, -omega) / pi, with E reconstructed from
       the previous bounce's volume and rho = ``albedo`` (with Mitsuba rays:
       the true normal and albedo of the hit):
       :math:`\lambda^{(i)} = \frac{4\pi}{n}\sum_k L(X_k, -\omega_k) Y(\omega_k)`.
       Two volumes hold the last bounce's input and output (swapped) and a
       third the running sum.
    5. *Blend*: exponential moving average ``cache = a new + (1 - a) cache``
       with ``a = blend`` for cells that were occupied in the previous frame
       (others start from the new value).
    6. *Reconstruct* at the G-buffer points: trilinear interpolation of the
       coefficients at x + n h / 2, closed-form irradiance (Ramamoorthi and
       Hanrahan), back to RGB (``presence`` scales Y, ``bleeding`` CoCg),
       outgoing diffuse radiance rho(x) E / pi.

    Random numbers: one stream per light path and per cell
    (:func:`slc.keys.keyed_rng`, keyed by the path or *cell* index, not by
    the position in the compacted list of active cells), so the same cell
    draws the same numbers whether or not other cells are active.

    Output: *indirect* light only (``output = "indirect"``): direct light
    is not cached; compose with a direct-light method or the ground truth.
    """

    name = "crc"
    output = "indirect"
    params = (
        Param("encoding", "y3co1cg1", "SH encoding of the radiance", choices=tuple(ENCODINGS)),
        Param("resolution", 16, "grid cells on the scene box's longest side", lo=2, hi=256),
        Param("bounces", 1, "indirect bounces (1: depth occupancy; more: geometry occupancy)", lo=1, hi=8),
        Param("occupancy", True, "cache points only in occupied cells (0: every cell)"),
        Param("vpls", 4096, "light paths (VPLs) per frame", lo=1, hi=4_000_000),
        Param("samples", 64, "VPL samples per cache point", lo=1, hi=1 << 16),
        Param("secondary_rays", 32, "directions per cache point for bounces 2+", lo=1, hi=1 << 16),
        Param("secondary_distance", 8.0, "march length of secondary rays [cells]", lo=0.25, hi=1024.0),
        Param("visibility", "march", "visibility by geometry-volume march or Mitsuba rays",
              choices=("march", "rays")),
        Param("march_samples", 0, "samples per marched ray (0: one per geometry voxel; paper 8-12)",
              lo=0, hi=4096),
        Param("blend", 0.25, "temporal blend weight of the new estimate", lo=0.01, hi=1.0),
        Param("jitter", 0.5, "jitter of the sample point around the cell centre [cells]", lo=0.0, hi=1.0),
        Param("min_distance", 0.5, "distance clamp of VPL contributions [cells]", lo=0.0, hi=8.0),
        Param("depth_stride", 1, "pixel stride of the depth occupancy", lo=1, hi=64),
        Param("albedo", 0.5, "grey albedo of marched secondary hits", lo=0.0, hi=1.0),
        Param("presence", 1.0, "scale of Y (artistic control)", lo=0.0, hi=16.0),
        Param("bleeding", 1.0, "scale of Co, Cg (artistic control)", lo=0.0, hi=16.0),
        Param("chroma", "offset", "chroma decoding: the paper's offset or the constant-chromaticity ratio",
              choices=("offset", "ratio")),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.enc = get_encoding(self.encoding)
        self.grid = Grid.around(scene.bbox_min, scene.bbox_max, self.resolution)
        self.geo = self.grid.finer(GEOMETRY_FACTOR)
        self.voxelize_ms = 0.0
        self._voxel_time = None
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        n = self.grid.n_cells
        self.cache = dr.zeros(mi.Float, self.enc.n * n)
        self.hist = dr.zeros(mi.UInt32, n)
        self.geometry = None
        self.geo_occ = None
        self.active = None
        self.n_active = 0
        self._volumes = 1

    def _voxelize(self) -> None:
        t = self.scene.time
        if self.geometry is not None and (not self.scene.dynamic or t == self._voxel_time):
            return
        t0 = time.perf_counter()
        self.geometry = volume.voxelize(volume.scene_triangles(self.scene.mi_scene), self.geo)
        self.geo_occ = volume.dilate(volume.occupancy_from_geometry(self.geometry, self.grid), self.grid)
        dr.eval(self.geometry, self.geo_occ)
        dr.sync_thread()
        self.voxelize_ms = (time.perf_counter() - t0) * 1e3
        self._voxel_time = t

    # ----------------------------------------------------------- coefficients
    def _lookup(self, vol: mi.Float, q: mi.Point3f, active: mi.Bool) -> list:
        """Trilinearly interpolated coefficients of ``vol`` at points q."""
        n = self.grid.n_cells
        acc = [mi.Float(0.0) for _ in range(self.enc.n)]
        for idx, w in self.grid.trilinear(q):
            for c in range(self.enc.n):
                acc[c] += w * dr.gather(mi.Float, vol, idx + c * n, active)
        return acc

    def _store(self, coeffs: list, cells: mi.UInt32) -> mi.Float:
        n = self.grid.n_cells
        vol = dr.zeros(mi.Float, self.enc.n * n)
        for c in range(self.enc.n):
            dr.scatter(vol, coeffs[c], cells + c * n)
        return vol

    # --------------------------------------------------------------- stages
    def _occupancy(self, gbuffers) -> mi.UInt32:
        if not self.occupancy:
            return dr.arange(mi.UInt32, self.grid.n_cells)
        if self.bounces == 1:
            occ = volume.dilate(volume.depth_occupancy(self.grid, gbuffers, self.depth_stride), self.grid)
        else:
            occ = self.geo_occ
        return dr.compress(occ != 0)

    def _lights(self, frame: int):
        """Virtual point lights: first hits of light paths (the RSM samples)."""
        sc = self.scene.mi_scene
        s = keyed_rng(dr.arange(mi.UInt32, self.vpls), self.seed, frame, STREAM_CRC + _LIGHTS)
        u1 = s.next_float32()
        u2 = mi.Point2f(s.next_float32(), s.next_float32())
        u3 = mi.Point2f(s.next_float32(), s.next_float32())
        ray, w, _ = sc.sample_emitter_ray(0.0, u1, u2, u3, True)
        si = sc.ray_intersect(ray)
        ok = si.is_valid() & (si.wi.z > 0.0)
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, ok))
        phi = dr.select(ok, mi.Color3f(w) * rho, 0.0)
        X = dr.select(ok, si.p, 0.0)
        N = front_normal(si)
        return X, N, phi

    def _integrate(self, frame: int, cells: mi.UInt32, stream: int, count: int, sample) -> list:
        """Sum over ``count`` samples per cache point, in registers, of
        ``project(enc, omega, L)`` for ``(omega, L) = sample(Pc, sampler)``
        (``Pc``: the cell centres; one keyed stream per cell)."""
        enc = self.enc
        sampler = keyed_rng(cells, self.seed, frame, STREAM_CRC + stream)
        Pc = self.grid.center(cells)
        n = dr.opaque(mi.UInt32, count)

        def cond(i, acc, sampler):
            return i < n

        def body(i, acc, sampler):
            omega, L = sample(Pc, sampler)
            acc = [a + b for a, b in zip(acc, project(enc, omega, L))]
            return i + 1, acc, sampler

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc, _ = dr.while_loop(state=(mi.UInt32(0), acc0, sampler), cond=cond, body=body,
                                  labels=("i", "acc", "sampler"))
        return acc

    def _jittered(self, Pc: mi.Point3f, sampler: mi.PCG32) -> mi.Point3f:
        off = mi.Vector3f(sampler.next_float32(), sampler.next_float32(), sampler.next_float32()) - 0.5
        return Pc + off * (self.jitter * self.grid.h)

    def _first_bounce(self, frame: int, cells: mi.UInt32, X, N, phi) -> list:
        geo, n_vpl = self.geo, self.vpls
        d2min = (self.min_distance * self.grid.h) ** 2
        sc = self.scene.mi_scene

        # ---------------- one VPL sample at a jittered cache point ----------------
        def sample(Pc, sampler):
            j = dr.minimum(mi.UInt32(sampler.next_float32() * n_vpl), n_vpl - 1)
            P = self._jittered(Pc, sampler)
            Xk = dr.gather(mi.Point3f, X, j)
            Nk = dr.gather(mi.Vector3f, N, j)
            Pk = dr.gather(mi.Color3f, phi, j)
            v = Xk - P
            d2 = dr.squared_norm(v)
            w_dir = v * dr.rsqrt(dr.maximum(d2, 1e-20))
            cos_k = -dr.dot(Nk, w_dir)
            ok = (cos_k > 0.0) & (dr.max(Pk) > 0.0) & (d2 > 0.0)
            # --------------------------- visibility ---------------------------
            if self.visibility == "march":
                ok = visible(self.geometry, geo, P, Xk, sampler.next_float32(), ok,
                             start_offset=geo.h, end_offset=2.0 * geo.h, samples=self.march_samples)
            else:
                ray = mi.Ray3f(P, w_dir)
                ray.maxt = dr.sqrt(d2) * (1.0 - 1e-3)
                ok &= ~sc.ray_test(ray, ok)
            return w_dir, Pk * dr.select(ok, cos_k / (math.pi * dr.maximum(d2, d2min)), 0.0)

        acc = self._integrate(frame, cells, _FIRST_BOUNCE, self.samples, sample)
        inv = 1.0 / float(self.samples)
        return [a * inv for a in acc]

    def _secondary_bounce(self, frame: int, bounce: int, cells: mi.UInt32, vin: mi.Float) -> list:
        geo, h = self.geo, self.grid.h
        tmax = self.secondary_distance * h
        sc = self.scene.mi_scene

        # ------------- one direction from a jittered cache point -------------
        def sample(Pc, sampler):
            d = mi.warp.square_to_uniform_sphere(mi.Point2f(sampler.next_float32(), sampler.next_float32()))
            P = self._jittered(Pc, sampler)
            # ------------------- nearest visible surface point -------------------
            if self.visibility == "march":
                hit, t = march(self.geometry, geo, P, d, geo.h, tmax, sampler.next_float32(), mi.Bool(True),
                               samples=self.march_samples)
                X = P + dr.select(hit, t, 0.0) * d
                n = -d
                rho = mi.Color3f(self.albedo)
            else:
                si = sc.ray_intersect(mi.Ray3f(P, d))
                hit = si.is_valid() & (si.wi.z > 0.0)
                X = dr.select(hit, si.p, P)
                n = front_normal(si)
                rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, hit))
            # ------------- reflected radiance of the previous bounce -------------
            coeffs = self._lookup(vin, X + n * (0.5 * h), hit)
            E = irradiance(self.enc, coeffs, n, clamp=True, chroma=self.chroma)
            return d, dr.select(hit, rho * mi.Color3f(*E) * (1.0 / math.pi), 0.0)

        acc = self._integrate(frame, cells, _SECONDARY + bounce, self.secondary_rays, sample)
        w = 4.0 * math.pi / float(self.secondary_rays)
        return [a * w for a in acc]

    def _blend(self, cells: mi.UInt32, coeffs: list) -> None:
        n = self.grid.n_cells
        had = dr.gather(mi.UInt32, self.hist, cells) != 0
        a = dr.select(had, self.blend, 1.0)
        for c in range(self.enc.n):
            old = dr.gather(mi.Float, self.cache, cells + c * n)
            dr.scatter(self.cache, dr.fma(a, coeffs[c] - old, old), cells + c * n)
        hist = dr.zeros(mi.UInt32, n)
        dr.scatter(hist, mi.UInt32(1), cells)
        self.hist = hist

    # ------------------------------------------------------------------ frame
    def update(self, frame: int, gbuffers, timer) -> None:
        """Rebuild the cache for this frame (all stages but reconstruction)."""
        self._voxelize()
        with timer.stage("occupancy") as st:
            cells = self._occupancy(gbuffers)
            st.outputs(cells)
        self.active = cells
        self.n_active = dr.width(cells)
        with timer.stage("lights") as st:
            X, N, phi = self._lights(frame)
            st.outputs(X, N, phi)
        with timer.stage("bounce1") as st:
            coeffs = self._first_bounce(frame, cells, X, N, phi)
            st.outputs(*coeffs)
        self._volumes = 2
        if self.bounces > 1:
            with timer.stage("bounce2+") as st:
                total = list(coeffs)
                inc = self._store(coeffs, cells)
                for b in range(2, self.bounces + 1):
                    new = self._secondary_bounce(frame, b, cells, inc)
                    total = [t + x for t, x in zip(total, new)]
                    if b < self.bounces:
                        inc = self._store(new, cells)
                coeffs = total
                st.outputs(*coeffs)
            self._volumes = 4 if self.bounces > 2 else 3
        with timer.stage("blend") as st:
            self._blend(cells, coeffs)
            st.outputs(self.cache, self.hist)

    def shade(self, gb) -> mi.Color3f:
        """Outgoing diffuse indirect radiance rho E / pi at the G-buffer points."""
        si, active = gb.si, gb.valid & (gb.si.wi.z > 0.0)
        n = front_normal(si)
        coeffs = self._lookup(self.cache, si.p + n * (0.5 * self.grid.h), active)
        E = mi.Color3f(*irradiance(self.enc, coeffs, n, self.presence, self.bleeding, chroma=self.chroma))
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, active))
        return dr.select(active, rho * E * (1.0 / math.pi), 0.0)

    def render(self, ctx, gbuffers, timer) -> list:
        """Indirect light per viewer: the cache update of frame ``ctx.frame``
        (shared by all viewers), then reconstruction at each G-buffer."""
        self.update(ctx.frame, gbuffers, timer)
        with timer.stage("reconstruct") as st:
            out = [self.shade(gb) for gb in gbuffers]
            st.outputs(*out)
        return out

    # ---------------------------------------------------------------- figures
    def occupancy_ratio(self) -> float:
        return self.n_active / max(self.grid.n_cells, 1)

    def memory_bytes(self) -> int:
        """Coefficient volumes (EMA + working volumes, dense over the grid,
        4 bytes per coefficient) + the geometry and occupancy bit volumes."""
        n = self.grid.n_cells
        coeff = 4 * self.enc.n * n * self._volumes
        bits = (self.geo.n_cells + 2 * n) // 8
        return coeff + bits

    def stats(self) -> dict:
        return {"occupancy_ratio": self.occupancy_ratio(), "active_cells": self.n_active,
                "cells": self.grid.n_cells, "coefficients": self.enc.n, "voxelize_ms": self.voxelize_ms}
