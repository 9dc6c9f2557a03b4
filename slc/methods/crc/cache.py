"""Compressed Radiance Caching (Vardis, Papaioannou and Gkaravelis 2014) on
a uniform grid: diffuse indirect illumination from an SH radiance field
stored in YCoCg with fewer bands for chrominance."""
from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.core.keys import STREAM_CRC, keyed_rng
from slc.methods import Method, Param
from slc.methods.sh.project import irradiance, project
from slc.methods.sh.ycocg import ENCODINGS
from slc.methods.sh.ycocg import encoding as get_encoding
from slc.methods.crc import volume
from slc.methods.crc.grid import GEOMETRY_FACTOR, Grid
from slc.methods.crc.march import march, visible

# Random streams of the stages (offsets of STREAM_CRC; keys: light path, RSM
# frame, (cell, sample) pair or cell index)
_LIGHTS, _FIRST_BOUNCE, _ROTATION, _RSM, _SECONDARY = 11, 12, 13, 14, 20
#: the paper's depth-occupancy stride s, at a 1 MPixel frame buffer
PAPER_STRIDE = 10


def front_normal(si: mi.SurfaceInteraction3f) -> mi.Vector3f:
    """Shading normal (the side ``si.wi`` comes from)."""
    n = mi.Vector3f(si.sh_frame.n)
    return dr.select(si.wi.z < 0.0, -n, n)


def halton(n: int, base: int) -> np.ndarray:
    """The first ``n`` points (index 0..n-1) of the radical inverse in ``base``."""
    out = np.zeros(n)
    i = np.arange(n)
    f = 1.0 / base
    while np.any(i > 0):
        out += (i % base) * f
        i //= base
        f /= base
    return out


