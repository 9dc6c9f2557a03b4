"""The CRC paper's image comparisons: CIE Lab RMSE (:func:`slc.reference.metrics.lab_rmse`)
and PerceptualDiff ("pdiff"), the percentage of pixels that Yee and Newman's
perceptual metric (SIGGRAPH 2004 sketch; the ``perceptualdiff`` tool the
paper used) finds visibly different.

:func:`pdiff` follows ``perceptualdiff``'s per-pixel test (as in its
C++ source, also ported as OpenImageIO's ``compare_Yee``), with its
defaults: field of view 45 degrees, adaptation luminance scale 100 cd/m^2,
colour factor 1.

1. RGB -> XYZ with the Adobe RGB (1998) matrix (D65) of the tool, XYZ ->
   CIE Lab with the white point of RGB = (1, 1, 1); the luminance image is
   ``Y * 100`` cd/m^2. Input here: linear HDR images times the exposure,
   clipped to [0, 1] (the tool linearises 8-bit images with gamma 2.2 first;
   ours are linear already).
2. A Gaussian "pyramid" of 8 levels of the luminance (all at full
   resolution: level i+1 = level i convolved with the separable kernel
   [0.05, 0.25, 0.4, 0.25, 0.05], borders mirrored).
3. Per pixel: contrast per level i < 6, ``max(|a_i - a_{i+1}|, |b_i -
   b_{i+1}|) / max(|a_{i+2}|, |b_{i+2}|, 1e-5)``; the adaptation luminance
   ``adapt`` = mean of the two images at the level whose width first
   exceeds one degree of view; the threshold elevation ``factor`` = sum_i
   contrast_i F_freq,i F_mask,i / sum contrast, clamped to [1, 10], with
   Barten's contrast sensitivity (``F_freq = csf(3.248, 100) / csf(cpd_i,
   100)``, ``cpd_0`` = half the pixels per degree, halved per level) and
   Daly's masking of ``contrast_i * csf(cpd_i, adapt)``.
4. The pixel *fails* when ``|a_0 - b_0| > factor * tvi(adapt)`` (Ward
   Larson's threshold-versus-intensity), or else when the colour
   difference ``(da^2 + db^2) * colour_scale > factor`` (Lab a*, b*;
   ``colour_scale`` = 1, scaled to 0.01 below 10 cd/m^2 as in the
   OpenImageIO port).

pdiff = 100 * failed pixels / pixels. :func:`de76_fraction` is the simpler
measure used here before: percent of pixels whose CIE76 difference exceeds
2.3 (one JND).
"""
from __future__ import annotations

import math

import numpy as np

JND_CIE76 = 2.3
PYRAMID_LEVELS = 8
_KERNEL = np.array([0.05, 0.25, 0.4, 0.25, 0.05])
_ADOBE_TO_XYZ = np.array([[0.576700, 0.185556, 0.188212],
                          [0.297361, 0.627355, 0.0752847],
                          [0.0270328, 0.0706879, 0.991248]])


def _lab(img, exposure):
    import colour  # optional and slow to import: only where a Lab figure is asked for
    rgb = np.clip(np.asarray(img, np.float64) * exposure, 0.0, 1.0)
    xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    return colour.XYZ_to_Lab(xyz)


def delta_e76(reference_hdr, test_hdr, exposure: float = 1.0) -> np.ndarray:
    import colour  # optional and slow to import: only where a Lab figure is asked for
    return colour.delta_E(_lab(reference_hdr, exposure), _lab(test_hdr, exposure), method="CIE 1976")


def de76_fraction(reference_hdr, test_hdr, exposure: float = 1.0, threshold: float = JND_CIE76) -> float:
    """Percent of pixels with CIE76 dE > ``threshold`` (not the paper's pdiff)."""
    d = delta_e76(reference_hdr, test_hdr, exposure)
    return float(np.mean(d > threshold) * 100.0)


# ---------------------------------------------------------------------------
# Yee and Newman's PerceptualDiff
# ---------------------------------------------------------------------------

def _xyz_lab_yee(rgb: np.ndarray):
    """(Lab, Y) with the tool's Adobe RGB matrix and white point."""
    xyz = rgb @ _ADOBE_TO_XYZ.T
    white = _ADOBE_TO_XYZ.sum(1)
    r = xyz / white
    eps, kappa = 216.0 / 24389.0, 24389.0 / 27.0
    f = np.where(r > eps, np.cbrt(r), (kappa * r + 16.0) / 116.0)
    lab = np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)
    return lab, xyz[..., 1]


