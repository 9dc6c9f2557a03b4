"""Surface Light Cones: insertion cases A-D, C update/reduction, shrink geometry,
packing bounds, convergence to the ground truth, glossy FLIP vs rt16, a moving
light that stops, and the hard cases (no NaN/Inf)."""
import dataclasses
import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import plane_under_rect_light, rect_irradiance
from slc.scene import gbuffer
from slc.lib.cones import packing as P
from slc.methods.cones.method import SurfaceLightCones
from slc.methods.cones.pixelcache import PixelSlotCache
from slc.lib.cones.update import (ConeParams, angle_between, c_reduction, end_cycle, insert_sample, merge_cones,
                              shrink_cone, shrink_step)
from slc.reference.groundtruth import direct_mis
from slc.methods import FrameContext, create
from slc.reference.metrics import evaluate
from slc.scene.gbuffer import frame_gbuffers
from slc.scene.builder import SceneBuilder, diffuse, rough_conductor, translate
from slc.scene.camera import FPS, CameraPath
from slc.core.timing import NullTimer
from slc.scene.views import single

W, H = 40, 30


def sph(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


def V(*dirs):
    """mi.Vector3f with one lane (entry) per given direction."""
    a = np.array(dirs, float)
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def vec(v):
    return np.array([v.x, v.y, v.z], float).T.reshape(-1, 3)


def ang(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b)))


def state(cones, K=3):
    """One entry with cones [(dir, alpha, L)], zeros elsewhere."""
    D = [V(c[0]) for c in cones] + [V([0, 0, 1]) for _ in range(K - len(cones))]
    A = [mi.Float(c[1]) for c in cones] + [mi.Float(0.0) for _ in range(K - len(cones))]
    L = [mi.Color3f(c[2]) for c in cones] + [mi.Color3f(0.0) for _ in range(K - len(cones))]
    S = [mi.Color3f(0.0) for _ in range(K)]
    return D, A, L, S, mi.UInt32(len(cones))


def insert(cones, s, w=1.0, K=3):
    D, A, L, S, n = state(cones, K)
    return insert_sample(D, A, L, S, n, mi.Float(0.0), V(s), mi.Color3f(w), mi.Bool(True), ConeParams(max_cones=K))


# ----------------------------------------------------------------------------- insertion cases

def test_case_a_inside_accumulates():
    D, A, L, S, n, beta, case = insert([(sph(0, 0), 0.2, 1.0)], sph(5.7, 30), w=2.0)
    assert case[0] == 1 and n[0] == 1
    assert np.allclose(np.array(S[0]).ravel(), 2.0)
    assert np.allclose(vec(D[0])[0], [0, 0, 1]) and abs(A[0][0] - 0.2) < 1e-7 and beta[0] == 0


def test_case_b_new_cone_when_room():
    s = sph(30, 0)
    D, A, L, S, n, beta, case = insert([(sph(0, 0), 0.2, 1.0)], s, w=3.0)
    assert case[0] == 2 and n[0] == 2
    assert np.allclose(vec(D[1])[0], s, atol=1e-6) and A[1][0] == 0.0
    assert np.allclose(np.array(S[1]).ravel(), 3.0) and np.allclose(np.array(L[1]).ravel(), 0.0)


THREE = [(sph(0, 0), 0.1, 1.0), (sph(60, 0), 0.1, 2.0), (sph(60, 180), 0.1, 4.0)]   # pair angles 60, 60, 120 deg


def test_case_c_widen_nearest():
    s = sph(20, 0)                        # 20 deg from cone 0 < 60 deg (closest pair)
    D, A, L, S, n, beta, case = insert(THREE, s)
    assert case[0] == 3 and n[0] == 3
    th = math.radians(20)
    assert abs(A[0][0] - (0.1 + th) / 2) < 1e-5                    # alpha' = (alpha + theta) / 2
    assert abs(ang(vec(D[0])[0], sph(0, 0)) - (th - 0.1) / 2) < 1e-5  # turned by (theta - alpha)/2 towards s
    assert abs(ang(vec(D[0])[0], s) - A[0][0]) < 1e-5                # s on the new boundary
    assert abs(beta[0] - (th - 0.1) / 2) < 1e-5
    assert np.allclose(np.array(S[0]).ravel(), 1.0)


def test_case_d_merge_closest_and_new():
    s = sph(80, 90)                       # 80 deg from cone 0, 85 from 1 and 2 > 60 deg
    D, A, L, S, n, beta, case = insert(THREE, s, w=5.0)
    assert case[0] == 4 and n[0] == 3
    # cones 0 and 1 (60 deg apart, alpha 0.1) merge into slot 0: alpha = (60deg + 0.2)/2, axis at 30 deg
    assert abs(A[0][0] - (math.radians(60) + 0.2) / 2) < 1e-5
    assert ang(vec(D[0])[0], sph(30, 0)) < 1e-5
    assert np.allclose(np.array(L[0]).ravel(), 3.0)               # radiance integrals add
    assert np.allclose(vec(D[1])[0], s, atol=1e-6) and A[1][0] == 0.0
    assert np.allclose(np.array(S[1]).ravel(), 5.0) and np.allclose(np.array(L[1]).ravel(), 0.0)
    assert np.allclose(np.array(L[2]).ravel(), 4.0)               # untouched


def test_insertion_vectorized_lanes_independent():
    """Several entries in one call: each lane follows its own case."""
    K = 3
    D, A, L, S, n = state(THREE, K)
    s = V(sph(5, 0), sph(20, 0), sph(80, 90))
    D = [dr.repeat(d, 1) if False else mi.Vector3f(dr.tile(d.x, 3), dr.tile(d.y, 3), dr.tile(d.z, 3)) for d in D]
    A = [dr.tile(a, 3) for a in A]
    L = [mi.Color3f(dr.tile(l[0], 3), dr.tile(l[1], 3), dr.tile(l[2], 3)) for l in L]
    S = [dr.zeros(mi.Color3f, 3) for _ in range(K)]
    n = dr.tile(n, 3)
    out = insert_sample(D, A, L, S, n, dr.zeros(mi.Float, 3), s, mi.Color3f(1.0), mi.Bool(True), ConeParams())
    assert list(out[-1]) == [1, 3, 4]


