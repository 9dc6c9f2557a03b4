"""Where an entry's cache rays start: from the entry's own point (the texel centre on its own
triangle), so that no ray starts behind geometry on a folded floor (one island, two planes)."""
import math

import numpy as np
import pytest

from slc import methods

from slc.scene import views
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath

import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent))
from helpers import render_frames  # noqa: E402


def folded_floor(angle_deg=20.0):
    """One mesh: a flat half (x in [-1, 0], y = 0) and a ramp rising at ``angle_deg`` (x in [0, 1]),
    both facing up (a valley, one island: normals within the island's 30-degree cone), under a
    square light."""
    t = math.tan(math.radians(angle_deg))
    V = np.array([[-1, 0, -1], [0, 0, -1], [0, 0, 1], [-1, 0, 1], [1, t, -1], [1, t, 1]], float)
    F = np.array([[0, 2, 1], [0, 3, 2], [1, 2, 5], [1, 5, 4]])
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    F = np.where((n[:, 1] < 0)[:, None], F[:, [0, 2, 1]], F)          # every face up
    b = SceneBuilder("folded_floor")
    b.add_mesh(V, F, bsdf=diffuse([0.6] * 3), name="floor")
    b.add_quad([0, 2.0, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]), emission=[10.0] * 3, name="light")
    cam = CameraPath([([0.0, 1.6, 2.2], [0.0, 0.1, 0.0])], frames=16, fov=60)
    return b.build([cam, cam, cam])


@pytest.fixture(scope="module")
def scene():
    return folded_floor()


def _backfaces(scene):
    m = methods.create("osc-gi:output=indirect", scene, seed=0)
    m.probe_origins = True
    img, _ = render_frames(scene, m, views.single(scene), 3, 32, 18)
    assert np.isfinite(img[0]).all()
    return m.origin_probe


def test_texel_origins_start_no_ray_behind_the_surface(scene):
    """Every cache ray's first hit is a front face (a ray starting below the ramp or the flat
    half, as from one plane standing for the island, meets the surface from behind)."""
    b_t, n_t = _backfaces(scene)
    assert n_t > 100
    assert b_t == 0, (b_t, n_t)
