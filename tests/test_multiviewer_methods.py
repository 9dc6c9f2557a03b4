"""Multi-viewer correctness of rt, restir and sh: a second viewer does not
change the first viewer's image (per-viewer methods: exactly; the shared SH
cache: exactly for still cameras, within a stated bound when moving), and
identical viewers of the shared cache get identical images."""
import numpy as np
import pytest

from helpers import render_frames
from slc import methods
from slc.scene import camera, views

W, H, FRAMES = 48, 27, 5


@pytest.fixture(scope="module")
def cornell(scene):
    return scene("cornell")


def _still(rig):
    return [camera.Viewer(v.name, (lambda f, c=v.camera(0): c), v.rig) for v in rig]


def _images(scene, spec, vs, frames=FRAMES):
    m = methods.create(spec, scene, seed=4)
    imgs, _ = render_frames(scene, m, vs, frames=frames, width=W, height=H, seed=4)
    return imgs


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["rt8", "restir", "restir:spatial=4"])
def test_second_viewer_leaves_first_unchanged(cornell, spec):
    """Per-viewer methods keep per-viewer state and random streams keyed by the
    viewer's index: the first viewer's image is bit-identical with and without a
    second viewer looking elsewhere, on moving cameras."""
    one = _images(cornell, spec, views.overlap_rig(cornell, 1, 0.6))
    two = _images(cornell, spec, views.overlap_rig(cornell, 2, 0.6))
    assert not np.array_equal(two[0], two[1])
    assert np.array_equal(one[0], two[0])


@pytest.mark.parametrize("spec", ["rt8", "restir"])
def test_identical_viewers_differ_by_noise_only(cornell, spec):
    """Two viewers at the same pose draw independent samples (a viewer is not a
    copy of another), so their images differ, but by noise only: the mean over the
    image agrees within 2%."""
    a, b = _images(cornell, spec, views.overlap_rig(cornell, 2, 1.0))
    assert not np.array_equal(a, b)
    assert abs(a.mean() / b.mean() - 1) < 0.02


@pytest.mark.slow
def test_sh_identical_viewers_identical_images(cornell):
    pytest.importorskip("slc.methods.sh")
    one = _images(cornell, "sh", views.overlap_rig(cornell, 1, 1.0))
    two = _images(cornell, "sh", views.overlap_rig(cornell, 2, 1.0))
    assert np.array_equal(two[0], two[1])
    assert np.array_equal(one[0], two[0])


@pytest.mark.slow
def test_sh_second_viewer(cornell):
    """Moving and still cameras: at most 5% of the first viewer's pixels change with a
    second viewer (40% of the screen away) and the mean change is below 1% of the image
    mean (an entry the second viewer saw first has a longer history when the first
    reaches it, which is the point of sharing). Measured (48x27, 5 frames): moving
    2.2% of pixels, mean change 0.19%; still 0.85%, 0.08%."""
    pytest.importorskip("slc.methods.sh")
    for still in (True, False):
        f = _still if still else (lambda rig: rig)
        one = _images(cornell, "sh", f(views.overlap_rig(cornell, 1, 0.6)))
        two = _images(cornell, "sh", f(views.overlap_rig(cornell, 2, 0.6)))
        d = np.abs(one[0] - two[0])
        assert np.mean(d.max(axis=2) > 0) <= 0.05, still
        assert d.mean() < 0.01 * one[0].mean(), still


def test_sh_second_viewer_still_cameras_exact(cornell):
    """With still cameras the first viewer's image is bit-exact, as for slc
    (tests/test_multiview.py): the SH update's random numbers are keyed by texel
    (``FrameRequests.keys`` through ``slc.core.keys.keyed_rng``), not by the physical slot,
    which depends on which viewers allocated blocks first (measured before that
    change: 0.85% of pixels differed)."""
    pytest.importorskip("slc.methods.sh")
    one = _images(cornell, "sh", _still(views.overlap_rig(cornell, 1, 0.6)))
    two = _images(cornell, "sh", _still(views.overlap_rig(cornell, 2, 0.6)))
    assert np.array_equal(one[0], two[0])