def test_merge_coincident_and_opposite_and_full():
    # coincident axes: merged cone is the larger one
    Dm, Am, ta, tb = merge_cones(V([0, 0, 1]), mi.Float(0.1), V([0, 0, 1]), mi.Float(0.3))
    assert abs(Am[0] - 0.3) < 1e-6 and np.allclose(vec(Dm)[0], [0, 0, 1], atol=1e-6)
    # opposite axes: a cone of half-angle pi/2 + alpha, finite
    Dm, Am, ta, tb = merge_cones(V([0, 0, 1]), mi.Float(0.1), V([0, 0, -1]), mi.Float(0.1))
    assert np.all(np.isfinite(vec(Dm))) and abs(Am[0] - (math.pi + 0.2) / 2) < 1e-5
    assert abs(np.linalg.norm(vec(Dm)[0]) - 1) < 1e-5
    # all cones coincident, then a sample exactly opposite: merge (pair angle 0), no NaN
    D, A, L, S, n, beta, case = insert([(sph(0, 0), 0.0, 1.0)] * 3, [0, 0, -1])
    assert case[0] == 4
    for d in D:
        assert np.all(np.isfinite(vec(d)))
    # one cone, max_cones=1: always widened (no pairs), even for the opposite direction
    D, A, L, S, n, beta, case = insert([(sph(0, 0), 0.0, 1.0)], [0, 0, -1], K=1)
    assert case[0] == 3 and abs(A[0][0] - math.pi / 2) < 1e-5 and np.all(np.isfinite(vec(D[0])))


def test_angle_between_is_precise_for_close_directions():
    a = V([0, 0, 1])
    b = V([math.sin(1e-5), 0, math.cos(1e-5)])
    assert abs(angle_between(a, b)[0] - 1e-5) < 1e-8   # acos(dot) would give 0 or 3.4e-4
    assert abs(angle_between(a, V([0, 0, -1]))[0] - math.pi) < 1e-6


# ----------------------------------------------------------------------------- C update, shrink

def test_c_reduction_formula():
    p = ConeParams()
    C = mi.Float(100.0, 100.0, 100.0, 100.0, 2.0)
    beta = mi.Float(*[math.radians(x) for x in (10.0, 0.5, 100.0, 1.5, 30.0)])
    Cn, red = c_reduction(C, beta, p)
    assert np.allclose(np.array(Cn), [100 / 1.5, 100, 100 / 3, 100 / 1.075, 2.0], rtol=1e-5)
    assert list(red) == [True, False, True, True, False]


def test_c_update_running_mean_and_cap():
    p = ConeParams(max_cones=1)
    L = [mi.Color3f(0.0)]
    C = mi.Float(0.0)
    # cycles of 2 samples with weight sums 2v: a per-sample running mean of all samples
    vals = [4.0, 2.0, 0.0, 6.0]
    for k, v in enumerate(vals):
        L, C, _ = end_cycle(L, [mi.Color3f(2 * v)], C, mi.UInt32(1), mi.Float(0.0), mi.UInt32(2), mi.Bool(True), p)
        assert abs(C[0] - 2 * (k + 1)) < 1e-6                      # C counts samples
        assert abs(L[0][0][0] - np.mean(vals[:k + 1])) < 1e-5      # mean over all samples
    # an 8-sample cycle weighs 8x a 1-sample cycle
    L, C, _ = end_cycle([mi.Color3f(1.0)], [mi.Color3f(8 * 3.0)], mi.Float(1.0), mi.UInt32(1), mi.Float(0.0),
                        mi.UInt32(8), mi.Bool(True), p)
    assert C[0] == 9 and abs(L[0][0][0] - (1.0 + 24.0) / 9) < 1e-5
    # cap at 255 (8 bits): L <- L (1 - n/255) + S / 255
    L, C, _ = end_cycle([mi.Color3f(1.0)], [mi.Color3f(0.0)], mi.Float(255.0), mi.UInt32(1), mi.Float(0.0),
                        mi.UInt32(1), mi.Bool(False), p)
    assert C[0] == 255 and abs(L[0][0][0] - 254 / 255) < 1e-6
    # a turn of 20 deg divides C by 2 before the samples are added
    _, C, red = end_cycle([mi.Color3f(1.0)], [mi.Color3f(0.0)], mi.Float(100.0), mi.UInt32(1),
                          mi.Float(math.radians(20)), mi.UInt32(1), mi.Bool(False), p)
    assert red[0] and abs(C[0] - 51.0) < 1e-4


def test_shrink_geometry():
    D, A = V([0, 0, 1]), mi.Float(0.5)
    s = V(sph(math.degrees(0.45), 0))                 # epsilon = 10% inside the boundary
    Dn, An, delta = shrink_cone(D, A, s)
    assert abs(delta[0] - 0.05) < 1e-5 and abs(An[0] - 0.45) < 1e-5
    d = vec(Dn)[0]
    assert abs(ang(d, [0, 0, 1]) - 0.025) < 1e-5      # turned by delta / 2 ...
    assert d[0] < 0 and abs(d[1]) < 1e-7              # ... away from s (s lies at phi = 0)


def test_shrink_step_drop_keep_compact():
    p = ConeParams()
    small, big = math.radians(1.0), 0.5
    D, A, L, S, n = state([(sph(0, 0), small, 1.0), (sph(60, 0), big, 2.0), (sph(60, 180), big, 3.0)])
    tests = [V(sph(0, 0)), V(sph(60 + math.degrees(0.45), 0)), V(sph(60, 180))]
    hit = [mi.Bool(False), mi.Bool(False), mi.Bool(True)]
    tested = [mi.Bool(True)] * 3
    D, A, L, S, n, beta, dropped, shrunk = shrink_step(D, A, L, S, n, mi.Float(0.0), tests, hit, tested, p)
    assert n[0] == 2 and dropped[0] and shrunk[0]      # small cone dropped, big one shrunk, the hit kept
    assert abs(A[0][0] - 0.45) < 1e-5 and np.allclose(np.array(L[0]).ravel(), 2.0)
    assert abs(A[1][0] - big) < 1e-7 and np.allclose(np.array(L[1]).ravel(), 3.0)
    assert abs(beta[0] - 0.025) < 1e-5


# ----------------------------------------------------------------------------- packing

