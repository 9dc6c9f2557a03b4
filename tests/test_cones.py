"""Surface Light Cones: insertion cases A-D, C update/reduction, shrink geometry,
packing bounds, convergence to the ground truth, glossy FLIP vs rt16, a moving
light that stops, and the hard cases (no NaN/Inf)."""
import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import plane_under_rect_light, rect_irradiance
from slc import gbuffer
from slc.cones import packing as P
from slc.cones.method import SurfaceLightCones
from slc.cones.pixelcache import PixelSlotCache
from slc.cones.update import (ConeParams, angle_between, c_reduction, end_cycle, insert_sample, merge_cones,
                              shrink_cone, shrink_step)
from slc.groundtruth import direct_mis
from slc.methods import FrameContext, create
from slc.metrics import evaluate
from slc.pipeline import gbuffers_for
from slc.scenes import FPS, CameraPath, SceneBuilder, diffuse, rough_conductor, translate
from slc.timing import NullTimer
from slc.views import single

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
        L, C, _ = end_cycle(L, [mi.Color3f(2 * v)], C, mi.UInt32(1), mi.Float(0.0), mi.UInt32(2), p)
        assert abs(C[0] - 2 * (k + 1)) < 1e-6                      # C counts samples
        assert abs(L[0][0][0] - np.mean(vals[:k + 1])) < 1e-5      # mean over all samples
    # an 8-sample cycle weighs 8x a 1-sample cycle
    L, C, _ = end_cycle([mi.Color3f(1.0)], [mi.Color3f(8 * 3.0)], mi.Float(1.0), mi.UInt32(1), mi.Float(0.0),
                        mi.UInt32(8), p)
    assert C[0] == 9 and abs(L[0][0][0] - (1.0 + 24.0) / 9) < 1e-5
    # cap at 255 (8 bits): L <- L (1 - n/255) + S / 255
    L, C, _ = end_cycle([mi.Color3f(1.0)], [mi.Color3f(0.0)], mi.Float(255.0), mi.UInt32(1), mi.Float(0.0),
                        mi.UInt32(1), p)
    assert C[0] == 255 and abs(L[0][0][0] - 254 / 255) < 1e-6
    # a turn of 20 deg divides C by 2 before the samples are added
    _, C, red = end_cycle([mi.Color3f(1.0)], [mi.Color3f(0.0)], mi.Float(100.0), mi.UInt32(1),
                          mi.Float(math.radians(20)), mi.UInt32(1), p)
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
    assert len(words) == 9 and P.entry_bits(3) == 286 and P.bytes_per_entry(3) == 36
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


def test_max_cones_4_uses_4_texels():
    assert P.entry_bits(4) == 379 and P.words_per_entry(4) == 12 and P.bytes_per_entry(4) == 48
    D = [V([0, 0, 1], [1, 0, 0]) for _ in range(4)]
    words = P.pack(D, [mi.Float(0.1, 0.2)] * 4, [mi.Color3f(1.0)] * 4, mi.Float(5, 6), mi.UInt32(4, 3), 4)
    _, _, _, C2, n2 = P.unpack(words, 4)
    assert list(n2) == [4, 3] and list(C2) == [5, 6]


# ----------------------------------------------------------------------------- end to end

def _make(scene, **kw):
    """The ``slc`` method on the on-surface cache when it exists, else on the
    private one-entry-per-pixel cache (static camera)."""
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
        gbs = gbuffers_for(scene, viewers, f, W, H)
        d = method.render(FrameContext(f, scene.time or 0.0, 0), gbs, NullTimer())
        out = (gbs[0], d[0])
    return out


def _gt(scene, gb, spp=1024):
    return np.array(direct_mis(scene.mi_scene, gb, spp)).T.reshape(-1, 3)


@pytest.mark.parametrize("cache", ["pixel", "osc"])
def test_small_light_diffuse_plane_converges(cache):
    """A 0.2 m square light 1 m above a diffuse plane, 24 frames (8 new + 16 settled
    updates). The estimator alone (one entry per pixel) is within 2% of the ground
    truth per pixel (mean abs error / mean); on the on-surface cache the image mean is
    within 1% and the per-pixel error below 5% (nearest-texel fetch: a texel's point is
    up to a texel away from the pixel's, measured 4%)."""
    sc = plane_under_rect_light(half=0.1, radiance=20.0)
    if cache == "pixel":
        m = SurfaceLightCones(sc, cache=PixelSlotCache())
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
    assert errs["bilinear"] < errs["nearest"], errs


def test_glossy_flip_below_rt16():
    sc = plane_under_rect_light(half=0.2, radiance=10.0, bsdf=rough_conductor(0.15, "Al"), name="glossy")
    m = _make(sc)
    gb, d = _run(sc, m, 16)
    rt = create("rt16", sc)
    d_rt = rt.render(FrameContext(15, 0.0, 0), [gb], NullTimer())[0]
    gt = gbuffer.to_image(gb, gbuffer.compose(gb, direct_mis(sc.mi_scene, gb, 1024)))
    f_slc = evaluate(gt, gbuffer.to_image(gb, gbuffer.compose(gb, d)))["flip"]
    f_rt = evaluate(gt, gbuffer.to_image(gb, gbuffer.compose(gb, d_rt)))["flip"]
    assert f_slc < f_rt, (f_slc, f_rt)


def _moving_scene(stop=12):
    def T(t):
        f = min(t * FPS, stop)   # frame index (scene time t = frame / FPS)
        return translate([0.04 * f, 0.0, 0.0])
    return plane_under_rect_light(half=0.1, radiance=20.0, light_transform=T, name="moving")


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
        gbs = gbuffers_for(sc, viewers, f, W, H)
        d = m.render(FrameContext(f, sc.time, 0), gbs, NullTimer())[0]
        if f in (12, 22, 32):
            v = np.array(gbs[0].valid)
            img = np.array(d).T.reshape(-1, 3)[v]
            assert np.all(np.isfinite(img))
            gt = _gt(sc, gbs[0], 256)[v]
            errs[f] = np.abs(img - gt).mean() / gt.mean()
    assert errs[12] > errs[22] > errs[32], errs
    assert errs[22] < 0.14 and errs[32] < 0.10, errs


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


@pytest.mark.parametrize("kind", ["grazing", "point", "hemisphere", "zero", "huge", "inside"])
def test_hard_cases_finite(kind):
    sc = _hard_scene(kind)
    m = _make(sc, max_cones=2 if kind == "hemisphere" else 3)
    gb, d = _run(sc, m, 10)
    img = np.array(d)
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    v = np.array(gb.valid)
    if kind == "zero":
        assert np.all(img == 0)
    if kind in ("point", "hemisphere", "huge"):
        gt = _gt(sc, gb, 256)[v]
        out = img.T.reshape(-1, 3)[v]
        # the hemisphere-sized light is a known weak case (heavy-tailed area sampling,
        # constant merging, directions below the horizon): only a loose bound
        tol = 0.05 if kind != "hemisphere" else 0.75
        assert abs(out.mean() / gt.mean() - 1) < tol, (out.mean(), gt.mean())
