"""Compressed Radiance Caching (Vardis, Papaioannou and Gkaravelis 2014) on
a uniform grid: diffuse indirect illumination from an SH radiance field
stored in YCoCg with fewer bands for chrominance."""
from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi

from ..lights import finite
from ..sh.project import irradiance, project
from ..sh.ycocg import encoding as get_encoding
from . import volume
from .grid import GEOMETRY_FACTOR, Grid
from .march import march, visible


def _seed(seed: int, frame: int, stream: int) -> mi.UInt64:
    s = (int(seed) * 0x9E3779B97F4A7C15 + int(frame) * 0xD1B54A32D192ED03 + stream * 0xBF58476D1CE4E5B9)
    return dr.opaque(mi.UInt64, s & 0xFFFFFFFFFFFFFFFF)


def cell_rng(cells: mi.UInt32, seed: int, frame: int, stream: int) -> mi.PCG32:
    """One PCG32 stream per cell, keyed by the cell index (not by its
    position in the compacted list), so the same cell draws the same numbers
    whether or not other cells are active."""
    s = mi.PCG32(size=dr.width(cells))
    key = dr.opaque(mi.UInt32, (int(seed) * 0x9E3779B1 + int(frame) * 0x85EBCA77 + stream * 0xC2B2AE3D) & 0xFFFFFFFF)
    v0, v1 = mi.sample_tea_32(mi.UInt32(cells), key, 4)
    s.inc = (mi.UInt64(cells) << 1) | 1
    s.state = (mi.UInt64(v0) << 32) | mi.UInt64(v1)
    s.next_uint32()
    return s


def front_normal(si: mi.SurfaceInteraction3f) -> mi.Vector3f:
    """Shading normal (the side ``si.wi`` comes from)."""
    n = mi.Vector3f(si.sh_frame.n)
    return dr.select(si.wi.z < 0.0, -n, n)