def test_packing_round_trip_limits():
    K = 3
    dirs = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 1e-7, 0], [-1, -1e-7, 0], sph(89.99, 200), sph(0.01, 77),
            sph(179.9, -100)]
    N = len(dirs)
    alphas = np.array([0.0, 1e-6, 1e-3, 0.01, 0.3, 1.5, 3.0, math.pi])
    rad = np.array([0.0, 1e-9, 1e-3, 0.5, 1.0, 12.3, 1e5, 1e6])
    D = [V(*[dirs[(i + k) % N] for i in range(N)]) for k in range(K)]
    A = [mi.Float(np.roll(alphas, k)) for k in range(K)]
    L = [mi.Color3f(np.roll(rad, k), np.roll(rad, k + 1), np.roll(rad, k + 2)) for k in range(K)]
    C = mi.Float([0, 1, 7, 100, 254.6, 255, 300, 17])
    cnt = mi.UInt32([0, 1, 2, 3, 3, 3, 2, 1])
    words = P.pack(D, A, L, C, cnt, K)
    # sizes measured from the packed arrays (not restated from packing.py's constants)
    assert 4 * len(words) == P.bytes_per_entry(K) == 36 and all(dr.width(w) == N for w in words)
    assert _bits_used(K) == 286                      # the paper's 286 bits, in 3 RGB32 texels
    D2, A2, L2, C2, n2 = P.unpack(words, K)
    assert list(n2) == list(cnt)
    assert np.allclose(np.array(C2), [0, 1, 7, 100, 255, 255, 255, 17])
    levels = P.alpha_levels()
    for k in range(K):
        a, b = vec(D[k]), vec(D2[k])
        for i in range(N):
            assert ang(a[i], b[i]) < 1.5e-3, (k, i, a[i], b[i])      # fp16 theta/phi, poles included
        a0, a1 = np.array(A[k]), np.array(A2[k])
        assert np.all(a1 >= a0 - 1e-7)                               # rounded up: still encloses
        for x, y in zip(a0, a1):
            q = min(i for i, lv in enumerate(levels) if lv >= x - 1e-7)
            assert abs(y - levels[q]) < 1e-6
        assert a1[list(a0).index(0.0)] == 0.0                         # point lights stay exactly 0
        l0, l1 = np.array(L[k]), np.array(L2[k])
        big = l0 >= P.RAD_MIN
        assert np.all(np.abs(l1[big] - l0[big]) <= P.RAD_REL_ERR * l0[big] * 1.0001)
        assert np.all(l1[l0 == 0] == 0)


def test_fp16_and_radiance_codes_match_reference():
    x = np.array([0.0, 1e-7, 6.1e-5, 0.333, 1.0, 2.5, math.pi, -math.pi, -0.7], np.float32)
    h = np.array(P.f32_to_f16_bits(mi.Float(x)), np.uint32)
    assert np.array_equal(h.astype(np.uint16), x.astype(np.float16).view(np.uint16))
    back = np.array(P.f16_bits_to_f32(mi.UInt32(h)))
    assert np.array_equal(back, x.astype(np.float16).astype(np.float32))
    r = np.array([1e6, 1e-20, np.inf, np.nan, -5], np.float32)
    dec = np.array(P.decode_radiance(P.encode_radiance(mi.Float(r))))
    assert abs(dec[0] / 1e6 - 1) <= P.RAD_REL_ERR and dec[1] == 0 and dec[3] == 0 and dec[4] == 0
    assert np.isfinite(dec[2])


