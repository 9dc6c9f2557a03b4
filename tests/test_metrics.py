import math

import numpy as np

from slc.core import io

from slc.reference import metrics


def _img(seed=0, shape=(40, 56, 3)):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def test_identical_images_are_the_limits():
    """The limits of each metric (FLIP 0, PSNR +inf, SSIM 1, errors 0) on two
    separately built copies; the metrics' values on known differences are
    checked below."""
    a = _img()
    m = metrics.evaluate(a, a.copy())
    assert m["flip"] == 0.0
    assert math.isinf(m["psnr"]) and m["psnr"] > 0
    assert m["ssim"] == 1.0 and m["rel_mse"] == 0.0 and m["lab_rmse"] == 0.0


def _lstar(Y):
    """CIE 1976 lightness of relative luminance Y (white Y = 1)."""
    Y = np.asarray(Y, np.float64)
    return np.where(Y > (6 / 29) ** 3, 116 * np.cbrt(Y) - 16, Y * (29 / 3) ** 3)


def test_lab_rmse_of_a_known_lightness_difference():
    """Grey pixels have a* = b* = 0, so their CIE76 difference is the L* difference
    (CIE formula, computed here without colour-science). Half the pixels at grey
    0.18 vs 0.5 (after exposure), the other half equal: RMSE = dL* / sqrt(2)."""
    a = np.full((20, 30, 3), 0.09, np.float32)
    b = a.copy()
    b[:10] = 0.25
    exp = 2.0
    dL = _lstar(0.5) - _lstar(0.18)
    assert abs(metrics.lab_rmse(a, b, exposure=exp) - dL / math.sqrt(2)) < 1e-3
    # clipping to [0, 1] after exposure: 1.0 and 3.0 are the same white
    assert metrics.lab_rmse(np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 1.5), exposure=2.0) < 1e-6


def test_ssim_closed_forms():
    """Constant images x = a, y = b (no structure): SSIM = (2ab + C1) / (a^2 + b^2 + C1),
    C1 = (0.01 * data range)^2. A constant offset c on a random image leaves the
    contrast-structure term at 1, so SSIM is the mean over 7x7 windows of the
    luminance term of the local means (scipy's uniform filter, crop 3)."""
    C1 = 1e-4
    for a, b in ((0.2, 0.3), (0.5, 0.05), (0.9, 0.7)):
        x, y = np.full((32, 40, 3), a), np.full((32, 40, 3), b)
        assert abs(metrics.ssim(x, y) - (2 * a * b + C1) / (a * a + b * b + C1)) < 1e-9
    from scipy.ndimage import uniform_filter
    x = _img(3).astype(np.float64) * 0.5
    c = 0.2
    mu = np.stack([uniform_filter(x[..., k], 7) for k in range(3)], axis=-1)
    lum = (2 * mu * (mu + c) + C1) / (mu ** 2 + (mu + c) ** 2 + C1)
    expected = lum[3:-3, 3:-3].mean()
    got = metrics.ssim(x, x + c)
    assert abs(got - expected) < 1e-6, (got, expected)
    assert got < 0.95


def test_known_perturbation_psnr():
    a = _img() * 0.9
    # a uniform offset of 0.01 on [0, 1] images: MSE 1e-4 -> PSNR 40 dB
    assert abs(metrics.psnr(a, a + 0.01) - 40.0) < 1e-3
    b = a.copy()
    b[::2] += 0.1  # half the rows off by 0.1: MSE 5e-3 -> 23.01 dB
    assert abs(metrics.psnr(a, b) - 10 * math.log10(1 / 5e-3)) < 1e-2


def test_flip_grows_with_error_and_rel_mse_closed_form():
    a = _img(1) * 0.5 + 0.1
    small, large = a * 1.02, a * 1.5
    assert 0 < metrics.evaluate(a, small)["flip"] < metrics.evaluate(a, large)["flip"]
    # rel_mse of a 10% scale error: mean(0.01 a^2 / (a^2 + 1e-2))
    expected = np.mean(0.01 * a.astype(np.float64) ** 2 / (a.astype(np.float64) ** 2 + 1e-2))
    assert abs(metrics.rel_mse(a, a * 1.1) - expected) < 1e-6


def test_tonemap_is_bounded_and_finite():
    x = np.array([[[0.0, 1.0, 1e9], [np.nan, np.inf, -1.0]]], np.float32)
    y = io.tonemap(x)
    assert np.isfinite(y).all() and y.min() >= 0 and y.max() <= 1
    assert y[0, 0, 0] == 0.0 and y[0, 0, 2] > 0.99


def test_exr_round_trip_and_atomic_writes(tmp_path):
    a = _img(2) * 100
    io.write_exr(tmp_path / "a.exr", a)
    b = io.read_exr(tmp_path / "a.exr")
    assert np.allclose(a, b, rtol=1e-6)
    assert not list(tmp_path.glob(".tmp-*"))
