"""The new coefficients of the CRC cache (:class:`Bounces`, held by
:class:`slc.methods.crc.cache.CRCCache` as ``transport``): light injection (the virtual point
lights from one reflective shadow map per emitter, or from random light paths), the first bounce's
(VPL, cell) samples with their visibility, the secondary bounces' marched or traced hits, and the
sums of their SH projections per cell."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.core.keys import STREAM_CRC, keyed_rng
from slc.lib.sh.project import irradiance, project
from slc.methods.crc.grid import Grid, lookup
from slc.methods.crc.march import march, visible
from slc.methods.crc.window import Region

# Random streams of the stages (offsets of STREAM_CRC; keys: light path, RSM
# frame, (cell, sample) pair or cell index)
_LIGHTS, _FIRST_BOUNCE, _ROTATION, _RSM, _SECONDARY = 11, 12, 13, 14, 20


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


def front_normal(si: mi.SurfaceInteraction3f) -> mi.Vector3f:
    """Shading normal (the side ``si.wi`` comes from)."""
    n = mi.Vector3f(si.sh_frame.n)
    return dr.select(si.wi.z < 0.0, -n, n)


class Bounces:
    """Light injection and the bounces of :class:`~slc.methods.crc.cache.CRCCache`.

    Parameters: ``scene``, ``enc`` (the SH encoding), ``region`` (:class:`Region`: the current
    cache grid and the random-stream key of a cell), ``geo`` (the geometry volume's lattice), and
    the cache's settings named in ``SETTINGS`` (``seed``, the VPLs: ``first_bounce``, ``vpls``,
    ``rsm_size``; the first bounce: ``samples``, ``jitter``, ``min_distance``, ``visibility``,
    ``march_samples``; the secondary bounces: ``secondary_rays``, ``secondary_distance``,
    ``secondary_march_samples``, ``albedo``; the irradiance's ``chroma`` decoding). Holds the
    precomputed Halton rectangles: ``halton_cells`` (``samples`` cell samples over the RSM atlas)
    and ``halton_rsm`` (``rsm_size``^2 RSM position samples)."""

    SETTINGS = ("seed", "first_bounce", "vpls", "rsm_size", "samples", "jitter", "min_distance", "visibility",
                "march_samples", "secondary_rays", "secondary_distance", "secondary_march_samples", "albedo",
                "chroma")

    def __init__(self, scene, enc, region: Region, geo: Grid, **settings):
        self.scene, self.enc, self.region, self.geo = scene, enc, region, geo
        for k in self.SETTINGS:
            setattr(self, k, settings[k])
        self.halton_cells = mi.Point2f(halton(self.samples, 2).astype(np.float32),
                                       halton(self.samples, 3).astype(np.float32))
        r2 = self.rsm_size * self.rsm_size
        self.halton_rsm = np.stack([halton(r2, 2), halton(r2, 3)], 1)

    def _vpl(self, si: mi.SurfaceInteraction3f, w):
        ok = si.is_valid() & (si.wi.z > 0.0)
        rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, ok))
        phi = dr.select(ok, mi.Color3f(w) * rho, 0.0)
        return dr.select(ok, si.p, 0.0), front_normal(si), phi

    def lights(self, frame: int):
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
        u2 = np.tile((self.halton_rsm + rot) % 1.0, (max(n_e, 1), 1)).astype(np.float32)
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

    def sum_projections(self, omega: mi.Vector3f, L: mi.Color3f, n_cells: int, count: int, scale: float) -> list:
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
        return Pc + off * (self.jitter * self.region.grid.h)

    def first_bounce_samples(self, frame: int, cells: mi.UInt32, X, N, phi, n_e: int, geometry: mi.UInt32,
                             points=None):
        """(omega_k, L_k) of every (cell, sample) lane: VPL choice and visibility.
        ``points`` (diagnostic): receive at these points (one per entry of
        ``cells``, no jitter) instead of the jittered cell centres."""
        geo, ns = self.geo, self.samples
        d2min = (self.min_distance * self.region.grid.h) ** 2
        cell, i = self._lanes(cells, ns)
        key = self.region.key(cell)
        sampler = keyed_rng(key * ns + i, self.seed, frame, STREAM_CRC + _FIRST_BOUNCE)
        # ------------------------------- VPL choice -------------------------------
        if self.first_bounce == "rsm":
            R = self.rsm_size
            rot = keyed_rng(key, self.seed, frame, STREAM_CRC + _ROTATION)   # one per cell
            h = dr.gather(mi.Point2f, self.halton_cells, i)
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
            P = self._jittered(self.region.grid.center(cell), sampler)
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
            ok = visible(geometry, geo, P, Xk, sampler.next_float32(), ok,
                         start_offset=geo.h, end_offset=2.0 * geo.h, samples=self.march_samples)
        else:
            ray = mi.Ray3f(P, w_dir)
            ray.maxt = dr.sqrt(d2) * (1.0 - 1e-3)
            ok &= ~self.scene.mi_scene.ray_test(ray, ok)
        return w_dir, Pk * dr.select(ok, cos_k / (math.pi * dr.maximum(d2, d2min)), 0.0)

    def secondary_samples(self, frame: int, bounce: int, cells: mi.UInt32, geometry: mi.UInt32):
        """(omega, lookup point, normal, albedo, hit) of every (cell, ray) lane."""
        geo, h, nr = self.geo, self.region.grid.h, self.secondary_rays
        cell, i = self._lanes(cells, nr)
        sampler = keyed_rng(self.region.key(cell) * nr + i, self.seed, frame, STREAM_CRC + _SECONDARY + bounce)
        d = mi.warp.square_to_uniform_sphere(mi.Point2f(sampler.next_float32(), sampler.next_float32()))
        P = self._jittered(self.region.grid.center(cell), sampler)
        # ----------------------- nearest visible surface point -----------------------
        if self.visibility == "march":
            hit, t = march(geometry, geo, P, d, geo.h, self.secondary_distance * h, sampler.next_float32(),
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

    def secondary_sum(self, n_cells: int, samples, vin: mi.Float) -> list:
        """Bounce i from the lanes of :meth:`secondary_samples` and the
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
            if self.region.moving:     # a hit whose stencil leaves the window reads nothing
                hit &= self.region.grid.stencil_inside(q)
            rho = dr.gather(mi.Color3f, rho_all, k, hit)
            coeffs = lookup(self.region.grid, vin, enc.n, q, hit)
            E = irradiance(enc, coeffs, nrm, clamp=True, chroma=self.chroma)
            L = dr.select(hit, rho * mi.Color3f(*E) * (1.0 / math.pi), 0.0)
            return i + 1, [a + b for a, b in zip(acc, project(enc, d, L))]

        acc0 = [mi.Float(0.0) for _ in range(enc.n)]
        _, acc = dr.while_loop(state=(mi.UInt32(0), acc0), cond=cond, body=body, labels=("i", "acc"))
        w = 4.0 * math.pi / float(nr)
        return [a * w for a in acc]
