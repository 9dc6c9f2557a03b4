"""Session gi11: the secondary cells' direct light by resampled importance sampling
(``secondary_direct=ris``) against plain light sampling and a closed form."""
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc import scenes
from slc.cones.update import light_inputs
from slc.keys import stream_key
from slc.oscgi.secondary import _REP, _direct_kernel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from helpers import plane_under_rect_light, rect_irradiance  # noqa: E402


def _cells_direct(sc, pts, nrms, ns, ris_m, seed=0):
    """E_dir at points ``pts`` (normals ``nrms``, albedo 1) by the cells' direct kernel (unfrozen)."""
    n = len(pts)
    rep = np.zeros((n, _REP), np.float32)
    rep[:, 0:3], rep[:, 3:6], rep[:, 6:9] = pts, nrms, 1.0
    keys = mi.UInt32(np.arange(n, dtype=np.uint32) * 7919 + 13)
    L, *_ = _direct_kernel(sc, light_inputs(sc), mi.Float(rep.ravel()), keys, dr.arange(mi.UInt32, n),
                           stream_key(seed, 0, 0x05EC0001), dr.opaque(mi.UInt32, ns), float(ns), ris_m)
    return np.array(L).T * np.pi          # E_dir (L_dir = E_dir / pi before the albedo)


def test_ris_matches_the_closed_form_under_a_rect_light():
    """On a plane under a square light the irradiance has a closed form: both estimators at 512
    samples per point agree with it within 2% (mean over 64 points) and 6% per point."""
    s = plane_under_rect_light(half=0.25, height=1.0, radiance=10.0)
    sc = s.mi_scene
    g = np.linspace(-1.2, 1.2, 8)
    px, pz = [a.ravel() for a in np.meshgrid(g, g)]
    pts = np.stack([px, np.full_like(px, 1e-4), pz], 1)
    nrms = np.tile([0.0, 1.0, 0.0], (len(px), 1))
    E = rect_irradiance(px, pz, -0.25, 0.25, -0.25, 0.25, 1.0, 10.0)
    for m in (0, 8):
        Ed = _cells_direct(sc, pts, nrms, 512, m)
        assert np.isfinite(Ed).all()
        assert abs(Ed[:, 0].mean() / E.mean() - 1.0) < 0.02, (m, Ed[:, 0].mean(), E.mean())
        assert np.all(np.abs(Ed[:, 0] / E - 1.0) < 0.06), (m, np.abs(Ed[:, 0] / E - 1.0).max())


@pytest.mark.slow
def test_ris_is_unbiased_on_cornell_and_has_less_variance_than_one_plain_sample():
    """Cornell (one area light, occluders): at points on the floor, walls and ceiling, the mean
    over many RIS samples equals plain light sampling's within noise (3 standard errors of the
    difference); one RIS sample (M = 8) has no more variance than one plain sample (unshadowed
    target: the variance of the light's geometry term is removed, not visibility's)."""
    s = scenes.load("cornell")
    sc = s.mi_scene
    bb = sc.bbox()
    lo, hi = np.array(bb.min), np.array(bb.max)
    rng = np.random.default_rng(1)
    n = 48
    pts, nrms = [], []
    for axis, side in ((1, 0), (0, 0), (0, 1), (2, 0)):       # floor, left, right, back wall
        p = lo + rng.uniform(0.1, 0.9, (n // 4, 3)) * (hi - lo)
        p[:, axis] = (lo if side == 0 else hi)[axis] + (1 if side == 0 else -1) * 1e-3 * (hi - lo)[axis]
        nn = np.zeros((n // 4, 3)); nn[:, axis] = 1.0 if side == 0 else -1.0
        pts.append(p); nrms.append(nn)
    pts, nrms = np.concatenate(pts), np.concatenate(nrms)
    K = 16                                                   # independent estimates per point
    est = {m: np.stack([_cells_direct(sc, pts, nrms, 64, m, seed=k)[:, 0] for k in range(K)]) for m in (0, 8)}
    one = {m: np.stack([_cells_direct(sc, pts, nrms, 1, m, seed=100 + k)[:, 0] for k in range(64)]) for m in (0, 8)}
    a, b = est[0].mean(), est[8].mean()
    se = np.sqrt(est[0].var(0).sum() / K + est[8].var(0).sum() / K) / len(pts)
    assert a > 0.0
    assert abs(a - b) < 3.0 * se + 1e-6, (a, b, se)
    assert np.isfinite(est[8]).all() and np.isfinite(one[8]).all()
    assert one[8].var(0).mean() <= one[0].var(0).mean() * 1.05, (one[8].var(0).mean(), one[0].var(0).mean())