def _bits_used(K, n=4096, seed=1):
    """Highest bit position set (+1) over the packed words of ``n`` random entries
    with every field spread over its range: the packed size in bits, measured."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(K, n, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    D = [mi.Vector3f(d[k, :, 0], d[k, :, 1], d[k, :, 2]) for k in range(K)]
    A = [mi.Float(rng.uniform(0, math.pi, n)) for _ in range(K)]
    L = [mi.Color3f(*[10.0 ** rng.uniform(-8, 9, n) for _ in range(3)]) for _ in range(K)]
    words = P.pack(D, A, L, mi.Float(rng.uniform(0, 255, n)), mi.UInt32(rng.integers(0, K + 1, n)), K)
    used = 0
    for i, w in enumerate(words):
        o = int(np.bitwise_or.reduce(np.array(w, np.uint32)))
        if o:
            used = 32 * i + o.bit_length()
    return used


def test_max_cones_4_uses_4_texels():
    assert _bits_used(4) == 379                      # 4 x 92 + 8 + 3 bits -> 4 RGB32 texels
    D = [V([0, 0, 1], [1, 0, 0]) for _ in range(4)]
    words = P.pack(D, [mi.Float(0.1, 0.2)] * 4, [mi.Color3f(1.0)] * 4, mi.Float(5, 6), mi.UInt32(4, 3), 4)
    assert 4 * len(words) == P.bytes_per_entry(4) == 48     # 32-bit words per entry, counted
    _, _, _, C2, n2 = P.unpack(words, 4)
    assert list(n2) == [4, 3] and list(C2) == [5, 6]


# ----------------------------------------------------------------------------- end to end

def _make(scene, **kw):
    """The ``slc`` method on the on-surface cache when it exists, else on the
    private one-entry-per-pixel cache (static camera). Nearest fetch unless asked:
    these tests were set for it (bilinear, the default since, needs the OSC's taps)."""
    kw.setdefault("fetch", "nearest")
    if os.environ.get("SLC_CONES_PIXEL_CACHE") != "1":
        try:
            import slc.osc  # noqa: F401
            return create("slc", scene, **kw)
        except ModuleNotFoundError:
            pass
    return SurfaceLightCones(scene, cache=PixelSlotCache(), **kw)


def _run(scene, method, frames, start=0):
    viewers = single(scene)
    out = None
    for f in range(start, start + frames):
        gbs = frame_gbuffers(scene, viewers, f, W, H)
        d = method.render(FrameContext(f), gbs, NullTimer())
        out = (gbs[0], d[0])
    return out


def _gt(scene, gb, spp=1024):
    return np.array(direct_mis(scene.mi_scene, gb, spp)).T.reshape(-1, 3)


@pytest.mark.slow
@pytest.mark.parametrize("cache", ["pixel", "osc"])
def test_small_light_diffuse_plane_converges(cache):
    """A 0.2 m square light 1 m above a diffuse plane, 24 frames (8 new + 16 settled
    updates). The estimator alone (one entry per pixel) is within 2% of the ground
    truth per pixel (mean abs error / mean); on the on-surface cache the image mean is
    within 1% and the per-pixel error below 5% (nearest-texel fetch: a texel's point is
    up to a texel away from the pixel's, measured 4%)."""
    sc = plane_under_rect_light(half=0.1, radiance=20.0)
    if cache == "pixel":
        m = SurfaceLightCones(sc, cache=PixelSlotCache(), fetch="nearest")
    else:
        pytest.importorskip("slc.osc")
        m = create("slc", sc)
    gb, d = _run(sc, m, 24)
    v = np.array(gb.valid)
    img = np.array(d).T.reshape(-1, 3)[v]
    gt = _gt(sc, gb)[v]
    assert np.all(np.isfinite(img))
    assert abs(img.mean() / gt.mean() - 1) < 0.01
    rel = np.abs(img - gt).mean() / gt.mean()
    assert rel < (0.02 if cache == "pixel" else 0.05), rel
    # and the closed form at the pixel points
    p = np.array(gb.si.p).T.reshape(-1, 3)[v]
    E = rect_irradiance(p[:, 0], p[:, 2], -0.1, 0.1, -0.1, 0.1, 1.0, 20.0)
    assert abs(img[:, 0].mean() / (0.5 / math.pi * E).mean() - 1) < 0.02


# per-pixel mean error / mean of slc:fetch=bilinear on the small-light plane against the
# closed form (measured 1.01%, image mean -0.18%; the nearest fetch: 4.1% against the ground truth)
BILINEAR_BOUND = 0.015


@pytest.mark.slow
def test_bilinear_fetch_taps_and_error():
    """Bilinear fetch on the OSC: every pixel's usable tap weights sum to 1, taps are
    entries of the pixel's own island, and on the small-light plane it is closer to
    the ground truth per pixel than the nearest-texel fetch (same frames, same
    update samples: the fetch is the only difference)."""
    pytest.importorskip("slc.osc")
    sc = plane_under_rect_light(half=0.1, radiance=20.0)
    errs = {}
    for fetch in ("nearest", "bilinear"):
        m = create("slc", sc, fetch=fetch)
        gb, d = _run(sc, m, 24)
        v = np.array(gb.valid)
        img = np.array(d).T.reshape(-1, 3)[v]
        assert np.all(np.isfinite(img))
        errs[fetch] = np.abs(img - _gt(sc, gb)[v]).mean() / _gt(sc, gb)[v].mean()
        if fetch == "bilinear":
            # absolute bound against the closed form at the pixel points (no reference noise)
            p = np.array(gb.si.p).T.reshape(-1, 3)[v]
            E = 0.5 / math.pi * rect_irradiance(p[:, 0], p[:, 2], -0.1, 0.1, -0.1, 0.1, 1.0, 20.0)
            cf = np.abs(img[:, 0] - E).mean() / E.mean()
            print("bilinear vs closed form: per-pixel", cf, "mean", img[:, 0].mean() / E.mean() - 1)
            assert cf < BILINEAR_BOUND and abs(img[:, 0].mean() / E.mean() - 1) < 0.01, cf
            taps, weights = m.cache.bilinear_taps(gb)
            total = sum(np.array(w) for w in weights)[v]
            assert np.allclose(total, 1.0, atol=1e-5)
            near = np.array(m.cache.begin_frame(24, [gb]).pixel_slot[0])[v]
            isl = m.cache.entry_info(mi.UInt32(near))["island"] if hasattr(m.cache, "entry_info") else None
            for s_j, w_j in zip(taps, weights):
                s_np, w_np = np.array(s_j)[v], np.array(w_j)[v]
                used = w_np > 0
                assert np.all(s_np[used] != 0xFFFFFFFF)
                if isl is not None:
                    isl_j = m.cache.entry_info(mi.UInt32(s_np[used]))["island"]
                    assert np.array_equal(np.array(isl_j), np.array(isl)[used])
    print("fetch per-pixel errors", errs)
    assert errs["bilinear"] < errs["nearest"], errs


@pytest.mark.slow
def test_glossy_flip_below_rt16():
    sc = plane_under_rect_light(half=0.2, radiance=10.0, bsdf=rough_conductor(0.15, "Al"), name="glossy")
    m = _make(sc)
    gb, d = _run(sc, m, 16)
    rt = create("rt16", sc)
    d_rt = rt.render(FrameContext(15), [gb], NullTimer())[0]
    gt = gbuffer.to_image(gb, gbuffer.compose(gb, direct_mis(sc.mi_scene, gb, 1024)))
    f_slc = evaluate(gt, gbuffer.to_image(gb, gbuffer.compose(gb, d)))["flip"]
    f_rt = evaluate(gt, gbuffer.to_image(gb, gbuffer.compose(gb, d_rt)))["flip"]
    assert f_slc < f_rt, (f_slc, f_rt)


def _moving_scene(stop=12):
    def T(t):
        f = min(t * FPS, stop)   # frame index (scene time t = frame / FPS)
        return translate([0.04 * f, 0.0, 0.0])
    return plane_under_rect_light(half=0.1, radiance=20.0, light_transform=T, name="moving")


@pytest.mark.slow
def test_moving_light_recovers_after_stop():
    """The light moves 4 cm (about 2.3 deg seen from below) per frame for 12 frames,
    then stops. Measured mean relative error (pixel cache, 40x30): about 0.21 right
    after the stop, 0.09 ten frames later, 0.08 twenty frames later (moving entries
    keep at most 8 cycles of memory, see ConeParams.multi_cycles). Asserted: it keeps
    falling, below 0.14 within 10 frames and below 0.10 within 20 frames."""
    sc = _moving_scene()
    m = _make(sc)
    viewers = single(sc)
    errs = {}
    for f in range(33):
        gbs = frame_gbuffers(sc, viewers, f, W, H)
        d = m.render(FrameContext(f), gbs, NullTimer())[0]
        if f in (12, 22, 32):
            v = np.array(gbs[0].valid)
            img = np.array(d).T.reshape(-1, 3)[v]
            assert np.all(np.isfinite(img))
            gt = _gt(sc, gbs[0], 256)[v]
            errs[f] = np.abs(img - gt).mean() / gt.mean()
    assert errs[12] > errs[22] > errs[32], errs
    assert errs[22] < 0.14 and errs[32] < 0.10, errs


@pytest.mark.slow
def test_half_occluded_large_light_measured():
    """DESIGN.md asks that a half-occluded large light be measured, not assumed:
    a 1 m x 1 m light 1 m above a diffuse plane, with a thin horizontal blocker
    at 0.5 m covering the half x < 0 of the light for the plane points in the
    middle. A cone stores the integral over its solid angle, but shading spreads
    it uniformly over the whole cone: where half the light is hidden, the visible
    half still gets its true integral, only its direction is smeared over the
    cone. Measured after 24 frames (40x30, on the OSC): image mean within 0.2% of
    the ground truth, mean per-pixel error 8.2% (the penumbra under the blocker's
    edge, where the cone that bounds the visible half is still shaded as a
    uniform disc). Asserted as a regression guard: mean within 1%, per-pixel
    mean error below 12%."""
    b = SceneBuilder("half_occluded")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_quad([0, 1.0, 0], [0.5, 0, 0], [0, 0, 0.5], bsdf=diffuse([0, 0, 0]), emission=[8.0] * 3, name="light")
    b.add_quad([-0.4, 0.5, 0], [0.4, 0, 0], [0, 0, -0.6], bsdf=diffuse([0.2] * 3), name="blocker")  # faces up
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=8, fov=60)
    sc = b.build([cam])
    m = _make(sc)
    gb, d = _run(sc, m, 24)
    v = np.array(gb.valid) & (np.array(gb.si.p)[1] < 1e-3)        # plane pixels only
    img = np.array(d).T.reshape(-1, 3)[v]
    gt = _gt(sc, gb)[v]
    assert np.all(np.isfinite(img))
    mean_err = abs(img.mean() / gt.mean() - 1)
    pix_err = np.abs(img - gt).mean() / gt.mean()
    print(f"half-occluded large light: mean error {mean_err:.4f}, per-pixel {pix_err:.4f}")
    assert mean_err < 0.01 and pix_err < 0.12, (mean_err, pix_err)


