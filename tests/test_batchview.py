"""``slc:batch=viewers``: all viewers' pixels shaded in one launch give the
per-viewer images bit for bit (random numbers keyed by each pixel's index within
its own viewer), in one call of the frozen shading per frame, with one recording,
and no kernel built after warm-up."""
import numpy as np
import pytest

from helpers import render_frames
from slc import methods
from slc.scene import views

W, H, FRAMES = 48, 27, 4


@pytest.fixture(scope="module")
def atrium(scene):
    return scene("atrium")


def _run(scene, spec, rig):
    m = methods.create(spec, scene, seed=3)
    imgs, _ = render_frames(scene, m, rig, frames=FRAMES, width=W, height=H, seed=3)
    return m, imgs


@pytest.mark.fresh_process
@pytest.mark.slow
@pytest.mark.parametrize("fetch", ["nearest", "bilinear"])
def test_batched_images_equal_per_viewer(atrium, fetch):
    """Three moving viewers at 60 % overlap (different entries per pixel and viewer),
    glossy and Lambertian pixels: the batched images equal the per-viewer ones exactly.
    The bilinear fetch is not batched (taps are per viewer) and falls back."""
    rig = views.overlap_rig(atrium, 3, 0.6)
    m0, per_viewer = _run(atrium, f"slc:fetch={fetch},batch=off", rig)
    m1, batched = _run(atrium, f"slc:fetch={fetch},batch=viewers", rig)
    assert len(batched) == 3
    assert all(img.max() > 0 for img in batched)
    assert not np.array_equal(batched[0], batched[1])
    for a, b in zip(per_viewer, batched):
        assert np.array_equal(a, b)
    # one shading call per frame when batched, one per viewer (and tap) otherwise
    calls_off, calls_on = m0._cone_shading.calls, m1._cone_shading.calls
    if fetch == "nearest":
        assert (calls_off, calls_on) == (3 * FRAMES, FRAMES)
        assert m1._cone_shading.n_recordings == 1
    else:
        assert calls_on == calls_off


def test_single_viewer_unchanged_by_batch(atrium):
    """One viewer takes the per-viewer path (nothing to batch)."""
    rig = views.overlap_rig(atrium, 1, 1.0)
    _, a = _run(atrium, "slc:batch=off", rig)
    _, b = _run(atrium, "slc:batch=viewers", rig)
    assert np.array_equal(a[0], b[0])


@pytest.mark.slow      # a fresh interpreter counting kernels
def test_batched_no_kernel_built_after_warmup():
    from test_compile import _run_case
    r = _run_case("slc:batch=viewers", "random", 4)
    assert r["compiled_after_warmup"] == 0, f"kernels built per frame {r['per_frame']}"
