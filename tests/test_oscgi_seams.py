"""Island borders show no seam: on a flat floor split into several islands of the on-surface cache
(a 16 x 16 grid of quads, 512 triangles, islands of at most 128), the jump of osc-gi's image
between two neighbouring pixels on either side of an island border deviates from the reference's
jump no more than 1.5x as much as between neighbouring pixels inside one island (measured figures
and the known miss at SEAM_MISSES)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.reference import references

from slc.scene import views
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath

import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_oscgi import _run  # noqa: E402

SEAM_BOUND = 1.5     # border-pair deviation / interior-pair deviation


def grid_floor_scene(n=16, size=2.0):
    b = SceneBuilder("grid_floor")
    xs = np.linspace(-size / 2, size / 2, n + 1)
    V = np.array([[x, 0.0, z] for z in xs for x in xs])
    F = []
    for j in range(n):
        for i in range(n):
            a, b_, c, d = j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i
            F += [[a, c, b_], [a, d, c]]                       # facing +y
    b.add_mesh(V, np.array(F), bsdf=diffuse([0.7, 0.7, 0.7]), name="floor")
    b.add_quad([0.0, 0.6, -1.0], [1.0, 0, 0], [0, 0.6, 0], bsdf=diffuse([0.8, 0.3, 0.2]), name="wall")
    b.add_quad([0.3, 1.5, 0.0], [0.25, 0, 0], [0, 0, 0.25], bsdf=diffuse([0, 0, 0]), emission=[8.0] * 3,
               name="light")
    cam = CameraPath([([0.0, 2.2, 1.6], [0.0, 0.0, -0.2])], frames=4, fov=60)
    return b.build([cam], unit=1.0)


@pytest.fixture(scope="module")
def floor_scene():
    return grid_floor_scene()


# Measured ratios: osc-gi 1.01, osc-gi:filter_radius=3 1.01, osc-gi:direct=cache,filter_radius=3
# 0.90; with the filter's support truncated on one side only at island borders (symmetric=False)
# 1.38 and 3.0 (the island-local kernel then leans into the island and the borders show).
SEAM_MISSES = {}
SEAM_SPECS = ["osc-gi", "osc-gi:filter_radius=3", "osc-gi:direct=cache,filter_radius=3"]
_SEAMS = {}


def _seam_ratio(s, spec):
    """osc-gi ``spec`` on the grid floor, 16 frames, against a 256-spp full reference
    (once per pytest session): the mean deviation of the image's jump from the reference's
    between neighbouring floor pixels across an island border, over the same inside an
    island; and whether image and reference are finite."""
    if spec in _SEAMS:
        return _SEAMS[spec]
    m, gbs, imgs = _run(s, spec, views.single(s), 16)
    gb, img = gbs[0], imgs[0]
    ref = references.reference_for("full", s, gb, 0, "seams", spp=256, use_cache=False)
    valid, isl, _, _, _ = m.cache.layout.pixel_coords(gb)
    H, W = img.shape[:2]
    isl = np.asarray(dr.select(valid, isl, 0xFFFFFFFF)).reshape(H, W)
    shape = np.asarray(mi.UInt32(gb.shape_index)).reshape(H, W)
    floor = (isl != 0xFFFFFFFF) & (shape == shape[H - 1, W // 2])       # the bottom row sees the floor
    dev_b, dev_i = [], []
    for ax in (0, 1):
        a = (slice(None), slice(0, W - 1)) if ax else (slice(0, H - 1), slice(None))
        b = (slice(None), slice(1, W)) if ax else (slice(1, H), slice(None))
        both = floor[a] & floor[b]
        dev = np.abs((img[a] - img[b]) - (ref[a] - ref[b])).mean(-1)
        dev_b.append(dev[both & (isl[a] != isl[b])])
        dev_i.append(dev[both & (isl[a] == isl[b])])
    dev_b, dev_i = np.concatenate(dev_b), np.concatenate(dev_i)
    _SEAMS[spec] = dict(borders=dev_b.size, interior=dev_i.size, ratio=dev_b.mean() / dev_i.mean(),
                        finite=bool(np.isfinite(img).all() and np.isfinite(ref).all()))
    print(f"seams {spec}: {_SEAMS[spec]}")
    return _SEAMS[spec]


@pytest.mark.slow
@pytest.mark.parametrize("spec", [x for x in SEAM_SPECS if x not in SEAM_MISSES])
def test_island_borders_show_no_seam(floor_scene, spec):
    r = _seam_ratio(floor_scene, spec)
    assert r["ratio"] <= SEAM_BOUND, r


@pytest.mark.slow
@pytest.mark.parametrize("spec", SEAM_SPECS)
def test_island_borders_finite_and_misses_no_worse(floor_scene, spec):
    """The floor has borders, image and reference are finite, and a known miss
    (SEAM_MISSES) stays within 1.5x its measured ratio."""
    r = _seam_ratio(floor_scene, spec)
    assert r["borders"] >= 20 and r["interior"] >= 200 and r["finite"], r
    if spec in SEAM_MISSES:
        assert r["ratio"] <= 1.5 * SEAM_MISSES[spec], r