# ----------------------------------------------------------------------------- hard cases

def _hard_scene(kind):
    b = SceneBuilder(f"hard_{kind}")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    if kind == "grazing":      # a light standing on the horizon, facing the plane's points
        b.add_quad([0, 0.1, -1.5], [0.5, 0, 0], [0, 0.1, 0], emission=[10.0] * 3, name="light")
    elif kind == "point":
        b.add_point_light([0.2, 0.7, 0.1], [3.0] * 3)
    elif kind == "hemisphere":  # a huge light above the plane (nearly the whole hemisphere)
        b.add_quad([0, 2.0, 0], [60, 0, 0], [0, 0, 60], emission=[1.0] * 3, name="light")
    elif kind == "zero":
        b.add_quad([0, 1, 0], [0.2, 0, 0], [0, 0, 0.2], emission=[0.0] * 3, name="light")
        b.add_point_light([0, -1, 0], [1.0] * 3)        # below the plane: contributes nothing
    elif kind == "huge":
        b.add_quad([0, 1, 0], [0.05, 0, 0], [0, 0, 0.05], emission=[1e6] * 3, name="light")
    elif kind == "inside":     # a box closed around part of the plane
        b.add_box([-0.3, -0.1, -0.3], [0.3, 0.3, 0.3], bsdf=diffuse([0.5] * 3))
        b.add_quad([0, 1, 0], [0.2, 0, 0], [0, 0, 0.2], emission=[5.0] * 3, name="light")
    if kind == "grazing":
        # faces +z towards the plane points in front of it
        pass
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=8, fov=70)
    return b.build([cam])


# kind: (bound on |mean / reference - 1|, bound on the per-pixel mean error / mean).
# Measured (40x30, 10 frames, check mode, plane pixels against helpers.quadrature_direct /
# the closed form): point +0.2% / 4.8%, huge +0.1% / 4.6%, inside -0.2% / 5.7%, hemisphere
# (2 cones) 0.14% / 2.2%: its bound fails the update without cosine-weighted sums
# (test_hemisphere_bound_needs_cosine_weights).
HARD_BOUNDS = {"point": (0.01, 0.07), "huge": (0.01, 0.07), "inside": (0.02, 0.09),
               "grazing": (0.05, 0.10), "hemisphere": (0.02, 0.04)}
# Known misses: cases whose target bound is not met (docs/hard-cases.md states them); they are left
# out of test_hard_cases_finite and test_hard_case_misses_no_worse holds each to 1.5x the
# (mean error, per-pixel error) recorded here. Measured, same run as above: grazing
# 40.5% / 49.9% (the 20 pixels within 0.1 m of the light's foot hold 62% of the reference and
# get a third of it: their entries' points lie up to a texel from the pixels').
HARD_MISSES = {"grazing": (0.405, 0.499)}      # a light standing on the horizon
_HARD_ERRORS = {}


def _hard_case_errors(kind, cosine_weights=True):
    """(mean error, per-pixel error) of slc on hard case ``kind`` against its independent
    reference, rendered once per pytest session in check mode (a NaN/Inf in any stage output or a
    NaN/Inf/negative value in the returned image raises); ``zero``: the largest |value|.
    ``cosine_weights=False``: the update's sums unweighted (``ConeParams.cosine_weights``)."""
    if (kind, cosine_weights) in _HARD_ERRORS:
        return _HARD_ERRORS[kind, cosine_weights]
    from helpers import HARD_POINT, HARD_RECTS, quadrature_direct
    from slc.core import check
    sc = _hard_scene(kind)
    m = _make(sc, max_cones=2 if kind == "hemisphere" else 3)
    m.cone_params = dataclasses.replace(m.cone_params, cosine_weights=cosine_weights)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(check.ENV, "1")
        with check.scope("slc", None):
            gb, d = _run(sc, m, 10)
            check.images([d], [gb])
    img = np.array(d).T.reshape(-1, 3)
    if kind == "zero":
        _HARD_ERRORS[kind, cosine_weights] = float(np.abs(img).max())
        return _HARD_ERRORS[kind, cosine_weights]
    p = np.array(gb.si.p).T.reshape(-1, 3)
    v = np.array(gb.valid) & (np.abs(p[:, 1]) < 1e-4)
    if kind == "hemisphere":
        ref = np.repeat((0.5 / math.pi * rect_irradiance(p[:, 0], p[:, 2], -60, 60, -60, 60, 2.0, 1.0))[:, None],
                        3, axis=1)
    else:
        rects, pts = list(HARD_RECTS.get(kind, {}).values()), ([HARD_POINT] if kind == "point" else [])
        ref = quadrature_direct(sc, gb, rects, pts, n=64)
        coarse = quadrature_direct(sc, gb, rects, pts, n=32)       # converged pixels only
        v &= np.abs(ref - coarse).max(axis=1) <= 1e-3 * np.maximum(ref.max(axis=1), 1e-12)
    assert v.sum() > 300, (kind, v.sum())
    a, r = img[v], ref[v]
    e = _HARD_ERRORS[kind, cosine_weights] = (abs(a.mean() / r.mean() - 1), np.abs(a - r).mean() / r.mean())
    print(f"cones hard case {kind} (cosine weights {cosine_weights}): mean error {e[0]:.4f}, per-pixel {e[1]:.4f}")
    return e


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["point", "zero", "huge", "inside"])
def test_hard_cases_finite(kind):
    """Every hard case in check mode, and the raw image against an independent reference
    on the plane's pixels: a quadrature over the light with exact visibility (point, huge,
    inside) or the closed form (hemisphere); zero radiance gives exactly 0.
    Bounds in HARD_BOUNDS; the known misses (HARD_MISSES) in test_hard_case_misses_no_worse."""
    if kind == "zero":
        assert _hard_case_errors(kind) == 0.0
        return
    mean_err, pix_err = _hard_case_errors(kind)
    bm, bp = HARD_BOUNDS[kind]
    assert mean_err < bm and pix_err < bp, (kind, mean_err, pix_err)


