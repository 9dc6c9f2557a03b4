"""Fit the linearly transformed cosines (Heitz et al. 2016) of Mitsuba's GGX reflection lobe and
write the table `slc/lib/lights/ltc_ggx.npz` that `polygon_glossy=ltc` shades with.

    python tools/fit_ltc.py [--alphas 64] [--size 32] [--samples 512] [--out slc/lib/lights/ltc_ggx.npz]

The lobe is Mitsuba's `roughconductor` (GGX, separable Smith shadowing) without Fresnel,
times the cosine, for a view at angle theta to the normal and roughness alpha:

    f(l) cos(l) = D(h) G1(v) G1(l) / (4 cos(v)),   h = (v + l)/|v + l|.

Its LTC is D(l) = D_o(M^-1 l / |M^-1 l|) |det M^-1| / |M^-1 l|^3 with D_o the clamped cosine
over pi and M = R [[a, 0, b], [0, c, 0], [0, 0, 1]], R the frame whose z is the lobe's mean
direction and whose x lies in the plane of the view and the normal. (a, b, c) minimise Heitz
et al.'s error, the mean of |f cos - n D|^3 over samples of both the lobe and the LTC, each
weighted by the balance heuristic's 1/(p_f + p_LTC) (n: the lobe's integral), by Nelder-Mead
from the fit at the next rougher alpha. The table holds, per cell (alpha = u^2 with u in
[0, 1] on `alphas` points, cos(theta) = 1 - t^2 with t in [0, 1) on `size` points), the five
non-zero entries of M (m00, m02, m11, m20, m22) in the view's frame (x towards the view's
tangential direction; M rather than its inverse because its entries are near-linear in alpha,
so the table interpolates), the lobe's integral n and the fit's L1 error (the integral of
|f cos / n - D| over the sphere, 0 to 2). Each cell is fitted from the next rougher cell's and
from the last view angle's fit, keeping the better. Deterministic: fixed Sobol points.

The frame is fixed by the lobe's mean direction, not fitted: with a free turn about y as a
fourth parameter the cells' errors fall (median 0.043 against 0.066) but neighbouring cells
trade the turn against the skew b, and the matrices the shading interpolates between them are
worse (atrium at 320x180, polygon_glossy=ltc: FLIP 0.0547 against 0.0527; point 0.0534).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

ALPHA_MIN = 1e-4


def ggx_d(cos_h: np.ndarray, alpha: float) -> np.ndarray:
    c2 = np.clip(cos_h, 1e-12, 1.0) ** 2
    t2 = (1.0 - c2) / c2
    return np.where(cos_h > 0.0, 1.0 / (np.pi * alpha ** 2 * c2 ** 2 * (1.0 + t2 / alpha ** 2) ** 2), 0.0)


def smith_g1(cos_v: np.ndarray, alpha: float) -> np.ndarray:
    c2 = np.clip(cos_v, 1e-12, 1.0) ** 2
    t2 = (1.0 - c2) / c2
    return np.where(cos_v > 0.0, 2.0 / (1.0 + np.sqrt(1.0 + alpha ** 2 * t2)), 0.0)


def lobe(v: np.ndarray, l: np.ndarray, alpha: float) -> np.ndarray:
    """f cos(l) of the GGX reflection lobe (no Fresnel) for unit view ``v`` and directions ``l`` (N, 3)."""
    h = v[None, :] + l
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-20)
    ok = l[:, 2] > 0.0
    vh = h @ v
    g = smith_g1(np.full(len(l), v[2]), alpha) * smith_g1(l[:, 2], alpha) * (vh > 0.0) * ((l * h).sum(1) > 0.0)
    return np.where(ok, ggx_d(h[:, 2], alpha) * g / (4.0 * v[2]), 0.0)


def _reflected_pdf(h: np.ndarray, vh: np.ndarray, alpha: float) -> np.ndarray:
    """Density of the direction reflected about normals ``h`` drawn from D(h) cos(h)."""
    return ggx_d(h[:, 2], alpha) * h[:, 2] / np.maximum(4.0 * np.abs(vh), 1e-12)


def sample_lobe(v: np.ndarray, u: np.ndarray, alpha: float):
    """Directions from the GGX normal distribution reflected about the view: (l, pdf)."""
    t = np.arctan(alpha * np.sqrt(u[:, 0] / np.maximum(1.0 - u[:, 0], 1e-12)))
    phi = 2.0 * np.pi * u[:, 1]
    h = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], 1)
    vh = h @ v
    l = 2.0 * vh[:, None] * h - v[None, :]
    return l, _reflected_pdf(h, vh, alpha)


def lobe_pdf(v: np.ndarray, l: np.ndarray, alpha: float) -> np.ndarray:
    """The density :func:`sample_lobe` draws ``l`` with (0 below the horizon)."""
    h = v[None, :] + l
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-20)
    return np.where(l[:, 2] > 0.0, _reflected_pdf(h, h @ v, alpha), 0.0)


def ltc_eval(minv: np.ndarray, l: np.ndarray) -> np.ndarray:
    lo = l @ minv.T
    n = np.linalg.norm(lo, axis=1)
    z = lo[:, 2] / np.maximum(n, 1e-30)
    return np.maximum(z, 0.0) / np.pi * abs(np.linalg.det(minv)) / np.maximum(n, 1e-30) ** 3


def ltc_sample(m: np.ndarray, u: np.ndarray) -> np.ndarray:
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    lo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u[:, 0], 0.0))], 1)
    l = lo @ m.T
    return l / np.linalg.norm(l, axis=1, keepdims=True)


def frame_of(avg: np.ndarray) -> np.ndarray:
    """Columns x, y, z: z the mean direction, x in the plane of the view (y = 0 plane)."""
    z = avg / np.linalg.norm(avg)
    y = np.array([0.0, 1.0, 0.0])
    x = np.cross(y, z)
    x /= np.linalg.norm(x)
    return np.stack([x, y, z], 1)


def matrix(p, R: np.ndarray) -> np.ndarray:
    a, c, b = p
    return R @ np.array([[abs(a) + 1e-7, 0.0, b], [0.0, abs(c) + 1e-7, 0.0], [0.0, 0.0, 1.0]])


def fit_cell(v, alpha, u_f, u_l, p0):
    l_f, pdf_f = sample_lobe(v, u_f, alpha)
    f_f = lobe(v, l_f, alpha)
    w = np.where(pdf_f > 0.0, f_f / np.maximum(pdf_f, 1e-30), 0.0)
    norm = float(w.mean())
    avg = (l_f * w[:, None]).mean(0)
    avg[1] = 0.0
    R = frame_of(avg if np.linalg.norm(avg) > 0 else np.array([0.0, 0.0, 1.0]))

    def error(p):
        m = matrix(p, R)
        minv = np.linalg.inv(m)
        l_l = ltc_sample(m, u_l)
        d_l = ltc_eval(minv, l_l)
        f_l = lobe(v, l_l, alpha) / norm
        pf_l = lobe_pdf(v, l_l, alpha)
        e1 = np.abs(f_l - d_l) ** 3 / np.maximum(d_l + pf_l, 1e-30)
        d_f = ltc_eval(minv, l_f)
        e2 = np.abs(f_f / norm - d_f) ** 3 / np.maximum(d_f + pdf_f, 1e-30)
        return float(np.mean(e1) + np.mean(e2))

    res = minimize(error, p0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 800})
    m = matrix(res.x, R)
    return res.x, m, norm, float(res.fun)


def l1_error(v, alpha, m, norm, u):
    """Integral of |f cos / n - D| by both strategies (balance heuristic)."""
    minv = np.linalg.inv(m)
    l_f, pdf_f = sample_lobe(v, u, alpha)
    l_l = ltc_sample(m, u)
    tot = 0.0
    for l_s in (l_f, l_l):
        d = ltc_eval(minv, l_s)
        f = lobe(v, l_s, alpha) / norm
        pf = lobe_pdf(v, l_s, alpha)
        tot += np.mean(np.abs(f - d) / np.maximum(d + pf, 1e-30))
    return float(tot)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--alphas", type=int, default=64, help="table points in sqrt(alpha) (default 64)")
    ap.add_argument("--size", type=int, default=32, help="table points in the view angle (default 32)")
    ap.add_argument("--samples", type=int, default=512, help="samples per strategy in the fit's error (default 512)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "slc/lib/lights/ltc_ggx.npz"))
    o = ap.parse_args(argv)
    u_f = qmc.Sobol(2, scramble=True, seed=1).random(o.samples)
    u_l = qmc.Sobol(2, scramble=True, seed=2).random(o.samples)
    u_e = qmc.Sobol(2, scramble=True, seed=3).random(8192)
    na, nt = o.alphas, o.size
    m_t = np.zeros((na, nt, 5))
    norm_t = np.zeros((na, nt))
    err_t = np.zeros((na, nt))
    prev = {}
    t0 = time.time()
    for j in range(nt):                               # view angle: cos = 1 - t^2
        t = j / nt
        ct = max(1.0 - t * t, 1e-3)
        v = np.array([np.sqrt(1.0 - ct * ct), 0.0, ct])
        p = np.array([1.0, 1.0, 0.0])
        for i in reversed(range(na)):                 # roughness, rough to smooth
            alpha = max((i / (na - 1)) ** 2, ALPHA_MIN)
            best = None
            for p0 in [p] + ([prev[i]] if i in prev else []):    # from the rougher fit, the last view's
                q, m, norm, e = fit_cell(v, alpha, u_f, u_l, p0)
                if best is None or e < best[3]:
                    best = (q, m, norm, e)
            p, m, norm, _ = best
            prev[i] = p
            m_t[i, j] = [m[0, 0], m[0, 2], m[1, 1], m[2, 0], m[2, 2]]
            norm_t[i, j] = norm
            err_t[i, j] = l1_error(v, alpha, m, norm, u_e)
        print(f"cos {ct:.3f}: L1 error max {err_t[:, j].max():.3f}, {time.time() - t0:.0f} s", file=sys.stderr)
    np.savez_compressed(o.out, m=m_t.astype(np.float32), norm=norm_t.astype(np.float32),
                        l1=err_t.astype(np.float32), alpha_min=ALPHA_MIN)
    print(f"wrote {o.out}: L1 error median {np.median(err_t):.3f}, max {err_t.max():.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
