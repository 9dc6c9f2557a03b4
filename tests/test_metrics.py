import math

import numpy as np

from slc import io, metrics


def _img(seed=0, shape=(40, 56, 3)):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def test_identical_images():
    a = _img()
    m = metrics.evaluate(a, a)
    assert m["flip"] == 0.0
    assert math.isinf(m["psnr"]) and m["psnr"] > 0
    assert m["ssim"] == 1.0 and m["rel_mse"] == 0.0 and m["lab_rmse"] == 0.0


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
