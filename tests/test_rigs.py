"""Rigs produce the overlap they are named for, measured with views.measure_overlap.

The controlled rig calibrates its yaw step at views.CALIBRATION_RES on
views.CALIBRATION_FRAMES; these tests measure it again at another
resolution and on other frames, so they check that the calibration holds
beyond the images it was fitted on (and that no fan wraps around the
circle, which would measure 75% for 16 views at 0%)."""
import numpy as np
import pytest

from slc.scene import random_walks, views
from slc.scene.gbuffer import frame_gbuffers

W, H = 80, 45                  # same aspect as the calibration, other resolution
FRAMES = (30, 90)              # other frames than the calibration's (0, 60, 120)
TOLERANCE = 10.0               # percentage points


@pytest.fixture(scope="module")
def atrium(scene):
    return scene("atrium")


@pytest.mark.slow
@pytest.mark.parametrize("n", [4, 16])
@pytest.mark.parametrize("target", [0, 25, 50, 75, 100])
def test_controlled_rig_reaches_its_target(atrium, n, target):
    rig = views.overlap_rig(atrium, n, target / 100.0, aspect=W / H)
    got = np.mean([views.measure_overlap(frame_gbuffers(atrium, rig, f, W, H)) for f in FRAMES])
    assert abs(got - target) <= TOLERANCE, f"{n} viewers, target {target}%: measured {got:.1f}%"


def test_controlled_rig_never_wraps(atrium):
    """The fan spans at most 360 degrees: the first and last viewers' yaws
    differ by less than 360 - hfov, whatever the viewer count."""
    for n in (4, 16):
        rig = views.overlap_rig(atrium, n, 0.0, aspect=W / H)
        dirs = []
        for v in rig:
            f, _, _ = v.camera(0).basis()
            dirs.append(np.degrees(np.arctan2(f[2], f[0])))
        hfov = views.horizontal_fov(rig[0].camera(0).fov, W / H)
        d = np.sort(np.mod(np.array(dirs) - dirs[0], 360.0))
        gaps = np.diff(np.concatenate([d, [d[0] + 360.0]]))
        # adjacent screens at 0%: every gap between neighbouring view directions is at least one field of view
        assert gaps.min() >= hfov - 1e-6, (n, gaps.min(), hfov)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_random_rig_overlap_start_and_average(atrium, seed):
    """16 random viewers, the paper's regime: about 50% overlap at the start
    (band 40-60%) and about 20% on average over the first 4 s (band
    15-25%), measured every 0.5 s at 64x36 (measured: seed 0 48% and 20%,
    seed 1 43% and 22%; the rig before the fix: 52% and 30%)."""
    rig = random_walks.random_viewers(atrium, 16, seed=seed)
    m = [views.measure_overlap(frame_gbuffers(atrium, rig, f, 64, 36)) for f in range(0, 241, 30)]
    assert 40.0 <= m[0] <= 60.0, m
    assert 15.0 <= np.mean(m) <= 25.0, m
    assert np.mean(m[2:]) < m[0] - 20.0, "the viewers do not drift apart"


@pytest.mark.slow
def test_random_rig_keeps_clear_of_surfaces(atrium):
    """No viewer starts inside a closed mesh or within 0.3 m of a surface,
    and no step of a walk passes through a surface (checked on the keys
    with the rig's own ray query, and on the poses between keys by a
    G-buffer with no hit nearer than 0.1 m)."""
    rig = random_walks.random_viewers(atrium, 16)
    for v in rig:
        keys = v.pose.__self__._k
        o = np.array([k[0] for k in keys])
        assert random_walks._clear(atrium, o[:-1], o[1:], 0.0).all(), v.name
        assert random_walks._clear(atrium, o[:1], o[:1] + [0.0, 1e-3, 0.0], 0.3).all(), v.name
    for f in (0, 45, 150, 239):
        for v, gb in zip(rig, frame_gbuffers(atrium, rig, f, 32, 18)):
            valid = np.array(gb.valid, bool)
            p = np.array(gb.si.p, np.float64).reshape(3, -1).T[valid]
            n = np.array(gb.si.n, np.float64).reshape(3, -1).T[valid]
            d = p - np.asarray(v.camera(f).origin)
            dist = np.linalg.norm(d, axis=1)
            back = np.sum(n * d, axis=1) > 0
            assert back.mean() < 0.05, (v.name, f, back.mean())     # not inside a closed mesh
            assert dist.min() > 0.1, (v.name, f, dist.min())


def test_random_rig_paths_are_uncorrelated_and_deterministic(atrium):
    a, b = random_walks.random_viewers(atrium, 16), random_walks.random_viewers(atrium, 16)
    starts = np.array([v.camera(0).origin for v in a])
    assert np.array_equal(starts, np.array([v.camera(0).origin for v in b]))
    # different start points, at least 1 m apart
    d = np.linalg.norm(starts[:, None, :] - starts[None, :, :], axis=2) + np.eye(len(a)) * 1e9
    assert d.min() > 1.0
    # headings after 2 s point in many directions (not one shared route)
    heads = []
    for v in a:
        o0, o1 = v.camera(119).origin, v.camera(120).origin
        heads.append(np.arctan2(o1[2] - o0[2], o1[0] - o0[0]))
    hist, _ = np.histogram(np.mod(heads, 2 * np.pi), bins=4, range=(0, 2 * np.pi))
    assert (hist > 0).sum() >= 3, hist