def test_hemisphere_bound_needs_cosine_weights():
    """The hemisphere case's bound holds a worse update to account: with unweighted sums
    (each cone spreading over its whole cap what the samples nearest its axis brought) the
    mean error is over its bound (measured +8.7%) and 5x the weighted update's at least."""
    weighted, _ = _hard_case_errors("hemisphere")
    unweighted, _ = _hard_case_errors("hemisphere", cosine_weights=False)
    assert unweighted > HARD_BOUNDS["hemisphere"][0] and unweighted > 5 * weighted, (unweighted, weighted)


@pytest.mark.parametrize("kind", list(HARD_MISSES))
def test_hard_case_misses_no_worse(kind):
    """A known miss runs in check mode and stays within 1.5x its measured errors."""
    mean_err, pix_err = _hard_case_errors(kind)
    bm, bp = HARD_MISSES[kind]
    assert mean_err <= 1.5 * bm and pix_err <= 1.5 * bp, (kind, mean_err, pix_err)


# ----------------------------------------------------------------------------- MIS shading

def _storage_after(sc, frames=12, cache="pixel"):
    """A converged cone storage and the shading inputs of the last frame."""
    from slc.core.keys import INVALID
    m = SurfaceLightCones(sc, cache=PixelSlotCache(), fetch="nearest") if cache == "pixel" else create("slc", sc)
    gb, _ = _run(sc, m, frames)
    fr = m.cache.begin_frame(frames, [gb])
    slot = mi.UInt32(fr.pixel_slot[0])
    ok = mi.Bool(gb.valid) & (slot != INVALID)
    tf = dr.gather(mi.Frame3f, fr.si.sh_frame, fr.pixel_index[0], ok)
    return m, gb, slot, ok, tf


@pytest.mark.fresh_process
@pytest.mark.slow
@pytest.mark.parametrize("bsdf", ["conductor", "plastic"])
def test_mis_shading_unbiased_and_deterministic(bsdf):
    """The MIS estimator is unbiased for the cone model: the mean of 128 differently
    keyed 16-direction shadings matches the mean of four 1024-direction shadings (the
    model's integral) to 1 % over the image and 3 % per pixel (L1; the two estimates'
    own noise is about 1-1.6 %), for a sharp (alpha 0.01) and a rough (0.3) lobe. The
    same key gives the same image, frozen or not."""
    from slc.lib.cones.shading import ConeShading
    for alpha in (0.01, 0.3):
        b = rough_conductor(alpha, "Al") if bsdf == "conductor" else \
            {"type": "roughplastic", "distribution": "ggx", "alpha": alpha,
             "diffuse_reflectance": {"type": "rgb", "value": [0.3] * 3}}
        sc = plane_under_rect_light(half=0.3, radiance=5.0, bsdf=b, name=f"mis_{bsdf}_{alpha}")
        m, gb, slot, ok, tf = _storage_after(sc)
        unfrozen = ConeShading(3, freeze=False)
        ref = sum(np.array(unfrozen(m.storage, slot, ok, gb.si, tf, 1024, 1 + k)) for k in range(4)) / 4
        frozen = ConeShading(3)
        mean = sum(np.array(frozen(m.storage, slot, ok, gb.si, tf, 16, 17 + 31 * k)) for k in range(128)) / 128
        assert np.all(np.isfinite(mean))
        assert abs(mean.sum() / ref.sum() - 1) < 0.01, (alpha, mean.sum() / ref.sum())
        err = np.abs(mean - ref).sum() / ref.sum()
        assert err < 0.03, (alpha, err)
        a = np.array(frozen(m.storage, slot, ok, gb.si, tf, 16, 5))
        assert np.array_equal(a, np.array(frozen(m.storage, slot, ok, gb.si, tf, 16, 5)))
        assert np.array_equal(a, np.array(unfrozen(m.storage, slot, ok, gb.si, tf, 16, 5)))
        assert frozen.n_recordings == 1


def _moving_camera_plane():
    """Static scene, camera sliding sideways: the OSC allocates new blocks (storage grows)."""
    b = SceneBuilder("sliding")
    b.add_quad([0, 0, 0], [3, 0, 0], [0, 0, -3], bsdf=rough_conductor(0.1, "Al"), name="plane")
    b.add_quad([0, 1.0, 0], [0.2, 0, 0], [0, 0, 0.2], bsdf=diffuse([0, 0, 0]), emission=[10.0] * 3, name="light")
    cam = CameraPath([([-1.5, 0.6, 1.0], [-1.5, 0.0, 0.0]), ([1.5, 0.6, 1.0], [1.5, 0.0, 0.0])], frames=8, fov=50)
    return b.build([cam])


@pytest.mark.fresh_process
@pytest.mark.slow
def test_shading_freeze_recordings_bounded():
    """Over a sequence that mimics one single-viewer experiment process
    (several scenes, static and animated, three settings each, a camera that makes the
    storage grow), every method instance's shading is recorded at most twice, in the
    animated scene (a light moved every frame) as in the static ones, also with 4 viewers.
    Images stay finite."""
    pytest.importorskip("slc.osc")
    scenes = [("static-growing", _moving_camera_plane()), ("animated", _moving_scene()),
              ("static", plane_under_rect_light(half=0.1, radiance=20.0, bsdf=rough_conductor(0.05, "Al")))]
    for name, sc in scenes:
        for spec in ("slc", "slc:fetch=bilinear", "slc:shade_samples=8"):
            kw = {}
            if name == "static-growing":     # a pool of 2 blocks: full at once, doubled as the camera moves
                from slc.osc import OnSurfaceCache
                kw["cache"] = OnSurfaceCache(sc, max_blocks=2)
            m = create(spec, sc, **kw)
            widths = []
            for f in range(8):
                gbs = frame_gbuffers(sc, single(sc), f, W, H)
                d = m.render(FrameContext(f), gbs, NullTimer())
                widths.append(dr.width(m.storage))
                assert np.all(np.isfinite(np.array(d[0])))
            sh = m._cone_shading
            assert sh.frozen and 1 <= sh.n_recordings <= 2, (name, spec, sh.n_recordings)
            if name == "static-growing":
                assert widths[-1] > widths[0], widths
    sc = _moving_scene()
    m = create("slc", sc)
    for f in range(6):
        d = m.render(FrameContext(f), frame_gbuffers(sc, single(sc) * 4, f, W, H), NullTimer())
        assert all(np.all(np.isfinite(np.array(x))) for x in d)
    sh = m._cone_shading
    assert sh.frozen and 1 <= sh.n_recordings <= 2, (sh.n_recordings, sh.frozen)