class CRCCache(Method):
    r"""Grid radiance cache with chrominance-compressed SH (CRC).

    Per frame (each step one timed stage; ``*_march`` stages do not depend
    on the encoding, ``*_project``, ``blend`` and ``reconstruct`` scale with
    its coefficient count):

    1. ``occupancy``: cache points (cell centres) exist only in occupied
       cells. With one bounce, the depth occupancy volume (the cells of the
       viewers' G-buffer points, every s-th pixel in x and y: the paper's
       s = 10 at 1 MPixel, scaled by the frame's side, i.e. 1 at 128x72 and 2
       at 320x180, or ``depth_stride``); with more, the cells that hold geometry voxels.
       Both dilated by one cell, so that the trilinear stencil of every
       shaded point (offset by half a cell along its normal) reads occupied
       cells.
    2. ``lights`` (light injection): the virtual point lights X_k with
       normal n_k, diffuse albedo rho_k and sample flux Phi_k (intensity
       Phi_k rho_k cos / pi).

       - ``first_bounce="rsm"`` (the paper): one reflective shadow map per
         emitter, ``rsm_size`` x ``rsm_size`` texels: texel (a, b) is the
         first hit of the emitter ray whose direction sample is the texel
         centre ((a + 1/2) / R, (b + 1/2) / R) (the RSM's image plane) and
         whose position sample is a 2D Halton point (bases 2, 3) rotated
         once per frame (where on an area light, or on a directional
         light's disk, the ray starts).
       - ``first_bounce="paths"``: ``vpls`` random light paths
         (``scene.sample_emitter_ray``, PCG32).
    3. ``bounce1_march`` / ``bounce1_project``: at each occupied cell,
       ``samples`` VPLs k, received at the cell centre jittered by
       ``jitter`` cells:

       .. math:: \lambda_{lm}(P) = \frac{n_e}{n_s}\sum_k
                 \frac{\Phi_k \rho_k \max(0, n_k\cdot(-\omega_k))}
                      {\pi \max(|X_k-P|^2, d_{min}^2)} V(X_k, P)\, Y_{lm}(\omega_k)

       (the paper's Eq. 2: Phi_k n_texels / n_s with the texel flux
       Phi_k = w_k / R^2 of the ray weight w_k; n_e = number of emitters,
       samples split uniformly among the RSMs). With ``"rsm"`` the texels
       are chosen at the points of a precomputed 2D Halton rectangle
       (bases 2, 3) over the n_e R x R RSM atlas, rotated per cell and
       frame (Cranley-Patterson); with ``"paths"`` uniformly at random
       (n_e = 1). V by ray marching in the geometry volume
       (``visibility="march"``, ``march_samples`` jittered samples per
       segment, the paper's 8-12; 0: one per voxel) or Mitsuba shadow rays
       (``"rays"``). The march stage stores (omega_k, L_k) per (cell,
       sample); the project stage sums ``project(enc, omega, L)`` per cell
       in the encoding's colour space (YCoCg with fewer chroma bands, or
       RGB).
    4. ``bounce2_march`` / ``bounce2_project`` (``bounces`` > 1): from each
       occupied cell, ``secondary_rays`` uniform directions are marched up
       to ``secondary_distance`` cells (``secondary_march_samples``, the
       paper's 4-6; 0: one per voxel); at the hit X, a virtual diffuse
       surface facing P reflects L = rho E(X, -omega) / pi, with E
       reconstructed from the previous bounce's volume and rho =
       ``albedo`` (with Mitsuba rays: the true normal and albedo of the
       hit): :math:`\lambda^{(i)} = \frac{4\pi}{n}\sum_k L(X_k, -\omega_k) Y(\omega_k)`.
       Two volumes hold the last bounce's input and output (swapped) and a
       third the running sum.
    5. ``blend``: exponential moving average ``cache = a new + (1 - a) cache``
       with ``a = blend`` for cells that were occupied in the previous frame
       (others start from the new value).
    6. ``reconstruct`` at the G-buffer points: trilinear interpolation of
       the coefficients at x + n h / 2, closed-form irradiance (Ramamoorthi
       and Hanrahan), back to RGB (``presence`` scales Y, ``bleeding``
       CoCg), outgoing diffuse radiance rho(x) E / pi.

    Moving volume (``volume="camera"``, the paper's Sec. 7): the cache grid
    is a ``window``^3 window of the world lattice (the ``resolution`` grid
    over the scene box) whose centre cell holds the first viewer's camera
    (moved ``ahead`` cells along its view); when it moves by whole cells
    the blended coefficients and the blend history are scrolled
    (:meth:`place`), the geometry volume stays global, and shaded points
    the window does not serve (:meth:`in_window`) get 0.

    Random numbers: one stream per light path, per frame (RSM rotation),
    per (cell, sample) and per cell (:func:`slc.core.keys.keyed_rng`, keyed by
    the *cell* index, not by the position in the compacted list of active
    cells), so the same cell draws the same numbers whether or not other
    cells are active.

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
        Param("first_bounce", "rsm", "VPLs: per-emitter RSM texels chosen by Halton points (paper) "
              "or random light paths chosen by PCG32", choices=("rsm", "paths")),
        Param("rsm_size", 64, "RSM texels per side and emitter (first_bounce=rsm)", lo=1, hi=2048),
        Param("vpls", 4096, "light paths (VPLs) per frame (first_bounce=paths)", lo=1, hi=4_000_000),
        Param("samples", 64, "VPL samples per cache point (paper 50-200)", lo=1, hi=1 << 16),
        Param("secondary_rays", 32, "directions per cache point for bounces 2+", lo=1, hi=1 << 16),
        Param("secondary_distance", 8.0, "march length of secondary rays [cells]", lo=0.25, hi=1024.0),
        Param("visibility", "march", "visibility by geometry-volume march or Mitsuba rays",
              choices=("march", "rays")),
        Param("march_samples", 10, "samples per first-bounce visibility march (paper 8-12; 0: one per voxel)",
              lo=0, hi=4096),
        Param("secondary_march_samples", 5, "samples per secondary-bounce march (paper 4-6; 0: one per voxel)",
              lo=0, hi=4096),
        Param("blend", 0.25, "temporal blend weight of the new estimate", lo=0.01, hi=1.0),
        Param("jitter", 0.5, "jitter of the sample point around the cell centre [cells]", lo=0.0, hi=1.0),
        Param("min_distance", 0.5, "distance clamp of VPL contributions [cells]", lo=0.0, hi=8.0),
        Param("depth_stride", 0, "pixel stride of the depth occupancy (0: the paper's 10 at 1 MPixel, scaled "
              "by sqrt(pixels / 1M); 1: every pixel)", lo=0, hi=64),
        Param("albedo", 0.5, "grey albedo of marched secondary hits", lo=0.0, hi=1.0),
        Param("presence", 1.0, "scale of Y (artistic control)", lo=0.0, hi=16.0),
        Param("bleeding", 1.0, "scale of Co, Cg (artistic control)", lo=0.0, hi=16.0),
        Param("chroma", "offset", "chroma decoding: the paper's offset or the constant-chromaticity ratio",
              choices=("offset", "ratio")),
        Param("volume", "scene", "grid over the whole scene box, or a moving window around the first viewer's "
              "camera (re-centred in whole cells, coefficients scrolled)", choices=("scene", "camera")),
        Param("window", 10, "cells per side of the moving window (volume=camera)", lo=4, hi=256),
        Param("ahead", 0.0, "window centre ahead of the camera along its view [cells] (volume=camera; "
              "0: centred at the viewer, as in the paper)", lo=0.0, hi=256.0),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.enc = get_encoding(self.encoding)
        # the world lattice (cell size h) and the geometry volume cover the scene box; the cache grid is
        # the world grid itself, or with volume=camera a window of it moved in whole cells
        self.world = Grid.around(scene.bbox_min, scene.bbox_max, self.resolution)
        self.geo = self.world.finer(GEOMETRY_FACTOR)
        self.moving = self.volume == "camera"
        self.offset = np.zeros(3, dtype=np.int64)     # window corner in world cells
        self.moves = 0
        self.grid = self._window_grid() if self.moving else self.world
        self.voxelize_ms = 0.0
        self._voxel_time = None
        # the precomputed Halton rectangles: cell samples over the RSM atlas, RSM position samples
        self._halton_cells = mi.Point2f(halton(self.samples, 2).astype(np.float32),
                                        halton(self.samples, 3).astype(np.float32))
        r2 = self.rsm_size * self.rsm_size
        self._halton_rsm = np.stack([halton(r2, 2), halton(r2, 3)], 1)
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
        self._placed = False

    def _voxelize(self) -> None:
        t = self.scene.time
        if self.geometry is not None and (not self.scene.dynamic or t == self._voxel_time):
            return
        t0 = time.perf_counter()
        self.geometry = volume.voxelize(volume.scene_triangles(self.scene.mi_scene), self.geo)
        self.geo_occ = volume.dilate(volume.occupancy_from_geometry(self.geometry, self.world), self.world)
        dr.eval(self.geometry, self.geo_occ)
        dr.sync_thread()
        self.voxelize_ms = (time.perf_counter() - t0) * 1e3
        self._voxel_time = t

    # ------------------------------------------------------- moving volume
    def _window_offset(self, gbuffers) -> np.ndarray:
        """World-cell corner of the window whose centre cell holds the first
        viewer's camera (moved ``ahead`` cells along its view)."""
        cam = gbuffers[0].camera
        f, _, _ = cam.basis()
        c = np.asarray(cam.origin, float) + f * (self.ahead * self.world.h)
        return np.floor((c - self.world.lo) / self.world.h).astype(np.int64) - self.window // 2

    def in_window(self, p: mi.Point3f, q: mi.Point3f) -> mi.Bool:
        """Shaded points the window serves: the lookup point q's trilinear
        stencil lies in the window and so does the point p's own cell (whose
        depth occupancy, dilated by one cell, marks that stencil)."""
        return self.grid.stencil_inside(q) & self.grid.cell_of(p)[1]

    def _cell_offset(self) -> mi.Vector3i:
        return mi.Vector3i(*(dr.opaque(mi.Int32, int(x)) for x in self.offset))

    def _key(self, cell: mi.UInt32) -> mi.UInt32:
        """Random-stream key of a cache cell: its flat index; in a moving
        window, the flat index of its world cell (the same key as with
        volume=scene), or for a cell outside the scene's grid ``n_world`` +
        its index on the world lattice padded by the window. So a cell draws
        the same numbers wherever the window is, and as the scene grid's."""
        if not self.moving:
            return cell
        P = self.window
        nx, ny, _ = self.world.dims
        i = self.grid.unflat(cell) + self._cell_offset()
        ip = i + P
        outside = mi.UInt32(self.world.n_cells) + mi.UInt32((ip.z * (ny + 2 * P) + ip.y) * (nx + 2 * P) + ip.x)
        return dr.select(self.world.inside(i), self.world.flat(i), outside)

    def _world_occupancy(self) -> mi.UInt32:
        """The (dilated) geometry occupancy of the window's cells, read from
        the world's."""
        if not self.moving:
            return self.geo_occ
        j = self.grid.unflat(dr.arange(mi.UInt32, self.grid.n_cells)) + self._cell_offset()
        ok = self.world.inside(j)
        return dr.gather(mi.UInt32, self.geo_occ, dr.select(ok, self.world.flat(j), 0), ok)

    def _scroll(self, delta: np.ndarray) -> None:
        """Move the window by ``delta`` whole cells: every coefficient (and
        the blend history) is copied from the cell that held the same world
        position; cells entering the window start empty. Gathers only (no
        recomputation), the shift an opaque input (no kernel build per move)."""
        n, nc = self.grid.n_cells, self.enc.n
        d = mi.Vector3i(*(dr.opaque(mi.Int32, int(x)) for x in delta))
        lane = dr.arange(mi.UInt32, nc * n)
        c, idx = lane // n, lane % n
        j = self.grid.unflat(idx) + d
        ok = self.grid.inside(j)
        src = dr.select(ok, self.grid.flat(j), 0)
        self.cache = dr.gather(mi.Float, self.cache, src + c * n, ok)
        jh = self.grid.unflat(dr.arange(mi.UInt32, n)) + d
        okh = self.grid.inside(jh)
        self.hist = dr.gather(mi.UInt32, self.hist, dr.select(okh, self.grid.flat(jh), 0), okh)

    def place(self, offset) -> None:
        """Put the window's corner at world cell ``offset``, scrolling the
        coefficients when the cache holds any."""
        offset = np.asarray(offset, dtype=np.int64)
        delta = offset - self.offset
        if not np.any(delta):
            return
        self.offset = offset
        if self._placed:
            self._scroll(delta)
            self.moves += 1
        self.grid = self._window_grid()

    def _window_grid(self) -> Grid:
        return Grid(lo=self.world.lo + self.offset * self.world.h, h=self.world.h, dims=(self.window,) * 3)

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
            occ = dr.zeros(mi.UInt32, self.grid.n_cells)
            for gb in gbuffers:
                occ |= volume.depth_occupancy(self.grid, [gb], self.stride_for(gb.width, gb.height))
            occ = volume.dilate(occ, self.grid)
        else:
            occ = self._world_occupancy()
        return dr.compress(occ != 0)

    def stride_for(self, width: int, height: int) -> int:
        """Depth-occupancy pixel stride at this frame size: ``depth_stride``,
        or with 0 the paper's s = 10 at 1 MPixel scaled with the frame's
        side, so that the depth samples per degree of view stay the paper's."""
        if self.depth_stride > 0:
            return self.depth_stride
        return max(1, int(round(PAPER_STRIDE * math.sqrt(width * height / 1e6))))

    def _vpl(self, si: mi.SurfaceInteraction3f, w):
        ok = si.is_valid() & (si.wi.z > 0.0)
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, ok))
        phi = dr.select(ok, mi.Color3f(w) * rho, 0.0)
        return dr.select(ok, si.p, 0.0), front_normal(si), phi

    def _lights(self, frame: int):
        """Virtual point lights (X, N, Phi rho) and the estimator's factor n_e."""
        sc = self.scene.mi_scene
        if self.first_bounce == "paths":
            s = keyed_rng(dr.arange(mi.UInt32, self.vpls), self.seed, frame, STREAM_CRC + _LIGHTS)
            u1 = s.next_float32()
            u2 = mi.Point2f(s.next_float32(), s.next_float32())
            u3 = mi.Point2f(s.next_float32(), s.next_float32())
            ray, w, _ = sc.sample_emitter_ray(0.0, u1, u2, u3, True)
            return (*self._vpl(sc.ray_intersect(ray), w), 1)
        # ---------------- one RSM per emitter, texels on a regular grid ----------------
        emitters = sc.emitters_dr()
        n_e, R = dr.width(emitters), self.rsm_size
        rot = np.random.default_rng([self.seed, frame, _RSM]).random(2)  # Cranley-Patterson, per frame
        u2 = np.tile((self._halton_rsm + rot) % 1.0, (max(n_e, 1), 1)).astype(np.float32)
        t = dr.arange(mi.UInt32, n_e * R * R)
        e, tex = t // (R * R), t % (R * R)
        u3 = (mi.Point2f(mi.Float(tex % R), mi.Float(tex // R)) + 0.5) * (1.0 / R)
        ep = dr.gather(mi.EmitterPtr, emitters, e)
        # aligned copies: a numpy column is mapped with whatever alignment numpy's allocator gave it,
        # and an unaligned input is another kernel (built in a timed frame in about 1 run of 4)
        ray, w = ep.sample_ray(0.0, 0.5, mi.Point2f(mi.Float(aligned(u2[:, 0], np.float32)),
                                                    mi.Float(aligned(u2[:, 1], np.float32))), u3, True)
        return (*self._vpl(sc.ray_intersect(ray), w), n_e)

    def _lanes(self, cells: mi.UInt32, count: int):
        """(cell, sample index) of the n_cells x count lanes, cell-major."""
        lane = dr.arange(mi.UInt32, dr.width(cells) * count)
        return dr.gather(mi.UInt32, cells, lane // count), lane % count

    def _sum(self, omega: mi.Vector3f, L: mi.Color3f, n_cells: int, count: int, scale: float) -> list:
        """``scale`` x the sum over each cell's ``count`` lanes of
        ``project(enc, omega, L)`` (in registers, one cell per lane)."""
        enc = self.enc
        base = dr.arange(mi.UInt32, n_cells) * count
        n = dr.opaque(mi.UInt32, count)

        def cond(i, acc):
            return i < n

        def body(i, acc):
            w = dr.gather(mi.Vector3f, omega, base + i)
            x = dr.gather(mi.Color3f, L, base + i)
            return i + 1, [a + b for a, b in zip(acc, project(enc, w, x))]

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc = dr.while_loop(state=(mi.UInt32(0), acc0), cond=cond, body=body, labels=("i", "acc"))
        return [a * scale for a in acc]

    def _jittered(self, Pc: mi.Point3f, sampler: mi.PCG32) -> mi.Point3f:
        off = mi.Vector3f(sampler.next_float32(), sampler.next_float32(), sampler.next_float32()) - 0.5
        return Pc + off * (self.jitter * self.grid.h)

    def _first_bounce_samples(self, frame: int, cells: mi.UInt32, X, N, phi, n_e: int, points=None):
        """(omega_k, L_k) of every (cell, sample) lane: VPL choice and visibility.
        ``points`` (diagnostic): receive at these points (one per entry of
        ``cells``, no jitter) instead of the jittered cell centres."""
        geo, ns = self.geo, self.samples
        d2min = (self.min_distance * self.grid.h) ** 2
        cell, i = self._lanes(cells, ns)
        key = self._key(cell)
        sampler = keyed_rng(key * ns + i, self.seed, frame, STREAM_CRC + _FIRST_BOUNCE)
        # ------------------------------- VPL choice -------------------------------
        if self.first_bounce == "rsm":
            R = self.rsm_size
            rot = keyed_rng(key, self.seed, frame, STREAM_CRC + _ROTATION)   # one per cell
            h = dr.gather(mi.Point2f, self._halton_cells, i)
            ux = h.x + rot.next_float32()
            uy = h.y + rot.next_float32()
            ux, uy = ux - dr.floor(ux), uy - dr.floor(uy)
            x = dr.minimum(mi.UInt32(ux * float(n_e * R)), n_e * R - 1)
            y = dr.minimum(mi.UInt32(uy * float(R)), R - 1)
            e = x // R
            j = e * (R * R) + y * R + (x - e * R)
        else:
            j = dr.minimum(mi.UInt32(sampler.next_float32() * self.vpls), self.vpls - 1)
        if points is None:
            P = self._jittered(self.grid.center(cell), sampler)
        else:
            P = mi.Vector3f(dr.gather(mi.Point3f, points, cell))   # the type _jittered() gives
        Xk = dr.gather(mi.Point3f, X, j)
        Nk = dr.gather(mi.Vector3f, N, j)
        Pk = dr.gather(mi.Color3f, phi, j)
        v = Xk - P
        d2 = dr.squared_norm(v)
        w_dir = v * dr.rsqrt(dr.maximum(d2, 1e-20))
        cos_k = -dr.dot(Nk, w_dir)
        ok = (cos_k > 0.0) & (dr.max(Pk) > 0.0) & (d2 > 0.0)
        # -------------------------------- visibility --------------------------------
        if self.visibility == "march":
            ok = visible(self.geometry, geo, P, Xk, sampler.next_float32(), ok,
                         start_offset=geo.h, end_offset=2.0 * geo.h, samples=self.march_samples)
        else:
            ray = mi.Ray3f(P, w_dir)
            ray.maxt = dr.sqrt(d2) * (1.0 - 1e-3)
            ok &= ~self.scene.mi_scene.ray_test(ray, ok)
        return w_dir, Pk * dr.select(ok, cos_k / (math.pi * dr.maximum(d2, d2min)), 0.0)

    def _secondary_samples(self, frame: int, bounce: int, cells: mi.UInt32):
        """(omega, lookup point, normal, albedo, hit) of every (cell, ray) lane."""
        geo, h, nr = self.geo, self.grid.h, self.secondary_rays
        cell, i = self._lanes(cells, nr)
        sampler = keyed_rng(self._key(cell) * nr + i, self.seed, frame, STREAM_CRC + _SECONDARY + bounce)
        d = mi.warp.square_to_uniform_sphere(mi.Point2f(sampler.next_float32(), sampler.next_float32()))
        P = self._jittered(self.grid.center(cell), sampler)
        # ----------------------- nearest visible surface point -----------------------
        if self.visibility == "march":
            hit, t = march(self.geometry, geo, P, d, geo.h, self.secondary_distance * h, sampler.next_float32(),
                           mi.Bool(True), samples=self.secondary_march_samples)
            X = P + dr.select(hit, t, 0.0) * d
            n = -d
            rho = mi.Color3f(self.albedo)
        else:
            si = self.scene.mi_scene.ray_intersect(mi.Ray3f(P, d))
            hit = si.is_valid() & (si.wi.z > 0.0)
            X = dr.select(hit, si.p, P)
            n = front_normal(si)
            rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, hit))
        return d, mi.Point3f(X + n * (0.5 * h)), n, dr.select(hit, rho, 0.0), hit

    def _secondary_sum(self, n_cells: int, samples, vin: mi.Float) -> list:
        """Bounce i from the lanes of :meth:`_secondary_samples` and the
        previous bounce's volume ``vin`` (lookup, irradiance, projection)."""
        enc, nr = self.enc, self.secondary_rays
        d_all, q_all, n_all, rho_all, hit_all = samples
        base = dr.arange(mi.UInt32, n_cells) * nr
        n = dr.opaque(mi.UInt32, nr)

        def cond(i, acc):
            return i < n

        def body(i, acc):
            k = base + i
            hit = dr.gather(mi.Bool, hit_all, k)
            d = dr.gather(mi.Vector3f, d_all, k)
            nrm = dr.gather(mi.Vector3f, n_all, k)
            q = dr.gather(mi.Point3f, q_all, k, hit)
            if self.moving:     # a hit whose stencil leaves the window reads nothing
                hit &= self.grid.stencil_inside(q)
            rho = dr.gather(mi.Color3f, rho_all, k, hit)
            coeffs = self._lookup(vin, q, hit)
            E = irradiance(enc, coeffs, nrm, clamp=True, chroma=self.chroma)
            L = dr.select(hit, rho * mi.Color3f(*E) * (1.0 / math.pi), 0.0)
            return i + 1, [a + b for a, b in zip(acc, project(enc, d, L))]

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc = dr.while_loop(state=(mi.UInt32(0), acc0), cond=cond, body=body, labels=("i", "acc"))
        w = 4.0 * math.pi / float(nr)
        return [a * w for a in acc]

    def _blend(self, cells: mi.UInt32, coeffs: list) -> None:
        n = self.grid.n_cells
        had = dr.gather(mi.UInt32, self.hist, cells) != 0
        a = dr.select(had, self.blend, 1.0)
        # all reads before the first write: one kernel (the target is copied once) instead of one per coefficient
        olds = [dr.gather(mi.Float, self.cache, cells + c * n) for c in range(self.enc.n)]
        for c, old in enumerate(olds):
            dr.scatter(self.cache, dr.fma(a, coeffs[c] - old, old), cells + c * n)
        hist = dr.zeros(mi.UInt32, n)
        dr.scatter(hist, mi.UInt32(1), cells)
        self.hist = hist

    # ------------------------------------------------------------------ frame
    def update(self, frame: int, gbuffers, timer) -> None:
        """Rebuild the cache for this frame (all stages but reconstruction)."""
        self._voxelize()
        if self.moving:
            with timer.stage("scroll") as st:
                self.place(self._window_offset(gbuffers))
                st.outputs(self.cache, self.hist)
            self._placed = True
        with timer.stage("occupancy") as st:
            cells = self._occupancy(gbuffers)
            st.outputs(cells)
        self.active = cells
        self.n_active = nc = dr.width(cells)
        if nc == 0:     # no cache point (e.g. a moving window over empty space): nothing to update
            self.hist = dr.zeros(mi.UInt32, self.grid.n_cells)
            return
        with timer.stage("lights") as st:
            X, N, phi, n_e = self._lights(frame)
            st.outputs(X, N, phi)
        with timer.stage("bounce1_march") as st:
            omega, L = self._first_bounce_samples(frame, cells, X, N, phi, n_e)
            st.outputs(omega, L)
        with timer.stage("bounce1_project") as st:
            coeffs = self._sum(omega, L, nc, self.samples, float(n_e) / float(self.samples))
            st.outputs(*coeffs)
        del omega, L
        self._volumes = 2
        if self.bounces > 1:
            total = list(coeffs)
            with timer.stage("bounce2_project") as st:
                inc = self._store(coeffs, cells)
                st.outputs(inc)
            for b in range(2, self.bounces + 1):
                with timer.stage("bounce2_march") as st:
                    smp = self._secondary_samples(frame, b, cells)
                    st.outputs(*smp)
                with timer.stage("bounce2_project") as st:
                    new = self._secondary_sum(nc, smp, inc)
                    total = [t + x for t, x in zip(total, new)]
                    if b < self.bounces:
                        inc = self._store(new, cells)
                        st.outputs(inc)
                    st.outputs(*total)
            coeffs = total
            self._volumes = 4 if self.bounces > 2 else 3
        with timer.stage("blend") as st:
            self._blend(cells, coeffs)
            st.outputs(self.cache, self.hist)

    def shade(self, gb) -> mi.Color3f:
        """Outgoing diffuse indirect radiance rho E / pi at the G-buffer points."""
        si, active = gb.si, gb.valid & (gb.si.wi.z > 0.0)
        n = front_normal(si)
        q = si.p + n * (0.5 * self.grid.h)
        if self.moving:         # outside the window: no cached indirect light
            active &= self.in_window(si.p, q)
        coeffs = self._lookup(self.cache, q, active)
        E = mi.Color3f(*irradiance(self.enc, coeffs, n, self.presence, self.bleeding, chroma=self.chroma))
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, active))
        return dr.select(active, rho * E * (1.0 / math.pi), 0.0)

    def shade_unfiltered(self, frame: int, gb) -> mi.Color3f:
        """Diagnostic (1 bounce, volume=scene): the first-bounce estimator evaluated at each
        G-buffer point's own lookup point p + n h/2 (no grid, no trilinear
        interpolation, no jitter, no temporal blend), with ``samples`` VPLs;
        the difference to :meth:`shade` at equal sample count is the
        interpolation (grid) error."""
        si, active = gb.si, gb.valid & (gb.si.wi.z > 0.0)
        n = front_normal(si)
        q = mi.Point3f(si.p + n * (0.5 * self.grid.h))
        if self.geometry is None:
            self._voxelize()
        X, N, phi, n_e = self._lights(frame)
        pts = dr.arange(mi.UInt32, dr.width(q))
        omega, L = self._first_bounce_samples(frame, pts, X, N, phi, n_e, points=q)
        coeffs = self._sum(omega, L, dr.width(q), self.samples, float(n_e) / float(self.samples))
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
    #: stages whose work scales with the coefficient count (where compression can save)
    COEFFICIENT_STAGES = ("bounce1_project", "bounce2_project", "blend", "reconstruct", "scroll")
    #: stages independent of the encoding (marching, light injection, occupancy)
    FIXED_STAGES = ("occupancy", "lights", "bounce1_march", "bounce2_march")

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
                "cells": self.grid.n_cells, "coefficients": self.enc.n, "voxelize_ms": self.voxelize_ms,
                "window_moves": self.moves}
