"""Compressed Radiance Caching (Vardis, Papaioannou and Gkaravelis 2014) on
a uniform grid: diffuse indirect illumination from an SH radiance field
stored in YCoCg with fewer bands for chrominance.

This module holds the cache, its state, occupancy, temporal blend, frame and reconstruction; the
parts it holds are the light injection and the bounces (``transport``,
:mod:`slc.methods.crc.bounces`) and the cells it covers, the scene grid or the moving volume
(``region``, :mod:`slc.methods.crc.window`)."""
from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods import Method, Param
from slc.lib.sh.project import irradiance
from slc.lib.sh.ycocg import ENCODINGS
from slc.lib.sh.ycocg import encoding as get_encoding
from slc.methods.crc import volume
from slc.methods.crc.bounces import Bounces, front_normal
from slc.methods.crc.grid import GEOMETRY_FACTOR, Grid, lookup
from slc.methods.crc.window import Region

#: the paper's depth-occupancy stride s, at a 1 MPixel frame buffer
PAPER_STRIDE = 10


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
    the window does not serve (:meth:`Region.in_window`) get 0.

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
    shade_stage = "reconstruct"
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
        self.region = Region(self.world, self.moving, self.window, self.ahead)
        self.voxelize_ms = 0.0
        self._voxel_time = None
        self.transport = Bounces(scene, self.enc, self.region, self.geo,
                                 **{k: getattr(self, k) for k in Bounces.SETTINGS})
        self.reset()

    @property
    def grid(self) -> Grid:
        """The current cache grid (the world lattice, or the moving window's cells)."""
        return self.region.grid

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

    def place(self, offset) -> None:
        """Put the moving window's corner at world cell ``offset``, scrolling the coefficients and
        the blend history when the cache holds any (:meth:`Region.place`)."""
        self.cache, self.hist = self.region.place(offset, self.cache, self.hist, self.enc.n, scroll=self._placed)

    # ----------------------------------------------------------- coefficients
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
            occ = self.region.occupancy(self.geo_occ)
        return dr.compress(occ != 0)

    def stride_for(self, width: int, height: int) -> int:
        """Depth-occupancy pixel stride at this frame size: ``depth_stride``,
        or with 0 the paper's s = 10 at 1 MPixel scaled with the frame's
        side, so that the depth samples per degree of view stay the paper's."""
        if self.depth_stride > 0:
            return self.depth_stride
        return max(1, int(round(PAPER_STRIDE * math.sqrt(width * height / 1e6))))

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
                self.place(self.region.corner(gbuffers))
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
            X, N, phi, n_e = self.transport.lights(frame)
            st.outputs(X, N, phi)
        with timer.stage("bounce1_march") as st:
            omega, L = self.transport.first_bounce_samples(frame, cells, X, N, phi, n_e, self.geometry)
            st.outputs(omega, L)
        with timer.stage("bounce1_project") as st:
            coeffs = self.transport.sum_projections(omega, L, nc, self.samples, float(n_e) / float(self.samples))
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
                    smp = self.transport.secondary_samples(frame, b, cells, self.geometry)
                    st.outputs(*smp)
                with timer.stage("bounce2_project") as st:
                    new = self.transport.secondary_sum(nc, smp, inc)
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

    def shade(self, ctx, fr, v: int, gb) -> mi.Color3f:
        """Outgoing diffuse indirect radiance rho E / pi at the G-buffer points (the cache
        reconstructed there; stage "reconstruct")."""
        si, active = gb.si, gb.valid & (gb.si.wi.z > 0.0)
        n = front_normal(si)
        q = si.p + n * (0.5 * self.grid.h)
        if self.moving:         # outside the window: no cached indirect light
            active &= self.region.in_window(si.p, q)
        coeffs = lookup(self.grid, self.cache, self.enc.n, q, active)
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
        X, N, phi, n_e = self.transport.lights(frame)
        pts = dr.arange(mi.UInt32, dr.width(q))
        omega, L = self.transport.first_bounce_samples(frame, pts, X, N, phi, n_e, self.geometry, points=q)
        coeffs = self.transport.sum_projections(omega, L, dr.width(q), self.samples, float(n_e) / float(self.samples))
        E = mi.Color3f(*irradiance(self.enc, coeffs, n, self.presence, self.bleeding, chroma=self.chroma))
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, active))
        return dr.select(active, rho * E * (1.0 / math.pi), 0.0)

    def update_frame(self, ctx, gbuffers, timer) -> None:
        """The cache update of frame ``ctx.frame``, shared by all viewers (:meth:`update`)."""
        self.update(ctx.frame, gbuffers, timer)

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
                "window_moves": self.region.moves}