@pytest.mark.slow
@pytest.mark.fresh_process
@pytest.mark.parametrize("n_viewers", [1, 4])
def test_shading_compiles_nothing_after_warmup(n_viewers):
    """After 3 warm-up frames, the shading stage builds no kernel (nor loads one from
    the disk cache) for 1 and 4 viewers: the frozen replay and the kernels around it are
    all in-memory cache hits."""
    from contextlib import contextmanager
    from slc.core.timing import StageTimer
    sc = plane_under_rect_light(half=0.1, radiance=20.0, bsdf=rough_conductor(0.05, "Al"), name="nocompile")
    m = _make(sc)
    missed = []

    class T(StageTimer):
        @contextmanager
        def stage(self, name):
            if name == "shade":
                dr.kernel_history()
            with super().stage(name) as st:
                yield st
            if name == "shade":
                self.hist = dr.kernel_history()

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        viewers = single(sc) * n_viewers
        for f in range(6):
            t = T()
            t.begin_frame()
            m.render(FrameContext(f), frame_gbuffers(sc, viewers, f, W, H), t)
            t.end_frame()
            if f >= 3:
                missed += [k for k in t.hist if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", False)]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert not missed, [(k.get("hash"), k.get("cache_disk")) for k in missed]


# Cases that miss relMSE(slc) <= relMSE(rt48): the ratio measured (this test, 40x30, 48 frames,
# OSC, llvm); test_glossy_plane_no_fireflies holds each to 1.5x. The cache (cone model of a
# square light, texel vs pixel point, young L_c noise), not the shading, sets these figures: with
# the cones' model integrated exactly (256 directions per cone) they stay of the same order.
GLOSSY_MISSES = {
    ("conductor", 0.005, "small"): 87.2, ("conductor", 0.01, "small"): 26.3,
    ("conductor", 0.05, "small"): 4.51, ("conductor", 0.2, "small"): 7.38,
    ("plastic", 0.005, "small"): 47.4, ("plastic", 0.01, "small"): 22.8,
    ("plastic", 0.05, "small"): 4.36, ("plastic", 0.2, "small"): 17.2,
    # the cosine-weighted update sums make a cone's irradiance exact and its density over a cap
    # larger than its light brighter by the light's mean cosine over the cap's: 0.97 unweighted
    ("conductor", 0.05, "large"): 1.033,
}   # the other large-light cases pass: measured 0.30 / 0.56 / 0.76 (conductor), 0.13 / 0.20 / 0.61 / 0.35 (plastic)


def _glossy_bsdf(kind, alpha):
    if kind == "conductor":
        return rough_conductor(alpha, "Al")
    return {"type": "roughplastic", "distribution": "ggx", "alpha": alpha,
            "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}}


GLOSSY_FRAMES = 48


_GLOSSY = {}


def _glossy_case(kind, alpha, light):
    """slc and rt48 on a conductor / plastic plane of GGX roughness alpha under a small
    (0.2 m square, 1 m above) or a large (2 m square) light, still camera, 48 frames on the
    on-surface cache, rendered once per pytest session: whether slc's image is finite, its
    fireflies (pixels above 10x the ground truth where the ground truth is smooth: 3x3
    neighbourhood within a factor 2) and the relMSE of both against the 2048-sample
    ground truth."""
    case = (kind, alpha, light)
    if case in _GLOSSY:
        return _GLOSSY[case]
    from scipy.ndimage import maximum_filter, minimum_filter
    from slc.reference.groundtruth import ground_truth
    from slc.reference.metrics import rel_mse
    half, radiance = (0.1, 20.0) if light == "small" else (1.0, 1.0)
    sc = plane_under_rect_light(half=half, radiance=radiance, bsdf=_glossy_bsdf(kind, alpha),
                                name=f"glossy_{kind}_{alpha}_{light}")
    m = _make(sc)
    gb, d = _run(sc, m, GLOSSY_FRAMES)
    img = gbuffer.to_image(gb, gbuffer.compose(gb, d))
    gt = ground_truth(sc, gb, GLOSSY_FRAMES - 1)
    d_rt = create("rt48", sc).render(FrameContext(GLOSSY_FRAMES - 1), [gb], NullTimer())[0]
    img_rt = gbuffer.to_image(gb, gbuffer.compose(gb, d_rt))
    g = gt.mean(-1)
    smooth = (maximum_filter(g, 3) <= 2.0 * minimum_filter(g, 3)) & (g > 1e-3)
    r = dict(finite=bool(np.all(np.isfinite(img))), fireflies=int(((img.mean(-1) > 10.0 * g) & smooth).sum()),
             slc=rel_mse(gt, img), rt48=rel_mse(gt, img_rt))
    print(f"glossy {kind} alpha={alpha} {light}: relMSE slc {r['slc']:.4g} rt48 {r['rt48']:.4g} "
          f"ratio {r['slc'] / r['rt48']:.3f} fireflies {r['fireflies']}")
    _GLOSSY[case] = r
    return r


GLOSSY_CASES = [(k, a, li) for k in ("conductor", "plastic") for a in (0.005, 0.01, 0.05, 0.2)
                for li in ("small", "large")]


@pytest.mark.slow
@pytest.mark.parametrize("kind,alpha,light", [c for c in GLOSSY_CASES if c not in GLOSSY_MISSES])
def test_glossy_plane_relmse_vs_rt48(kind, alpha, light):
    """relMSE(slc) <= relMSE(rt48) against the 2048-sample ground truth
    (_glossy_case), on the cases that meet it. The cases that miss (GLOSSY_MISSES, with the
    measured ratio, held to 1.5x it by test_glossy_plane_no_fireflies) are left out: the cones' piecewise-uniform model of a small square light, not the
    shading's sampling, is what a near-mirror lobe resolves there."""
    r = _glossy_case(kind, alpha, light)
    assert r["slc"] <= r["rt48"], (r, r["slc"] / r["rt48"])


@pytest.mark.slow
@pytest.mark.parametrize("kind,alpha,light", GLOSSY_CASES)
def test_glossy_plane_no_fireflies(kind, alpha, light):
    """Every glossy case (_glossy_case): slc's image is finite with no firefly, and a
    known miss (GLOSSY_MISSES) stays within 1.5x its measured relMSE ratio to rt48."""
    r = _glossy_case(kind, alpha, light)
    assert r["finite"] and r["fireflies"] == 0, r
    if (kind, alpha, light) in GLOSSY_MISSES:
        assert r["slc"] / r["rt48"] <= 1.5 * GLOSSY_MISSES[kind, alpha, light], (r, r["slc"] / r["rt48"])


@pytest.mark.slow
def test_stratified_update_samples_lower_error():
    """Update samples from a per-entry R2 sequence that counts on across cycles
    (``samples=r2``, the default) against independent random numbers per cycle
    (``samples=random``): a 0.4 m light 1 m above a diffuse plane, one entry per
    pixel, 6 frames of the default schedule (48 samples per entry). Both are
    unbiased (image mean within 1 % of the ground truth); the stratified one
    has the lower per-pixel error (measured mean abs error / mean 0.65 % against
    0.89 %, with the light's triangles sampled in solid angle; by area it was
    1.11 % against 2.15 %)."""
    sc = plane_under_rect_light(half=0.2, radiance=20.0)
    errs = {}
    for mode in ("random", "r2"):
        m = SurfaceLightCones(sc, cache=PixelSlotCache(), samples=mode)
        gb, d = _run(sc, m, 6)
        v = np.array(gb.valid)
        img = np.array(d).T.reshape(-1, 3)[v]
        gt = _gt(sc, gb, 2048)[v]
        assert abs(img.mean() / gt.mean() - 1) < 0.01, mode
        errs[mode] = np.abs(img - gt).mean() / gt.mean()
    assert errs["r2"] < 0.8 * errs["random"] and errs["r2"] < 0.0075, errs


def _switch_off_scene(off):
    """Two lights over a diffuse plane; the larger one (0.6 m, about 30 deg seen from
    the plane) leaves at frame ``off`` (it jumps 50 m below the plane: switched off)."""
    b = SceneBuilder("switch_off")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_quad([-0.6, 1, 0], [0.15, 0, 0], [0, 0, 0.15], bsdf=diffuse([0] * 3), emission=[10] * 3, name="stays")

    def T(t):
        return translate([0.0, -50.0 if t * FPS >= off - 0.5 else 0.0, 0.0])
    b.add_quad([0.6, 1, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0] * 3), emission=[10] * 3, name="goes",
               transform=T)
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=64, fov=60)
    return b.build([cam, cam, cam])


