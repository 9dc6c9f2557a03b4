"""osc-gi's direct light per pixel (``direct``), its stratified light samples, and the edge of the
secondary cells (``secondary_cm``, ``secondary_scene``)."""
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc import methods

from slc.reference import references

from slc.scene import views

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_oscgi import _run  # noqa: E402


@pytest.fixture(scope="module")
def cornell(scene):
    return scene("cornell")


def test_per_pixel_direct_light_is_unbiased_and_leaves_the_cache_alone(cornell):
    """``direct=rt`` (default): the cache runs as for ``output=indirect`` (same random numbers, same
    cells), so full minus indirect is the per-pixel RT-16 estimate alone: its mean is within 3% of
    the 2048-sample direct ground truth (the cached direct light of ``direct=cache`` is checked by
    the full-output test of test_oscgi.py)."""
    vs = views.single(cornell)
    mf, gbs, (full,) = _run(cornell, "osc-gi", vs, 4)
    mi_, _, (ind,) = _run(cornell, "osc-gi:output=indirect", vs, 4)
    assert mf.direct == "rt" and not mf.primary.cache_direct
    assert mf.secondary.used_cells() == mi_.secondary.used_cells()
    assert np.array_equal(np.array(mf.storage), np.array(mi_.storage))       # the same cache
    gt = references.reference_for("direct", cornell, gbs[0], 0, "test")
    d = full - ind
    valid = np.array(gbs[0].valid).reshape(gt.shape[:2])
    assert np.isfinite(d).all()
    assert abs(d[valid].mean() / gt[valid].mean() - 1.0) < 0.03, (d[valid].mean(), gt[valid].mean())


@pytest.mark.slow
@pytest.mark.parametrize("direct", ["cache", "cones", "restir"])
def test_other_direct_options_approach_the_full_reference(cornell, direct):
    """The cached direct light and the cones / ReSTIR run beside the cache: finite, and the full image
    within 15% of the reference's mean after 8 still frames at 32x18."""
    m, gbs, (img,) = _run(cornell, f"osc-gi:direct={direct}", views.single(cornell), 8, 32, 18)
    ref = references.reference_for("full", cornell, gbs[0], 0, "test", spp=128, bounces=2)
    valid = np.array(gbs[0].valid).reshape(ref.shape[:2])
    assert np.isfinite(img).all()
    assert abs(img[valid].mean() / ref[valid].mean() - 1.0) < 0.15, (img[valid].mean(), ref[valid].mean())
    assert (m._sub is not None) == (direct != "cache")


def test_cell_edge_follows_the_scene_size(cornell):
    """max(secondary_cm, secondary_scene x diagonal); the default: 15 cm or 4% of the diagonal,
    whichever is larger."""
    diag = float(np.linalg.norm(np.array(cornell.mi_scene.bbox().max) - np.array(cornell.mi_scene.bbox().min)))

    def edge(spec):
        return methods.create(spec, cornell)._cell_edge()

    assert edge("osc-gi") == pytest.approx(max(0.15, 0.04 * diag))                 # the default
    assert edge("osc-gi:secondary_cm=1") == pytest.approx(0.04 * diag)             # scene fraction
    assert edge("osc-gi:secondary_cm=30,secondary_scene=0") == pytest.approx(0.30)
    assert edge("osc-gi:secondary_cm=1,secondary_scene=0") == pytest.approx(0.01)  # both off


@pytest.mark.slow
def test_stratified_light_samples_are_unbiased_and_less_noisy(cornell):
    """``direct_lds`` (default): a pixel's n light samples are a Hammersley set shifted by a random
    offset per pixel and frame. Averaged over 64 frames (new offsets), RT-4's image converges to the
    2048-sample direct ground truth as the independent samples do (image mean within 1%, per-pixel
    error no larger), and a single frame's error is smaller than with independent samples. Measured
    on Cornell at 32x18: mean 0.9999 (independent 0.9994), RMSE of one frame 0.73x, of the 64-frame
    average 0.66x that of independent samples."""
    from slc.scene.lights import light_inputs
    from slc.core.keys import stream_key
    from slc.scene.lights import diffuse_flags
    from slc.methods.oscgi.kernels import STREAM_PIXEL_DIRECT, pixel_direct_kernel
    from slc.scene.gbuffer import frame_gbuffers
    gb = frame_gbuffers(cornell, views.single(cornell), 0, 32, 18)[0]
    sc = cornell.mi_scene
    gt = references.reference_for("direct", cornell, gb, 0, "test")
    valid = np.array(gb.valid).reshape(gt.shape[:2])
    idx = dr.arange(mi.UInt32, dr.width(gb.valid))
    err1, err64, means = {}, {}, {}
    for lds in (True, False):
        imgs = np.stack([references.image_of("full", gb, pixel_direct_kernel(
            sc, light_inputs(sc), diffuse_flags(sc), gb.si, mi.Bool(gb.valid), idx,
            stream_key(0, f, STREAM_PIXEL_DIRECT), dr.opaque(mi.UInt32, 4), lds)) for f in range(64)])
        assert np.isfinite(imgs).all()
        avg = imgs.mean(0)
        means[lds] = avg[valid].mean() / gt[valid].mean()
        err1[lds] = np.sqrt(np.mean((imgs[:, valid] - gt[valid]) ** 2))
        err64[lds] = np.sqrt(np.mean((avg[valid] - gt[valid]) ** 2))
    assert abs(means[True] - 1.0) < 0.01, means
    assert err64[True] <= 1.05 * err64[False], err64
    assert err1[True] < 0.85 * err1[False], err1
