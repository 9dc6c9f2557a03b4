"""Image metrics against the ground truth.

- FLIP: the official ``flip-evaluator``, **LDR-FLIP on the tone-mapped
  images** (the tone map of :func:`slc.core.io.tonemap`), the same choice
  everywhere. Lower is better; 0 for identical images.
- PSNR and SSIM (scikit-image) on the same tone-mapped images, data range 1.
  PSNR of identical images is +inf (reported as ``inf`` in JSON).
- Relative MSE on HDR: mean over pixels and channels of
  ``(x - y)^2 / (y^2 + 1e-2)``.
- CIE Lab RMSE (colour-science): linear sRGB (exposure applied, clipped to
  [0, 1]) -> XYZ -> Lab (D65); RMSE of the per-pixel CIE76 difference,
  divided by 100 (the L* range) and given in percent.
"""
from __future__ import annotations

import math

import flip_evaluator as fe
import numpy as np
from skimage.metrics import structural_similarity

from slc.core.io import tonemap


def flip(reference_ldr: np.ndarray, test_ldr: np.ndarray):
    """(mean LDR-FLIP, error map HxW) of two tone-mapped sRGB images."""
    ref = np.ascontiguousarray(np.clip(reference_ldr, 0, 1), dtype=np.float32)
    tst = np.ascontiguousarray(np.clip(test_ldr, 0, 1), dtype=np.float32)
    emap, mean, _ = fe.evaluate(ref, tst, "LDR", inputsRGB=True, applyMagma=False)
    return float(mean), np.asarray(emap, np.float32).squeeze()


def psnr(reference_ldr, test_ldr) -> float:
    mse = float(np.mean((np.asarray(reference_ldr, np.float64) - np.asarray(test_ldr, np.float64)) ** 2))
    if mse <= 0.0:
        return math.inf
    return 10.0 * math.log10(1.0 / mse)


def ssim(reference_ldr, test_ldr) -> float:
    r, t = np.asarray(reference_ldr, np.float64), np.asarray(test_ldr, np.float64)
    win = min(7, min(r.shape[0], r.shape[1]) // 2 * 2 - 1)
    return float(structural_similarity(r, t, channel_axis=2, data_range=1.0, win_size=max(win, 3)))


def rel_mse(reference_hdr, test_hdr, eps: float = 1e-2) -> float:
    r, t = np.asarray(reference_hdr, np.float64), np.asarray(test_hdr, np.float64)
    return float(np.mean((t - r) ** 2 / (r ** 2 + eps)))


def lab_rmse(reference_hdr, test_hdr, exposure: float = 1.0) -> float:
    import colour  # colour-science takes seconds to import: only when a Lab error is asked for
    def lab(img):
        rgb = np.clip(np.asarray(img, np.float64) * exposure, 0.0, 1.0)
        xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
        return colour.XYZ_to_Lab(xyz)
    d = colour.delta_E(lab(reference_hdr), lab(test_hdr), method="CIE 1976")
    return float(np.sqrt(np.mean(d ** 2)) / 100.0 * 100.0)


def evaluate(reference_hdr, test_hdr, exposure: float = 1.0, with_map: bool = False) -> dict:
    """All metrics of one image. ``with_map`` adds the FLIP error map."""
    r_ldr, t_ldr = tonemap(reference_hdr, exposure), tonemap(test_hdr, exposure)
    f, fmap = flip(r_ldr, t_ldr)
    out = {"flip": f, "psnr": psnr(r_ldr, t_ldr), "ssim": ssim(r_ldr, t_ldr),
           "rel_mse": rel_mse(reference_hdr, test_hdr),
           "lab_rmse": lab_rmse(reference_hdr, test_hdr, exposure)}
    if with_map:
        out["flip_map"] = fmap
    return out