def _blur(img: np.ndarray) -> np.ndarray:
    """Separable 5-tap convolution, borders mirrored as in the tool
    (index -i -> i, index n-1+i -> n-i)."""
    out = img
    for axis in (0, 1):
        n = out.shape[axis]
        idx = np.arange(-2, n + 2)
        idx = np.where(idx < 0, -idx, idx)
        idx = np.where(idx >= n, 2 * n - idx - 1, idx)
        idx = np.clip(idx, 0, n - 1)
        ext = np.take(out, idx, axis=axis)
        acc = np.zeros_like(out)
        for k, w in enumerate(_KERNEL):
            acc += w * np.take(ext, np.arange(k, k + n), axis=axis)
        out = acc
    return out


def _pyramid(lum: np.ndarray) -> list:
    levels = [lum]
    for _ in range(PYRAMID_LEVELS - 1):
        levels.append(_blur(levels[-1]))
    return levels


def _csf(cpd, lum):
    """Barten's contrast sensitivity (cycles per degree, cd/m^2)."""
    a = 440.0 * np.power(1.0 + 0.7 / lum, -0.2)
    b = 0.3 * np.power(1.0 + 100.0 / lum, 0.15)
    return a * cpd * np.exp(-b * cpd) * np.sqrt(1.0 + 0.06 * np.exp(b * cpd))


def _mask(contrast):
    """Daly's visual masking."""
    a = np.power(392.498 * contrast, 0.7)
    b = np.power(0.0153 * a, 4.0)
    return np.power(1.0 + b, 0.25)


def _tvi(adapt):
    """Ward Larson's threshold versus intensity [cd/m^2]."""
    la = np.log10(adapt)
    r = np.select([la < -3.94, la < -1.44, la < -0.0184, la < 1.9],
                  [np.full_like(la, -2.86),
                   np.power(np.maximum(0.405 * la + 1.6, 0.0), 2.18) - 2.86,
                   la - 0.395,
                   np.power(np.maximum(0.249 * la + 0.65, 0.0), 2.7) - 0.72],
                  la - 1.255)
    return np.power(10.0, r)


def pdiff_map(reference_hdr, test_hdr, exposure: float = 1.0, fov: float = 45.0, luminance: float = 100.0,
              colour_factor: float = 1.0) -> np.ndarray:
    """(H, W) bool: the pixels PerceptualDiff finds visibly different."""
    a = np.clip(np.asarray(reference_hdr, np.float64) * exposure, 0.0, 1.0)
    b = np.clip(np.asarray(test_hdr, np.float64) * exposure, 0.0, 1.0)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"pdiff needs two (H, W, 3) images of one size, got {a.shape} and {b.shape}")
    lab_a, ya = _xyz_lab_yee(a)
    lab_b, yb = _xyz_lab_yee(b)
    la, lb = _pyramid(ya * luminance), _pyramid(yb * luminance)
    width = a.shape[1]
    one_degree = 2.0 * math.tan(math.radians(fov) * 0.5) * 180.0 / math.pi
    ppd = width / one_degree
    adaptation_level, npix = 0, 1
    for i in range(PYRAMID_LEVELS):
        if npix > one_degree:
            break
        adaptation_level = i
        npix *= 2
    cpd = 0.5 * ppd * 0.5 ** np.arange(PYRAMID_LEVELS)
    f_freq = _csf(3.248, 100.0) / _csf(cpd, 100.0)
    contrast = []
    for i in range(PYRAMID_LEVELS - 2):
        num = np.maximum(np.abs(la[i] - la[i + 1]), np.abs(lb[i] - lb[i + 1]))
        den = np.maximum(np.maximum(np.abs(la[i + 2]), np.abs(lb[i + 2])), 1e-5)
        contrast.append(num / den)
    sum_contrast = np.maximum(sum(contrast), 1e-5)
    adapt = np.maximum(0.5 * (la[adaptation_level] + lb[adaptation_level]), 1e-5)
    factor = sum(c * f_freq[i] * _mask(c * _csf(cpd[i], adapt)) for i, c in enumerate(contrast)) / sum_contrast
    factor = np.clip(factor, 1.0, 10.0)
    lum_fail = np.abs(la[0] - lb[0]) > factor * _tvi(adapt)
    colour_scale = np.where(adapt < 10.0, (1.0 - (10.0 - colour_factor) / 10.0) ** 2, colour_factor)
    d_ab = ((lab_a[..., 1] - lab_b[..., 1]) ** 2 + (lab_a[..., 2] - lab_b[..., 2]) ** 2) * colour_scale
    return lum_fail | (d_ab > factor)


def pdiff(reference_hdr, test_hdr, exposure: float = 1.0, fov: float = 45.0) -> float:
    """PerceptualDiff: percent of pixels visibly different (see the module text)."""
    return float(np.mean(pdiff_map(reference_hdr, test_hdr, exposure, fov)) * 100.0)
