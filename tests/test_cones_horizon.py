"""Lambertian pixels whose cones cross the horizon: the exact integral of the cosine
over the part of each cone above the horizon (``slc:horizon=clip``, the default)
against the MIS sampling it replaces (``horizon=sample``), and the layered G-buffer
of several viewers (one launch for all viewers, the per-viewer images bit for bit)."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import hard_scene, render_frames
from slc import methods
from slc.scene import scenes, views
from slc.lib.cones import packing as P
from slc.lib.cones.closedforms import lambertian
from slc.lib.cones.conestate import above_fraction, above_mean_cosine
from slc.lib.cones.shading import ConeShading


def _clipped_cap_integral(cos_d, alpha, n=400_000, seed=0):
    """Monte Carlo integral of max(cos, 0) over the cap (cos_d, alpha): the reference."""
    rng = np.random.default_rng(seed)
    u, ph = rng.random(n), 2 * math.pi * rng.random(n)
    ct = 1 - u * (1 - math.cos(alpha))
    st = np.sqrt(1 - ct * ct)
    th = math.acos(cos_d)
    z = -st * np.cos(ph) * math.sin(th) + ct * math.cos(th)
    return 2 * math.pi * (1 - math.cos(alpha)) * np.maximum(z, 0).mean()


def test_clipped_cap_formula_matches_quadrature():
    """The closed form in shade_kernel (Snyder's clipped spherical cap) against Monte
    Carlo, for narrow to wide cones above, across and just below the horizon."""
    for alpha in (0.05, 0.3, 0.8, 1.3):
        for cos_d in (0.99 * math.sin(alpha), 0.1 * math.sin(alpha), 0.0, -0.5 * math.sin(alpha)):
            sd = math.sqrt(1 - cos_d ** 2)
            x = math.cos(alpha) / math.sin(alpha)
            y = min(max(-x * cos_d / sd, -1.0), 1.0)
            sy = sd * math.sqrt(1 - y * y)
            part = (cos_d * math.acos(y) - x * sy) * math.sin(alpha) ** 2 + math.atan2(sy, x)
            ref = _clipped_cap_integral(cos_d, alpha)
            assert abs(part - ref) <= 3e-3 * ref + 1e-7, (alpha, cos_d, part, ref)


def test_above_mean_cosine_against_monte_carlo():
    """``above_mean_cosine`` (the mean cosine over the part of a cap above the horizon, which
    the cone update divides its cosine-weighted sums by) against Monte Carlo in float64: caps
    from 0.02 rad (the planar segment) to wider than a hemisphere (the complement), wholly
    above, across and wholly below the horizon (exactly 0)."""
    rng = np.random.default_rng(5)
    n = 400_000
    for alpha in (0.02, 0.035, 0.3, 1.0, 1.5, 1.65, 2.5):
        for d in (0.1, math.pi / 2 - 0.6 * alpha, math.pi / 2, math.pi / 2 + 0.6 * min(alpha, 1.0), 2.0):
            u, ph = rng.random(n), 2 * math.pi * rng.random(n)
            ct = 1 - u * (1 - math.cos(alpha))
            z = -np.sqrt(1 - ct * ct) * np.cos(ph) * math.sin(d) + ct * math.cos(d)
            ref = z[z > 0].mean() if (z > 0).any() else 0.0
            got = float(above_mean_cosine(mi.Float(math.cos(d)), mi.Float(alpha))[0])
            assert abs(got - ref) <= 5e-3 * ref + 2e-4, (alpha, d, got, ref)
    assert float(above_mean_cosine(mi.Float(math.cos(2.9)), mi.Float(0.2))[0]) == 0.0


def _above_fraction64(cos_d, alpha):
    """Omega^+ / Omega of a cap in float64 (the two-cap intersection formula)."""
    sd, sa, ca = math.sqrt(1 - cos_d ** 2), math.sin(alpha), math.cos(alpha)
    t = min(max(cos_d / sa, -1.0), 1.0)
    b = min(max(-cos_d * ca / max(sd * sa, 1e-300), -1.0), 1.0)
    return max(2 * (math.pi - math.acos(t) - ca * math.acos(b)), 0.0) / (2 * math.pi * (1 - ca))


def test_above_fraction_float32_against_float64_and_monte_carlo():
    """``above_fraction`` (the part of a cap above the horizon, float32) within 2e-4 of the
    float64 formula for caps from 0.001 rad to nearly pi at every position across the
    horizon (the planar segment below SMALL_CAP), exactly 1 and 0 wholly above and below,
    and the formula itself against Monte Carlo."""
    for alpha in (0.0011, 0.003, 0.01, 0.039, 0.041, 0.05, 0.1, 0.5, 1.0, 1.5, 1.6, 2.0, 2.5, 3.0):
        ds = np.pi / 2 + np.linspace(-1.3, 1.3, 61) * min(alpha, np.pi / 2)
        got = np.array(above_fraction(mi.Float(np.cos(ds)), mi.Float(np.full(len(ds), alpha))))
        ref = np.array([_above_fraction64(math.cos(d), alpha) for d in ds])
        assert np.abs(got - ref).max() < 2e-4, (alpha, np.abs(got - ref).max())
    got = np.array(above_fraction(mi.Float([math.cos(0.2), math.cos(2.9)]), mi.Float([0.3, 0.2])))
    assert got[0] == 1.0 and got[1] == 0.0
    rng = np.random.default_rng(3)
    n = 400_000
    for alpha, d in ((0.3, 1.6), (1.0, 1.2), (1.4, 2.2), (2.0, 0.5)):
        u, ph = rng.random(n), 2 * math.pi * rng.random(n)
        ct = 1 - u * (1 - math.cos(alpha))
        z = -np.sqrt(1 - ct * ct) * np.cos(ph) * math.sin(d) + ct * math.cos(d)
        assert abs((z > 0).mean() - _above_fraction64(math.cos(d), alpha)) < 4e-3, (alpha, d)


@pytest.mark.parametrize("front_only", [False, True])
def test_horizon_clip_equals_converged_sampling(front_only):
    """``grazing`` (a light standing on a diffuse plane's horizon): the clipped closed form
    matches the mean of four 1024-direction MIS shadings (the model's integral) to 0.5 %
    over the image and 2 % per pixel (L1), is exact where the 16-direction sampling is
    noisy, and leaves pixels whose cones clear the horizon bit for bit; with ``front_only``
    (each cone's radiance spread over its part above the horizon) as without."""
    from test_cones import _storage_after
    sc = hard_scene("grazing")
    m, gb, slot, ok, tf = _storage_after(sc)
    clip = ConeShading(3, freeze=False, front_only=front_only)
    sample = ConeShading(3, freeze=False, horizon=False, front_only=front_only)
    a = np.array(clip(m.storage, slot, ok, gb.si, tf, 16, 5))
    b = np.array(sample(m.storage, slot, ok, gb.si, tf, 16, 5))
    ref = sum(np.array(sample(m.storage, slot, ok, gb.si, tf, 1024, 1 + k)) for k in range(4)) / 4
    # which pixels have a live cone across the horizon
    D, A, L, C, n = P.unpack(P.gather_words(m.storage, slot, 3, ok), 3)
    across = np.zeros(dr.width(slot), bool)
    for i in range(3):
        d = dr.normalize(tf.to_world(D[i]))
        cd = np.array(dr.dot(gb.si.sh_frame.n, d))
        ang = np.arccos(np.clip(cd, -1, 1))
        across |= np.array(ok & (n > i)) & (ang + np.array(A[i]) >= math.pi / 2)
    lam = np.array(lambertian(gb.si.bsdf(), gb.si, ok))
    assert (across & lam).sum() > 50
    assert np.array_equal(a[:, ~across], b[:, ~across])
    assert abs(a.sum() / ref.sum() - 1) < 0.005, a.sum() / ref.sum()
    assert np.abs(a - ref).sum() / ref.sum() < 0.02
    # the sampled 16-direction estimate is noisier than the closed form
    assert np.abs(b - ref).sum() > np.abs(a - ref).sum()


@pytest.mark.slow
def test_layered_gbuffer_batch_equals_per_viewer_and_concatenation():
    """Three moving viewers: shading from the frame's layered G-buffer, from G-buffers
    concatenated in the method (no layers attached) and per viewer give the same images."""
    sc = scenes.load("atrium")
    rig = views.overlap_rig(sc, 3, 0.6)

    def run(spec, strip=False):
        m = methods.create(spec, sc, seed=3)
        if strip:
            inner = m.shade_all

            def shade_all(ctx, fr, gbs):
                for gb in gbs:
                    gb.layers = None
                return inner(ctx, fr, gbs)
            m.shade_all = shade_all
        return render_frames(sc, m, rig, frames=3, width=40, height=24, seed=3)[0]

    layered, concat, per_viewer = run("slc"), run("slc", strip=True), run("slc:batch=off")
    assert not np.array_equal(layered[0], layered[1])
    for a, b, c in zip(layered, concat, per_viewer):
        assert np.array_equal(a, b) and np.array_equal(a, c)