class CRCCache:
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

    Parameters (defaults): ``encoding`` ("y3co1cg1"; "rgb3", "y3co3cg3",
    "y3co2cg2"), ``resolution`` (16 cells on the longest side), ``bounces``
    (1), ``occupancy`` (True; False = every cell is a cache point),
    ``vpls`` (4096), ``samples`` (64 VPLs per cell), ``secondary_rays``
    (32), ``secondary_distance`` (8 cells), ``visibility`` ("march"),
    ``march_samples`` (0 = one sample per geometry voxel; n > 0 = the
    paper's fixed sparse count), ``blend`` (0.25), ``jitter`` (0.5 cell),
    ``min_distance`` (0.5 cell), ``depth_stride`` (1 pixel; larger strides
    skip pixels whose cells the dilation may not cover), ``albedo``
    (0.5), ``presence``/``bleeding`` (1, 1), ``chroma`` ("offset", the
    paper; "ratio": constant-term chroma scaled by the directional
    luminance, see :func:`slc.sh.project.irradiance`), ``seed`` (0).
    """

    def __init__(self, scene, encoding="y3co1cg1", resolution: int = 16, bounces: int = 1,
                 occupancy: bool = True, vpls: int = 4096, samples: int = 64, secondary_rays: int = 32,
                 secondary_distance: float = 8.0, visibility: str = "march", march_samples: int = 0,
                 blend: float = 0.25, jitter: float = 0.5, min_distance: float = 0.5, depth_stride: int = 1,
                 albedo: float = 0.5, presence: float = 1.0, bleeding: float = 1.0, chroma: str = "offset",
                 seed: int = 0):
        if visibility not in ("march", "rays"):
            raise ValueError(f"visibility must be 'march' or 'rays', got '{visibility}'")
        self.scene = scene
        self.enc = get_encoding(encoding)
        self.resolution = int(resolution)
        self.bounces = max(int(bounces), 1)
        self.occupancy = bool(occupancy)
        self.n_vpl = max(int(vpls), 1)
        self.samples = max(int(samples), 1)
        self.secondary_rays = max(int(secondary_rays), 1)
        self.secondary_distance = float(secondary_distance)
        self.visibility = visibility
        self.march_samples = int(march_samples)
        self.blend = float(blend)
        self.jitter = float(jitter)
        self.min_distance = float(min_distance)
        self.depth_stride = int(depth_stride)
        self.albedo = float(albedo)
        self.presence = float(presence)
        self.bleeding = float(bleeding)
        if chroma not in ("offset", "ratio"):
            raise ValueError(f"chroma must be 'offset' or 'ratio', got '{chroma}'")
        self.chroma = chroma
        self.seed = int(seed)
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

    def settings(self) -> dict:
        return {"encoding": self.enc.name, "resolution": self.resolution, "bounces": self.bounces,
                "occupancy": self.occupancy, "vpls": self.n_vpl, "samples": self.samples,
                "visibility": self.visibility}

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
        s = mi.PCG32(size=self.n_vpl, initstate=_seed(self.seed, frame, 11),
                     initseq=dr.arange(mi.UInt64, self.n_vpl))
        u1 = s.next_float32()
        u2 = mi.Point2f(s.next_float32(), s.next_float32())
        u3 = mi.Point2f(s.next_float32(), s.next_float32())
        ray, w, _ = sc.sample_emitter_ray(0.0, u1, u2, u3, True)
        si = sc.ray_intersect(ray)
        ok = si.is_valid() & (si.wi.z > 0.0)
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, ok))
        phi = finite(dr.select(ok, mi.Color3f(w) * rho, 0.0))
        X = dr.select(ok, si.p, 0.0)
        N = front_normal(si)
        return X, N, phi

    def _first_bounce(self, frame: int, cells: mi.UInt32, X, N, phi) -> list:
        enc, grid, geo = self.enc, self.grid, self.geo
        sampler = cell_rng(cells, self.seed, frame, 12)
        Pc = grid.center(cells)
        n_vpl, h, jit = self.n_vpl, grid.h, self.jitter
        d2min = (self.min_distance * h) ** 2
        n_s = dr.opaque(mi.UInt32, self.samples)
        sc = self.scene.mi_scene
        vis_mode, ms = self.visibility, self.march_samples

        # ---------------- n_s VPL samples per cache point, in registers ----------------
        def cond(i, acc, sampler):
            return i < n_s

        def body(i, acc, sampler):
            j = dr.minimum(mi.UInt32(sampler.next_float32() * n_vpl), n_vpl - 1)
            off = mi.Vector3f(sampler.next_float32(), sampler.next_float32(), sampler.next_float32()) - 0.5
            P = Pc + off * (jit * h)
            Xk = dr.gather(mi.Point3f, X, j)
            Nk = dr.gather(mi.Vector3f, N, j)
            Pk = dr.gather(mi.Color3f, phi, j)
            v = Xk - P
            d2 = dr.squared_norm(v)
            w_dir = v * dr.rsqrt(dr.maximum(d2, 1e-20))
            cos_k = -dr.dot(Nk, w_dir)
            ok = (cos_k > 0.0) & (dr.max(Pk) > 0.0) & (d2 > 0.0)
            # --------------------------- visibility ---------------------------
            if vis_mode == "march":
                ok = visible(self.geometry, geo, P, Xk, sampler.next_float32(), ok,
                             start_offset=geo.h, end_offset=2.0 * geo.h, samples=ms)
            else:
                ray = mi.Ray3f(P, w_dir)
                ray.maxt = dr.sqrt(d2) * (1.0 - 1e-3)
                ok &= ~sc.ray_test(ray, ok)
            # --------------------------- projection ---------------------------
            L = Pk * dr.select(ok, cos_k / (math.pi * dr.maximum(d2, d2min)), 0.0)
            c = project(enc, w_dir, L)
            acc = [a + b for a, b in zip(acc, c)]
            return i + 1, acc, sampler

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc, _ = dr.while_loop(state=(mi.UInt32(0), acc0, sampler), cond=cond, body=body,
                                  labels=("i", "acc", "sampler"))
        inv = 1.0 / float(self.samples)
        return [a * inv for a in acc]

    def _secondary_bounce(self, frame: int, bounce: int, cells: mi.UInt32, vin: mi.Float) -> list:
        enc, grid, geo = self.enc, self.grid, self.geo
        sampler = cell_rng(cells, self.seed, frame, 20 + bounce)
        Pc = grid.center(cells)
        h, jit, rho_avg = grid.h, self.jitter, self.albedo
        tmax = self.secondary_distance * h
        n_sec = dr.opaque(mi.UInt32, self.secondary_rays)
        sc = self.scene.mi_scene
        vis_mode, ms = self.visibility, self.march_samples

        def cond(i, acc, sampler):
            return i < n_sec

        def body(i, acc, sampler):
            d = mi.warp.square_to_uniform_sphere(mi.Point2f(sampler.next_float32(), sampler.next_float32()))
            off = mi.Vector3f(sampler.next_float32(), sampler.next_float32(), sampler.next_float32()) - 0.5
            P = Pc + off * (jit * h)
            # ------------------- nearest visible surface point -------------------
            if vis_mode == "march":
                hit, t = march(self.geometry, geo, P, d, geo.h, tmax, sampler.next_float32(), mi.Bool(True),
                               samples=ms)
                X = P + dr.select(hit, t, 0.0) * d
                n = -d
                rho = mi.Color3f(rho_avg)
            else:
                si = sc.ray_intersect(mi.Ray3f(P, d))
                hit = si.is_valid() & (si.wi.z > 0.0)
                X = dr.select(hit, si.p, P)
                n = front_normal(si)
                rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, hit))
            # ------------- reflected radiance of the previous bounce -------------
            coeffs = self._lookup(vin, X + n * (0.5 * h), hit)
            E = irradiance(enc, coeffs, n, clamp=True, chroma=self.chroma)
            L = dr.select(hit, rho * mi.Color3f(*E) * (1.0 / math.pi), 0.0)
            c = project(enc, d, L)
            acc = [a + b for a, b in zip(acc, c)]
            return i + 1, acc, sampler

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc, _ = dr.while_loop(state=(mi.UInt32(0), acc0, sampler), cond=cond, body=body,
                                  labels=("i", "acc", "sampler"))
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
        return finite(dr.select(active, rho * E * (1.0 / math.pi), 0.0))

    def render(self, frame: int, gbuffers, timer) -> list:
        self.update(frame, gbuffers, timer)
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
