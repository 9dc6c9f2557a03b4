"""The hard cases of DESIGN.md for the ground truth, RT-N and ReSTIR, run in
check mode (SLC_CHECK=1: the first NaN/Inf or negative value in any stage
output or returned image raises), with error bounds against an independent
reference instead of finiteness alone:

- rectangular lights: a deterministic midpoint quadrature over the light with
  exact visibility (:func:`helpers.quadrature_direct`, 64 x 64 points; pixels
  where it has not converged, i.e. differs from a 32 x 32 quadrature by more
  than 0.1%, are left out: a few next to the grazing light and in the
  penumbra of the box);
- the hemisphere-sized light: the closed-form irradiance of a rectangle;
- the point light: the closed form I cos / d^2 (through the same quadrature);
- zero radiance: exactly 0.

Plane pixels only (y = 0; the box top for ``inside`` is excluded with the
light seen directly). Measured figures are in each test's docstring.
"""
import numpy as np
import pytest

from helpers import HARD_POINT, HARD_RECTS, hard_scene, quadrature_direct, rect_irradiance, z_test
from slc import check, methods, views
from slc.groundtruth import direct_mis
from slc.methods import FrameContext
from slc.pipeline import gbuffers_for
from slc.timing import StageTimer

W, H = 48, 32
KINDS = ["grazing", "point", "hemisphere", "zero", "huge", "inside"]


@pytest.fixture(autouse=True)
def check_mode(monkeypatch):
    monkeypatch.setenv(check.ENV, "1")


_CACHE = {}


def case(kind):
    """(scene, G-buffer, reference N x 3, mask of tested pixels)."""
    if kind in _CACHE:
        return _CACHE[kind]
    sc = hard_scene(kind)
    gb = gbuffers_for(sc, views.single(sc), 0, W, H)[0]
    p = np.array(gb.si.p).T
    mask = np.array(gb.valid) & (np.abs(p[:, 1]) < 1e-4)
    if kind == "hemisphere":
        (c, u, v, L), = HARD_RECTS[kind].values()
        E = rect_irradiance(p[:, 0], p[:, 2], -u[0], u[0], -v[2], v[2], c[1], L)
        ref = np.repeat((0.5 / np.pi * E)[:, None], 3, axis=1)
    else:
        rects = list(HARD_RECTS.get(kind, {}).values())
        pts = [HARD_POINT] if kind == "point" else []
        ref = quadrature_direct(sc, gb, rects, pts, n=64)
        coarse = quadrature_direct(sc, gb, rects, pts, n=32)
        mask &= np.abs(ref - coarse).max(axis=1) <= 1e-3 * np.maximum(ref.max(axis=1), 1e-12)
    assert mask.sum() > 800, (kind, mask.sum())
    _CACHE[kind] = (sc, gb, ref, mask)
    return _CACHE[kind]


def render(spec, sc, gb, frames=1, seed=0):
    """Direct light of the last of ``frames`` frames (N x 3), every stage output
    and the returned image checked (check mode)."""
    m = methods.create(spec, sc, seed=seed)
    timer = StageTimer()
    for f in range(frames):
        timer.begin_frame()
        with check.scope(spec, f, [gb]):
            d = m.render(FrameContext(f), [gb], timer)
            check.images(d, [gb])
        timer.end_frame()
    return np.array(d[0], np.float64).T


def rel_errors(img, ref, mask):
    a, r = img[mask], ref[mask]
    return abs(a.mean() / r.mean() - 1.0), np.abs(a - r).mean() / r.mean()


