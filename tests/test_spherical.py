"""Solid-angle sampling of emissive triangles (slc.scene.spherical, EmitterSampler.sample with
``solid_angle=True``, the cone update's light samples): the sampled directions follow the
density P(e) P(t|e) / Omega_t (chi-square), small triangles fall back to area sampling bit for
bit, and the weights' mean is the rectangle's closed-form irradiance at a far lower variance
than area sampling where the light is large."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.scene import emitter_sampling, spherical
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath

from helpers import first_emitter_hit, rect_irradiance

X = [0.1, 0.0, -0.2]   # the shading point, on the plane y = 0


def _scene(half, height=2.0, far=True):
    """A square light of half-size ``half`` at ``height`` above X's plane, facing down; with
    ``far``, a second small one (30 cm, 20 m away: 1.1e-4 sr per triangle, below OMEGA_MIN,
    sampled by area)."""
    b = SceneBuilder(f"spherical_{half}_{height}_{far}")
    b.add_quad([0, -1, 0], [3, 0, 0], [0, 0, -3], bsdf=diffuse([0.5] * 3), name="floor")
    b.add_quad([0, height, 0], [half, 0, 0], [0, 0, half], emission=[1.0] * 3, name="light")
    if far:
        b.add_quad([20.0, 2.0, 0.0], [0, 0, 0.15], [0, 0.15, 0], emission=[3.0] * 3, name="far")
    return b.build([CameraPath([([0.0, 0.5, 2.0], [0.0, 0.0, 0.0])], frames=2, fov=60)]).mi_scene


def _point(n):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(*X)
    si.n = mi.Normal3f(0, 1, 0)
    si.sh_frame = mi.Frame3f(si.n)
    return si


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    """A failing chi-square test writes ``chi2_data.py`` into the working folder: a temporary one."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _triangles(scene):
    """Per emitter index: (p0, e0, e1) arrays of its triangles (float64)."""
    out = {}
    for i, e in enumerate(scene.emitters()):
        sh = e.get_shape()
        V = np.array(sh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        F = np.array(sh.faces_buffer()).reshape(-1, 3)
        out[i] = (V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return out


def _omega(p0, e0, e1):
    """Solid angle of one triangle from X (numpy, float64)."""
    a, b, c = (v / np.linalg.norm(v) for v in (p0 - X, p0 + e0 - X, p0 + e1 - X))
    return 2.0 * math.atan2(abs(np.dot(a, np.cross(b, c))), 1.0 + a @ b + b @ c + c @ a)


@pytest.mark.usefixtures("in_tmp")
def test_chi2_solid_angle_samples_follow_their_density():
    """Directions drawn with ``solid_angle=True`` from a point 2 m under a 2 m square light (two
    triangles in solid angle) follow the density stated in EmitterSampler.sample,
    P(e) (A_t / A_e) / Omega_t. (A triangle below OMEGA_MIN is too small for the test's
    tabulation: its area fallback is test_small_triangles_are_sampled_by_area_bit_for_bit.)"""
    sc = _scene(1.0, far=False)
    t = emitter_sampling.EmitterSampler(sc)
    tris = _triangles(sc)
    ems = list(sc.emitters())

    def sample_dir(u):
        ds, w, ok, _ = t.sample(_point(dr.width(u)), mi.Point2f(u), mi.Bool(True), solid_angle=True)
        return ds.d, dr.select(ok, 1.0, 0.0)

    # the expected density per emitter triangle, looked up by the hit's emitter and primitive
    table = []
    for i in sorted(t.pmf):
        p0, e0, e1 = tris[i]
        areas = 0.5 * np.linalg.norm(np.cross(e0, e1), axis=1)
        for k in range(len(p0)):
            om = _omega(p0[k], e0[k], e1[k])
            sa = spherical.OMEGA_MIN < om < spherical.OMEGA_MAX
            table.append((i, k, float(t.pmf[i] * areas[k] / areas.sum() / om if sa else -t.pmf[i] / areas.sum())))
    assert sum(v > 0 for *_, v in table) == 2 and len(table) == 2, table

    def pdf(wo):
        n = dr.width(wo)
        wo, si2, hit, em = first_emitter_hit(sc, _point(n), wo)
        cos_y = dr.abs(dr.dot(si2.n, wo))
        out = dr.zeros(mi.Float, n)
        for i, k, v in table:
            on = hit & (em == mi.EmitterPtr(ems[i])) & (si2.prim_index == k) & (dr.dot(si2.n, wo) < 0.0)
            val = v if v > 0 else -v * dr.square(si2.t) / dr.select(cos_y > 0.0, cos_y, 1.0)
            out = dr.select(on, val, out)
        return out

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample_dir, pdf_func=pdf,
                                 sample_dim=2, sample_count=300_000, res=31, ires=64, seed=5)
    assert test.run(significance_level=0.01), test.messages


def test_small_triangles_are_sampled_by_area_bit_for_bit():
    """Where every triangle's solid angle is below OMEGA_MIN (a 2 cm light 40 m away), the
    solid-angle option draws exactly the area samples."""
    b = SceneBuilder("spherical_far_only")
    b.add_quad([40.0, 5.0, 0.0], [0, 0, 0.01], [0, 0.01, 0], emission=[3.0] * 3, name="far")
    sc = b.build([CameraPath([([0.0, 0.5, 2.0], [0.0, 0.0, 0.0])], frames=2, fov=60)]).mi_scene
    t = emitter_sampling.EmitterSampler(sc)
    n = 1 << 12
    rng = mi.PCG32(n)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    a = t.sample(_point(n), u, mi.Bool(True), solid_angle=False)
    s = t.sample(_point(n), u, mi.Bool(True), solid_angle=True)
    assert np.array(a[2]).mean() > 0.9
    for x, y in ((a[0].p, s[0].p), (a[0].pdf, s[0].pdf), (a[1], s[1]), (a[2], s[2])):
        assert np.array_equal(np.array(x), np.array(y))


@pytest.mark.parametrize("half", [60.0, 1.0, 0.1])
def test_weights_give_the_rectangles_irradiance(half):
    """E[w cos] at X is the closed-form irradiance of the square (within 4 standard errors and
    0.5%); where the light is large, solid angle sampling's per-sample variance is far below
    area sampling's (120 m square 2 m up: area sampling's relative standard deviation per
    sample is about 20, solid angle's about 0.5)."""
    sc = _scene(half, far=False)
    t = emitter_sampling.EmitterSampler(sc)
    n = 1 << 20
    rng = mi.PCG32(n)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    E = rect_irradiance(np.array([X[0]]), np.array([X[2]]), -half, half, -half, half, 2.0, 1.0)[0]
    rel_std = {}
    for sa in (False, True):
        ds, w, ok, _ = t.sample(_point(n), u, mi.Bool(True), solid_angle=sa)
        est = np.array(dr.select(ok, w.x * dr.maximum(ds.d.y, 0.0), 0.0), np.float64)
        rel_std[sa] = est.std() / est.mean()
        if sa:
            se = est.std() / math.sqrt(n)
            assert abs(est.mean() - E) < max(4.0 * se, 0.005 * E), (half, est.mean(), E, se)
            assert np.isfinite(est).all()
    if half >= 1.0:
        assert rel_std[True] < 0.5 * rel_std[False], rel_std
    if half == 60.0:
        assert rel_std[True] < 0.05 * rel_std[False], rel_std