@pytest.mark.slow
def test_light_that_switches_off_fades():
    """Hard case "a light that switches off": after 24 frames (settled entries, C
    about 80) the larger of two lights leaves. Its cones are wider than 2 degrees,
    so the paper's rim test only shrinks them by epsilon alpha per miss and keeps
    their L_c and C: the stale light fades as (1 - 1/C) per frame (measured mean
    relative error 3.4-3.8 at the switch, 2.7-3.2 eight frames later). With the
    axis test (``gone_test=axis``, an option: it costs FLIP on street, docs/cones.md)
    a cone that got no sample and whose rim and axis both miss divides C by 3 and
    puts the entry in the moving state: measured 0.07 eight frames after the
    switch, and 0.04-0.05 before it in both settings."""
    off = 24
    sc = _switch_off_scene(off)
    errs = {}
    for mode in ("axis", "off"):
        m = SurfaceLightCones(sc, cache=PixelSlotCache(), gone_test=mode)
        for f in range(off + 9):
            gbs = frame_gbuffers(sc, single(sc), f, W, H)
            d = m.render(FrameContext(f), gbs, NullTimer())[0]
            if f in (off - 1, off + 8):
                v = np.array(gbs[0].valid)
                img = np.array(d).T.reshape(-1, 3)[v]
                assert np.all(np.isfinite(img))
                gt = _gt(sc, gbs[0], 256)[v]
                errs[mode, f - off] = np.abs(img - gt).mean() / gt.mean()
    assert errs["axis", -1] < 0.08 and errs["off", -1] < 0.08, errs
    assert errs["axis", 8] < 0.15, errs            # measured 0.07
    assert errs["off", 8] > 1.0, errs              # measured 2.7: the stale cone the axis test removes


@pytest.mark.slow
def test_stochastic_fetch_mean_and_determinism():
    """``fetch=stochastic`` shades one bilinear tap per pixel, drawn with its weight
    as probability: the image mean stays within 1 % of the closed form, the image is
    the same for the same seed and frame, and averaged over frames of a still camera
    it approaches the bilinear fetch's (per-pixel error of the 8-frame mean below the
    nearest fetch's single frame)."""
    pytest.importorskip("slc.osc")
    sc = plane_under_rect_light(half=0.1, radiance=20.0)
    imgs = {}
    for run in ("a", "b"):
        m = create("slc", sc, fetch="stochastic")
        acc = []
        for f in range(24):
            gbs = frame_gbuffers(sc, single(sc), f, W, H)
            d = m.render(FrameContext(f), gbs, NullTimer())[0]
            if f >= 16:
                acc.append(np.array(d).T.reshape(-1, 3))
        imgs[run] = acc
    assert all(np.array_equal(a, b) for a, b in zip(imgs["a"], imgs["b"]))
    v = np.array(gbs[0].valid)
    p = np.array(gbs[0].si.p).T.reshape(-1, 3)[v]
    E = 0.5 / math.pi * rect_irradiance(p[:, 0], p[:, 2], -0.1, 0.1, -0.1, 0.1, 1.0, 20.0)
    last = imgs["a"][-1][v][:, 0]
    assert np.all(np.isfinite(last)) and abs(last.mean() / E.mean() - 1) < 0.01
    mean8 = np.mean([a[v][:, 0] for a in imgs["a"]], axis=0)
    m = create("slc", sc, fetch="nearest")
    gb, d = _run(sc, m, 24)
    near = np.array(d).T.reshape(-1, 3)[v][:, 0]
    assert np.abs(mean8 - E).mean() < np.abs(near - E).mean()