@pytest.mark.parametrize("kind", KINDS)
def test_ground_truth_hard_cases(kind):
    """2048 MIS samples. Measured (48x32): grazing mean -0.3%, per-pixel mean
    error 1.8%; hemisphere 0.01% / 0.3%; huge 0.00% / 0.09%; inside 0.02% / 0.44%;
    point exact (one delta light: no variance); zero exactly 0. Asserted: mean
    within 1%, per-pixel mean error below 3% (0.5% for huge and hemisphere)."""
    sc, gb, ref, mask = case(kind)
    gt = np.array(direct_mis(sc.mi_scene, gb, 2048), np.float64).T
    check.array(gt, f"ground truth ({kind})")
    if kind == "zero":
        assert np.all(gt == 0.0)
        return
    mean_err, pix_err = rel_errors(gt, ref, mask)
    assert mean_err < 0.01, (kind, mean_err)
    assert pix_err < (0.005 if kind in ("huge", "hemisphere") else 0.03), (kind, pix_err)


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "hemisphere"])
def test_rt_hard_cases_per_pixel_z_test(kind):
    """32 independent runs of rt16 (seeds 0..31) against the reference, per-pixel
    Z-test (Sidak-corrected 1% significance over all pixels and channels): an
    unbiased estimator must pass it at every pixel."""
    sc, gb, ref, mask = case(kind)
    runs = np.stack([render("rt16", sc, gb, seed=s) for s in range(32)])
    if kind == "zero":
        assert np.all(runs == 0.0)
        return
    t = z_test(runs[:, mask], ref[mask])
    assert t["p_min"] > t["alpha"], (kind, t["p_min"], t["alpha"], len(t["failed"]))
    # and the test has power: a 2% bias is rejected (measured smallest p-values ~1e-30 and below)
    t2 = z_test(runs[:, mask] * 1.02, ref[mask])
    assert t2["p_min"] < t2["alpha"], (kind, t2["p_min"])


def test_rt_hemisphere_light_image_mean():
    """Area sampling of a 120 m light 2 m above a point has a heavy tail (a
    sample straight below weighs about 1000x the mean): per pixel the relative
    standard deviation of one sample is about 20, so rt is unbiased but a
    per-pixel Z-test at practical sample counts is not meaningful (the sample
    variance itself does not converge). Asserted instead: the image mean of 16
    runs of rt64 is within 4 standard errors of the closed form (measured
    standard error about 2%), and the ground truth (MIS) gets the same
    pixels within 0.5% (test above)."""
    sc, gb, ref, mask = case("hemisphere")
    runs = np.stack([render("rt64", sc, gb, seed=s)[mask].mean() for s in range(16)])
    se = runs.std(ddof=1) / np.sqrt(len(runs))
    r = ref[mask].mean()
    assert se < 0.05 * r, (se, r)
    assert abs(runs.mean() - r) < 4 * se, (runs.mean(), r, se)


RESTIR_BOUNDS = {  # kind: (mean, per-pixel mean error), about 1.5x the measured figures
    "grazing": (0.02, 0.06), "point": (1e-4, 1e-4), "hemisphere": (0.02, 0.04),
    "huge": (0.005, 0.003), "inside": (0.04, 0.05),
}


@pytest.mark.parametrize("kind", KINDS)
def test_restir_hard_cases(kind):
    """ReSTIR (RTXDI defaults: temporal + spatial reuse, bias=basic, initial
    visibility), 4 frames at a still camera, averaged over 8 independent seeds
    (frames of one run are correlated through the reservoirs, seeds are not).
    Measured (48x32; mean error, per-pixel mean error): grazing 0.15%, 3.9%;
    hemisphere 0.23%, 2.6%; huge 0.02%, 0.17%; inside 2.6%, 3.4% (darker: the
    known bias of RTXDI's initial visibility with basic 1/Z weights, an occluded
    initial sample keeps its M, see docs/restir.md); point exact; zero exactly 0.
    Bounds in RESTIR_BOUNDS."""
    sc, gb, ref, mask = case(kind)
    img = np.mean([render("restir", sc, gb, frames=4, seed=s) for s in range(8)], axis=0)
    if kind == "zero":
        assert np.all(img == 0.0)
        return
    mean_err, pix_err = rel_errors(img, ref, mask)
    print(f"restir {kind}: mean error {mean_err:.4f}, per-pixel {pix_err:.4f}")
    bm, bp = RESTIR_BOUNDS[kind]
    assert mean_err < bm and pix_err < bp, (kind, mean_err, pix_err)
