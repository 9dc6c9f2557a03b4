"""Polygon lights (slc.lib.lights.polygon_lights): Lambert's formula with horizon
clipping against a quadrature of the irradiance over the emitter's triangles, for a
rectangle and a cube light (twelve triangles), from points that see them whole, cut by the
horizon, from behind and from the side."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.lib.lights.polygon_lights import MAX_TRIANGLES, PolygonLights
from slc.scene import emitter_sampling
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath

# (point, normal): under the rectangle, all of it above the horizon; just under it with the normal
# tilted so that the horizon cuts it (twice, other ways); facing the cube; next to the cube, the
# horizon through it; above the rectangle (behind its emitting side: 0)
POINTS = [([0.1, 0.0, 0.05], [0, 1, 0]), ([0.0, 0.9, 0.0], [0.8, 0.6, 0]), ([0.3, 0.95, 0.1], [-0.3, 0.3, 0.9]),
          ([1.5, 0.4, 0.2], [1, 0, 0]), ([1.9, 0.4, 0.2], [0.6, 0.8, 0]), ([0.0, 1.5, 0.0], [0, -1, 0])]


@pytest.fixture(scope="module")
def lights():
    b = SceneBuilder("polygon_lights")
    b.add_quad([0, 1.0, 0], [0.5, 0, 0], [0, 0, 0.3], emission=[2.0, 1.0, 0.5], name="rect")   # faces down
    b.add_box([2.0, 0.2, 0.0], [2.4, 0.6, 0.4], bsdf=diffuse([0.0] * 3), emission=[1.0] * 3)
    b.add_sphere([0.0, 3.0, 0.0], 0.2, subdivisions=2, emission=[1.0] * 3)   # 320 triangles: not listed
    sc = b.build([CameraPath([([0.0, 0.5, 2.0], [0.0, 0.0, 0.0])], frames=2, fov=60)]).mi_scene
    t = emitter_sampling.EmitterSampler(sc)
    return sc, t, PolygonLights(t)


def _quadrature(shape, p, n, L, k=200):
    """E at p (normal n): midpoint rule over each triangle's k(k+1)/2 sub-triangles, float64,
    cosines clamped at 0 on both sides (one-sided emitter, the receiver's horizon)."""
    V = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    F = np.array(shape.faces_buffer()).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    up = i + j < k
    bu, bv = (i[up] + 1 / 3) / k, (j[up] + 1 / 3) / k
    dn = i + j < k - 1
    bu2, bv2 = (i[dn] + 2 / 3) / k, (j[dn] + 2 / 3) / k
    bu, bv = np.concatenate([bu, bu2]), np.concatenate([bv, bv2])
    E = 0.0
    for f in F:
        a, e0, e1 = V[f[0]], V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]
        A = 0.5 * np.linalg.norm(np.cross(e0, e1))
        ny = np.cross(e0, e1) / (2 * A)
        y = a + bu[:, None] * e0 + bv[:, None] * e1
        w = y - p
        d2 = (w * w).sum(1)
        d = w / np.sqrt(d2)[:, None]
        E += (np.maximum(d @ n, 0) * np.maximum(-(d @ ny), 0) / d2).sum() * A / len(bu)
    return L * E


def test_flags_list_rectangles_and_small_meshes(lights):
    sc, t, pl = lights
    faces = [e.get_shape().face_count() for e in sc.emitters()]
    assert list(pl.flag) == [f <= MAX_TRIANGLES for f in faces] and faces[:2] == [2, 12], (pl.flag, faces)


@pytest.mark.parametrize("k", range(len(POINTS)))
def test_lambert_formula_matches_quadrature(lights, k):
    """E cos(n, d) of PolygonLights.light equals the quadrature within 0.3% (and both are 0
    behind the rectangle)."""
    sc, t, pl = lights
    P, N = POINTS[k]
    n = np.array(N, float) / np.linalg.norm(N)
    for em, e in enumerate(list(sc.emitters())[:2]):
        L = float(np.array(mi.traverse(e)["radiance.value"]).ravel()[0])
        is_p, d, E = pl.light(t, mi.Point3f(*P), mi.Vector3f(*[float(x) for x in n]), mi.UInt32(em), mi.Bool(True))
        got = float(np.array(E.x)[0]) * max(float(np.array(d).ravel() @ n), 0.0)
        ref = _quadrature(e.get_shape(), np.array(P, float), n, L)
        assert bool(np.array(is_p)[0])
        assert abs(got - ref) <= 3e-3 * max(ref, 1e-3), (k, em, got, ref)
        assert np.isfinite(np.array(d)).all()


def test_not_listed_emitter_gives_nothing(lights):
    sc, t, pl = lights
    is_p, d, E = pl.light(t, mi.Point3f(0.1, 0.0, 0.05), mi.Vector3f(0, 1, 0), mi.UInt32(2), mi.Bool(True))
    assert not bool(np.array(is_p)[0]) and float(np.array(E.x)[0]) == 0.0
