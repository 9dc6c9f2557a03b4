r"""Bright small regions of an environment map as listable lights of
VISIBILITY records (docs/adaptive.md, "Environment lights").

At load the scene's environment emitter is evaluated (its own ``eval``, so
``to_world`` and ``scale`` are those the renderer sees) at the centres of a
latitude-longitude grid of world directions :math:`\omega_p` (``res`` rows x
2 ``res`` columns, pixel solid angle :math:`\Omega_p = \frac{2\pi}{W}\frac{\pi}{H}\sin\theta_p`).
A pixel is *bright* when its luminance exceeds ``ratio`` times the map's mean
radiance :math:`\bar L = \frac1{4\pi}\sum_p \mathrm{lum}(L_p)\Omega_p`; bright pixels
are grouped into 8-connected regions (wrapping in :math:`\phi`), and a region
is kept when its solid angle :math:`\Omega_j = \sum_{p\in j}\Omega_p` is at most
``max_sr``. Per kept region, with :math:`\Phi_j = \sum_{p\in j} L_p\Omega_p` (RGB)
and :math:`\mathbf P_j = \sum_{p\in j}\mathrm{lum}(L_p)\Omega_p\,\omega_p`:

- direction :math:`\mathbf d_j = \mathbf P_j/|\mathbf P_j|`, mean resultant length
  :math:`R_j = |\mathbf P_j| / \mathrm{lum}(\Phi_j)`;
- angular radius :math:`\alpha_j`: the largest angle between :math:`\mathbf d_j` and a
  pixel of the region, plus a pixel's half diagonal.

Unoccluded irradiance at a point with normal :math:`n` from region :math:`j`,
while the region is wholly above the horizon (:math:`n\cdot\mathbf d_j \ge \sin\alpha_j`):

.. math:: E_j(n) = \int_{j} L(\omega)\,(n\cdot\omega)\,d\omega = n\cdot\sum_{p\in j} L_p\Omega_p\,\omega_p
          \approx \Phi_j R_j\,(n\cdot\mathbf d_j),

exact (up to the grid's quadrature) for a region of one colour; a VISIBILITY
record lists region :math:`j` as a directional light of irradiance
:math:`\Phi_j R_j` (per unit cosine) along :math:`\mathbf d_j` and light index
``base + j`` (``base``: the scene's emitter count). A light sample of the
environment whose direction falls in a region's pixels is that region's
sample: its shadow ray updates the region's visible fraction (a running
mean of shadow rays to points inside the region). Samples of regions not
wholly above the entry's horizon feed the residual.

The sky: the map without its kept regions' pixels, projected once onto
spherical harmonics of 3 bands (RGB, world frame: :math:`L_{lm} = \sum_p L_p
Y_{lm}(\omega_p)\Omega_p`). Its unoccluded irradiance at a normal :math:`n` is
their cosine convolution (Ramamoorthi and Hanrahan 2001),
:math:`E_s(n) = \sum_{lm} \hat A_l L_{lm} Y_{lm}(n)` (a few percent off at most for a
map without its small bright regions), so a VISIBILITY record lists the sky as
one more light of exact unoccluded term with a cached visible fraction
:math:`v_s`, the ratio estimator of the polygon lights: the environment's
samples outside the kept regions step :math:`v_s` by their share
:math:`r = \mathrm{lum}(w\cos\theta) P_{env} / \mathrm{lum}(E_s(n))` of it
(:math:`E[r] = 1`), so :math:`v_s` settles at the sky's visible share of its
irradiance, not the visible share of its directions.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.lib.sh.basis import A_HAT, band_of, basis

NONE = 0xFFFFFFFF
SKY_TOLERANCE = 0.03    # largest error of the sky's SH irradiance (over its mean) at which the sky is listed


def _sh_irradiance_error(sh: np.ndarray, lum: np.ndarray, D: np.ndarray, om: np.ndarray, n: int = 128) -> float:
    """The largest error of the SH irradiance of a map (coefficients ``sh``, 3 x 9) against its
    exact irradiance (the grid's sum, luminance ``lum`` on directions ``D`` of solid angles ``om``)
    over ``n`` normals spread over the sphere, relative to their mean exact irradiance. A sky
    with a sharp glow (a sunset's, around the sun) rings in 3 bands."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    N = np.stack([np.sqrt(1 - z * z) * np.cos(phi), z, np.sqrt(1 - z * z) * np.sin(phi)], -1)
    Dl = D.reshape(-1, 3)
    w = (lum * om).reshape(-1)
    exact = np.maximum(N @ Dl.T, 0.0) @ w
    Y = np.stack(basis(N[:, 0], N[:, 1], N[:, 2], 3), -1)                      # (n, 9)
    shl = 0.212671 * sh[0] + 0.715160 * sh[1] + 0.072169 * sh[2]
    approx = np.maximum(Y @ (shl * np.array([A_HAT[band_of(i)] for i in range(9)])), 0.0)
    mean = exact.mean()
    return float(np.abs(approx - exact).max() / mean) if mean > 0.0 else 0.0


def environment_index(scene) -> int | None:
    """Index into ``scene.emitters()`` of the one environment emitter
    (infinite, not delta), or None (none, or more than one)."""
    sc = getattr(scene, "mi_scene", scene)
    found = [i for i, e in enumerate(sc.emitters()) if bool(int(e.flags()) & int(mi.EmitterFlags.Infinite))
             and not bool(int(e.flags()) & int(mi.EmitterFlags.Delta))]
    return found[0] if len(found) == 1 else None


def _lum(c):
    return 0.212671 * c[..., 0] + 0.715160 * c[..., 1] + 0.072169 * c[..., 2]


def _directions(H: int, W: int):
    """World directions of the grid's pixel centres (Mitsuba's envmap layout
    for an identity ``to_world``: theta from +y, phi from -z towards +x)."""
    th = (np.arange(H) + 0.5) * (math.pi / H)
    ph = (np.arange(W) + 0.5) * (2.0 * math.pi / W)
    T, P = np.meshgrid(th, ph, indexing="ij")
    return np.stack([np.sin(T) * np.sin(P), np.cos(T), -np.sin(T) * np.cos(P)], -1), T


def _components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of ``mask`` (H, W), joined across the phi seam."""
    from scipy import ndimage  # scipy only where an environment map is split into regions
    lab, n = ndimage.label(mask, structure=np.ones((3, 3), int))
    if n == 0:
        return lab, 0
    parent = np.arange(n + 1)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a
    H = mask.shape[0]
    for r in range(H):
        a = lab[r, -1]
        if not a:
            continue
        for rr in (r - 1, r, r + 1):
            if 0 <= rr < H and lab[rr, 0]:
                ra, rb = find(a), find(lab[rr, 0])
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([find(a) for a in range(n + 1)])
    uniq, inv = np.unique(roots, return_inverse=True)      # root 0 (background) stays 0
    return inv[lab], len(uniq) - 1


class EnvLights:
    """The environment's bright small regions and its sky (see the module). Parameters:
    ``scene``, ``ratio`` (10): brightness threshold over the map's mean
    radiance; ``max_sr`` (0.05 sr, a disc of about 7 degrees): largest solid
    angle of a region; ``res`` (512): grid rows; ``max_regions`` (4096);
    ``sky_light`` (True): the rest of the map is listed too, as the sky.
    ``n`` regions, ``share``: their share of the map's luminous power;
    ``sky_sh`` the sky's SH coefficients (RGB x 9, world frame), ``sky_error`` the largest
    error of their irradiance (over the mean), ``sky_share`` its share, ``has_sky``: the sky is
    listed (its error at most ``SKY_TOLERANCE``)."""

    def __init__(self, scene, ratio: float = 10.0, max_sr: float = 0.05, res: int = 512,
                 max_regions: int = 4096, sky_light: bool = True):
        sc = getattr(scene, "mi_scene", scene)
        ems = list(sc.emitters())
        self.base = len(ems)
        self.index = environment_index(sc)
        self.n, self.share, self.sky_share, self.has_sky = 0, 0.0, 0.0, False
        if self.index is None or self.base + 1 >= 0xFFFF:
            return
        H, W = int(res), 2 * int(res)
        D, T = _directions(H, W)
        # ----------------------- the emitter's radiance on the grid (its own eval)
        si = dr.zeros(mi.SurfaceInteraction3f, H * W)
        flat = D.reshape(-1, 3).astype(np.float32)
        si.wi = -mi.Vector3f(flat[:, 0], flat[:, 1], flat[:, 2])
        ptr = dr.gather(mi.EmitterPtr, sc.emitters_dr(), mi.UInt32(self.index))
        Lm = ptr.eval(si, True)
        L = np.stack([np.array(Lm[k], np.float64) for k in range(3)], -1).reshape(H, W, 3)
        L = np.where(np.isfinite(L), np.maximum(L, 0.0), 0.0)
        om = (2.0 * math.pi / W) * (math.pi / H) * np.sin(T)
        lum = _lum(L)
        total = float((lum * om).sum())
        if not total > 0.0:
            return
        mean = total / (4.0 * math.pi)
        self.H, self.W = H, W
        # ----------------------- bright pixels -> regions (the kept ones, brightest first)
        lab, n = _components(lum > ratio * mean)
        lf = lab.ravel()
        order = []
        if n > 0:
            w = (lum * om).ravel()
            Om = np.bincount(lf, om.ravel(), n + 1)[1:]
            Phi = np.stack([np.bincount(lf, (L[..., k] * om).ravel(), n + 1)[1:] for k in range(3)], -1)
            P = np.stack([np.bincount(lf, w * D[..., k].ravel(), n + 1)[1:] for k in range(3)], -1)
            Pl = np.bincount(lf, w, n + 1)[1:]
            keep = (Om <= max_sr) & (Pl > 0.0)
            order = [j for j in np.argsort(-Pl) if keep[j]][:max_regions]
        newid = np.full(n + 1, NONE, np.uint64)
        if order:
            order = np.array(order)
            newid[order + 1] = np.arange(len(order))
            d = P[order] / np.linalg.norm(P[order], axis=1, keepdims=True)
            R = np.linalg.norm(P[order], axis=1) / Pl[order]
            # angular radius: the farthest pixel of the region from d, plus half a pixel's diagonal
            cosmin = np.full(len(order), 1.0)
            sel = newid[lf] != NONE
            ids = newid[lf][sel].astype(np.int64)
            cosp = np.einsum("ij,ij->i", D.reshape(-1, 3)[sel], d[ids])
            np.minimum.at(cosmin, ids, cosp)
            alpha = np.arccos(np.clip(cosmin, -1.0, 1.0)) + 0.5 * math.hypot(math.pi / H, 2.0 * math.pi / W)
            self.n = len(order)
            self.share = float(Pl[order].sum() / total)
            self.dir, self.w = d, Phi[order] * R[:, None]
            self.omega, self.sin_a = Om[order], np.sin(np.minimum(alpha, 0.5 * math.pi))
        else:
            self.dir, self.w, self.omega, self.sin_a = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        self.label = newid[lf].astype(np.uint32).reshape(H, W)
        # ----------------------- the sky: the map without its kept regions, in SH (3 bands, RGB)
        sky = np.where((self.label == NONE)[..., None], L, 0.0)
        Y = np.stack(basis(D[..., 0], D[..., 1], D[..., 2], 3), -1)              # (H, W, 9)
        self.sky_sh = np.einsum("hwc,hwi,hw->ci", sky, Y, om)                  # (3, 9)
        self.sky_error = _sh_irradiance_error(self.sky_sh, _lum(sky), D, om)
        self.sky_share = float((_lum(sky) * om).sum() / total) if sky_light and self.sky_error <= SKY_TOLERANCE \
            else 0.0
        self.has_sky = self.sky_share > 0.0
        # ----------------------- device tables (width >= 2: never a literal)
        pad = lambda a: np.concatenate([a, a[:1]]) if len(a) else np.zeros((2,) + a.shape[1:])   # noqa: E731
        dd, ww, sa = pad(self.dir), pad(self.w), pad(self.sin_a)
        self._dir = mi.Vector3f(*[dd[:, k].astype(np.float32) for k in range(3)])
        self._w = mi.Color3f(*[ww[:, k].astype(np.float32) for k in range(3)])
        self._sin = mi.Float(sa.astype(np.float32))
        self._label = mi.UInt32(self.label.ravel())
        self._sky = mi.Float(self.sky_sh.ravel().astype(np.float32))
        self._base = dr.opaque(mi.UInt32, self.base)
        self._n = dr.opaque(mi.UInt32, self.n)
        self._env = dr.opaque(mi.UInt32, self.index)
        dr.make_opaque(self._dir, self._w, self._sin, self._label, self._sky)

    @property
    def any(self) -> bool:
        """Something to list: a region, or the sky."""
        return self.n > 0 or self.has_sky

    def arrays(self) -> list:
        """The arrays the lookups read (inputs of a frozen function)."""
        return [self._dir, self._w, self._sin, self._label, self._base, self._n, self._env, self._sky]

    def sky_irradiance(self, n: mi.Vector3f, active: mi.Bool) -> mi.Color3f:
        """The sky's unoccluded irradiance at unit normals ``n`` (world): the cosine convolution of
        its SH (Ramamoorthi and Hanrahan 2001), clamped at 0."""
        Y = basis(n.x, n.y, n.z, 3)
        E = []
        for c in range(3):
            e = mi.Float(0.0)
            for i in range(9):
                e += A_HAT[band_of(i)] * dr.gather(mi.Float, self._sky, mi.UInt32(9 * c + i), active) * Y[i]
            E.append(dr.maximum(e, 0.0))
        return dr.select(mi.Bool(active), mi.Color3f(*E), 0.0)

    def sky_map_radiance(self, emitters_dr, d: mi.Vector3f, active: mi.Bool) -> mi.Color3f:
        """The sky's radiance arriving from world directions ``d``: the environment's own ``eval``,
        0 in its kept regions' pixels."""
        active = mi.Bool(active)
        active &= ~self.region_of(d, self._env, active)[0]
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(active))
        si.wi = -d
        ptr = dr.gather(mi.EmitterPtr, emitters_dr, self._env, active)
        return dr.select(active, mi.Color3f(ptr.eval(si, active)), 0.0)

    def sky_sample(self, d: mi.Vector3f, em: mi.UInt32, active: mi.Bool) -> mi.Bool:
        """Environment samples (emitter ``em``, direction ``d``) that are the sky's: outside the
        kept regions' pixels."""
        on = mi.Bool(active) & (mi.UInt32(em) == self._env)
        if not self.has_sky:
            return dr.zeros(mi.Bool, dr.width(on))
        return on & ~self.region_of(d, em, on)[0]

    # ------------------------------------------------------------------ lookups
    def region_of(self, d: mi.Vector3f, em: mi.UInt32, active: mi.Bool):
        """(mask, region index) of environment samples (emitter ``em``) whose
        direction ``d`` lies in a kept region's pixels."""
        active = mi.Bool(active) & (mi.UInt32(em) == self._env)
        th = dr.safe_acos(dr.clip(d.y, -1.0, 1.0))
        ph = dr.atan2(d.x, -d.z)
        ph = dr.select(ph < 0.0, ph + 2.0 * math.pi, ph)
        i = dr.minimum(mi.UInt32(th * (self.H / math.pi)), self.H - 1)
        k = dr.minimum(mi.UInt32(ph * (self.W / (2.0 * math.pi))), self.W - 1)
        j = dr.gather(mi.UInt32, self._label, i * self.W + k, active)
        ok = active & (j != NONE)
        return ok, dr.select(ok, j, 0)

    def light(self, idx: mi.UInt32, active: mi.Bool):
        """(region mask, direction, irradiance per unit cosine Phi R (RGB),
        sin of the angular radius) of light indices ``idx`` (``base + j``)."""
        idx = mi.UInt32(idx)
        is_r = mi.Bool(active) & (idx >= self._base) & (idx < self._base + self._n)
        j = dr.select(is_r, idx - self._base, 0)
        d = dr.gather(mi.Vector3f, self._dir, j, is_r)
        w = dr.gather(mi.Color3f, self._w, j, is_r)
        s = dr.gather(mi.Float, self._sin, j, is_r)
        return is_r, d, dr.select(is_r, w, 0.0), s

    def sample_listable(self, d: mi.Vector3f, em: mi.UInt32, nrm: mi.Vector3f, active: mi.Bool):
        """For light samples (direction ``d``, emitter ``em``) at points of normal
        ``nrm``: (mask of samples in a region wholly above the horizon, the
        region's light index, its direction, its unoccluded irradiance there)."""
        inr, j = self.region_of(d, em, active)
        li = self._base + j
        _, dj, wj, sj = self.light(li, inr)
        c = dr.dot(dj, nrm)
        up = inr & (c >= sj)
        return up, li, dj, dr.select(up, wj * dr.maximum(c, 0.0), 0.0)

    def is_region(self, idx: mi.UInt32) -> mi.Bool:
        """Whether light indices ``idx`` are regions (``base <= idx < base + n``)."""
        idx = mi.UInt32(idx)
        return (idx >= self._base) & (idx < self._base + self._n)

    def unlisted_irradiance(self, nrm: mi.Vector3f, listed, active: mi.Bool) -> mi.Color3f:
        r"""Unoccluded irradiance at normals ``nrm`` of the regions wholly above
        the horizon and not among the light indices ``listed`` (a list of K
        arrays): :math:`\sum_j \Phi_j R_j (n\cdot\mathbf d_j)` over them (a loop
        over the regions, one kernel loop whatever their number)."""
        active = mi.Bool(active)
        listed = [mi.UInt32(x) for x in listed]

        def cond(j, E):
            return j < self._n

        def body(j, E):
            d = dr.gather(mi.Vector3f, self._dir, j, active)
            w = dr.gather(mi.Color3f, self._w, j, active)
            s = dr.gather(mi.Float, self._sin, j, active)
            c = dr.dot(d, nrm)
            li = self._base + j
            on = active & (c >= s)
            for x in listed:
                on &= x != li
            return j + 1, E + dr.select(on, w * c, 0.0)

        _, E = dr.while_loop(state=(mi.UInt32(0), dr.zeros(mi.Color3f, dr.width(active))), cond=cond, body=body)
        return E

    def unlisted_radiance(self, si, bsdf, listed, vu, active, nrm=None) -> mi.Color3f:
        r"""Outgoing radiance at the pixels ``si`` from the regions wholly above
        the horizon and not among the light indices ``listed``, each at its own
        direction, with the shared visible fraction ``vu``:
        :math:`v_u \sum_j f_r(\mathbf d_j)\,\Phi_j R_j` (``bsdf.eval`` has the cosine;
        one BSDF call site in a loop over the regions). ``nrm``: the pixels' normal whose
        horizon counts (default: the shading normal)."""
        active = mi.Bool(active) & (mi.Float(vu) > 0.0)
        listed = [mi.UInt32(x) for x in listed]
        ctx = mi.BSDFContext()
        nrm = si.sh_frame.n if nrm is None else nrm

        def cond(j, L):
            return (j < self._n) & active

        def body(j, L):
            d = dr.gather(mi.Vector3f, self._dir, j, active)
            w = dr.gather(mi.Color3f, self._w, j, active)
            s = dr.gather(mi.Float, self._sin, j, active)
            li = self._base + j
            on = active & (dr.dot(d, nrm) >= s)
            for x in listed:
                on &= x != li
            f = bsdf.eval(ctx, si, si.to_local(d), on)
            return j + 1, L + dr.select(on, mi.Color3f(f) * w, 0.0)

        _, L = dr.while_loop(state=(mi.UInt32(0), dr.zeros(mi.Color3f, dr.width(active))), cond=cond, body=body)
        return L * mi.Float(vu)
