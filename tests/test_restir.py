"""Tests of ReSTIR DI (slc.methods.restir.method): convergence, temporal reuse,
disocclusion/stale samples, determinism, memory and settings."""
import numpy as np
import pytest

from helpers import independent_runs
from slc import methods
from slc.scene import scenes, views
from slc.scene.gbuffer import frame_gbuffers, to_image
from slc.reference.groundtruth import direct_mis
from slc.reference.metrics import rel_mse
from slc.methods import FrameContext, MethodError
from slc.scene.builder import SceneBuilder, diffuse, translate
from slc.core.timing import NullTimer
from slc.scene.camera import FPS, Camera, Viewer

W, H = 64, 36


@pytest.fixture(scope="module")
def cornell(scene):
    return scene("cornell")


@pytest.fixture(scope="module")
def cornell_static(cornell):
    """G-buffer of the first camera of cornell (static camera) and its
    2048-sample direct-illumination reference."""
    gbs = frame_gbuffers(cornell, views.single(cornell), 0, W, H)
    gt = to_image(gbs[0], direct_mis(cornell.mi_scene, gbs[0], 2048))
    return gbs, gt


def run_frames(method, scene, viewers, frames, width=W, height=H, gbs=None):
    """Render ``frames`` frames; returns the list of direct images of viewer 0."""
    out = []
    for f in range(frames):
        g = gbs if gbs is not None else frame_gbuffers(scene, viewers, f, width, height)
        d = method.render(FrameContext(f), g, NullTimer())
        out.append(to_image(g[0], d[0]))
    return out


@pytest.mark.slow
def test_converges_to_ground_truth(cornell, cornell_static):
    """Static scene, bias=basic and pairwise (default): the mean over pixels of the 16-frame average
    is within 3% of the 2048-spp ground truth without initial visibility
    (where basic 1/Z weights are unbiased), within 5% with RTXDI's initial
    visibility (known slight darkening: occluded initial samples keep their
    M). The frame average is also closer per pixel than a single frame."""
    gbs, gt = cornell_static
    for spec, tol in (("restir:bias=basic,visibility=0", 0.03), ("restir:bias=basic", 0.05),
                      ("restir:visibility=0", 0.03), ("restir", 0.05)):
        m = methods.create(spec, cornell, seed=3)
        imgs = run_frames(m, cornell, None, 16, gbs=gbs)
        assert all(np.isfinite(i).all() for i in imgs)
        avg = np.mean(imgs, axis=0)
        assert abs(avg.mean() / gt.mean() - 1.0) < tol, (spec, avg.mean(), gt.mean())
        err_avg = np.sqrt(np.mean((avg - gt) ** 2))
        err_one = np.sqrt(np.mean((imgs[0] - gt) ** 2))
        assert err_avg < err_one


def test_temporal_reuse_lowers_error(cornell, cornell_static):
    """Same frames, same seed: mean RMSE vs ground truth of frames 4..9 is
    lower with temporal reuse than with temporal=0."""
    gbs, gt = cornell_static

    def err(spec):
        imgs = run_frames(methods.create(spec, cornell, seed=5), cornell, None, 10, gbs=gbs)
        return np.mean([np.sqrt(np.mean((i - gt) ** 2)) for i in imgs[4:]])

    assert err("restir") < 0.9 * err("restir:temporal=0")


# ---------------------------------------------------------------- disocclusion


def _slab(b, lo, hi):
    b.add_box(lo, hi, bsdf=diffuse([0.7, 0.7, 0.7]), name="slab")


def two_rooms():
    """Two closed rooms side by side (A: x < 0, B: x > 0) separated by a wall
    at x = 0, each lit by its own ceiling light facing down. Light A faces
    the floor of room B geometrically but the wall blocks it."""
    b = SceneBuilder("two_rooms")
    _slab(b, [-2.2, -0.1, -1.2], [2.2, 0.0, 1.2])     # floor
    _slab(b, [-2.2, 2.0, -1.2], [2.2, 2.1, 1.2])      # ceiling
    _slab(b, [-0.05, 0.0, -1.2], [0.05, 2.0, 1.2])    # separating wall
    _slab(b, [-2.2, 0.0, -1.2], [-2.1, 2.0, 1.2])     # outer walls
    _slab(b, [2.1, 0.0, -1.2], [2.2, 2.0, 1.2])
    _slab(b, [-2.2, 0.0, -1.2], [2.2, 2.0, -1.1])
    _slab(b, [-2.2, 0.0, 1.1], [2.2, 2.0, 1.2])
    ida = b.add_quad([-1.0, 1.95, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]),
                     emission=[10, 10, 10], name="lightA")
    b.add_quad([1.0, 1.95, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]),
               emission=[10, 10, 10], name="lightB")
    sc = b.build([])
    idx = [i for i, e in enumerate(sc.mi_scene.emitters()) if e.get_shape().id() == ida][0]
    return sc, idx


def _stale_count(m, light_idx, valid):
    r = m.reservoirs(0)
    return int(np.count_nonzero((r["light"] == light_idx) & (r["W"] > 0) & valid))


def test_camera_cut_no_stale_samples():
    """Camera in room A for 4 frames, then cut into room B (looking back at
    the wall, so B's surfaces reproject into A's previous image). Criterion:
    after the cut no pixel holds a contributing sample (W > 0) on light A,
    which no point of room B can see; the image is finite. The same run with
    the depth/normal rejection disabled does show such stale samples, so the
    criterion can fail."""
    sc, light_a = two_rooms()
    cam_a = Camera(np.array([-1.9, 1.0, 0.0]), np.array([0.0, 0.6, 0.0]), fov=70)
    cam_b = Camera(np.array([1.9, 1.0, 0.0]), np.array([-1.0, 0.6, 0.0]), fov=70)
    cut = Viewer("cut", lambda f: cam_a if f < 4 else cam_b)
    counts = {}
    for spec in ("restir", "restir:depth=1e9,normal=-1"):
        m = methods.create(spec, sc, seed=2)
        imgs = run_frames(m, sc, [cut], 5)
        gb = frame_gbuffers(sc, [cut], 4, W, H)[0]
        valid = np.array(gb.valid)
        assert np.isfinite(imgs[-1]).all()
        counts[spec] = _stale_count(m, light_a, valid)
    assert counts["restir"] == 0
    assert counts["restir:depth=1e9,normal=-1"] > 0


def test_moving_light_no_stale_samples():
    """A light that jumps by 1 m at frame 3: afterwards every contributing
    sample on it lies on the light's current rectangle (temporal history on a
    moved light is discarded)."""
    b = SceneBuilder("jump")
    _slab(b, [-3, -0.1, -2], [3, 0, 2])
    lid = b.add_quad([0.0, 1.5, 0], [0.4, 0, 0], [0, 0, 0.4], bsdf=diffuse([0, 0, 0]), emission=[8, 8, 8],
                     name="light", transform=lambda t: translate([0.0 if t < 2.5 / FPS else 1.0, 0, 0]))
    sc = b.build([])
    idx = [i for i, e in enumerate(sc.mi_scene.emitters()) if e.get_shape().id() == lid][0]
    cam = Camera(np.array([0.0, 2.5, 3.0]), np.array([0.3, 0.0, 0.0]), fov=60)
    v = Viewer("v", lambda f: cam)
    m = methods.create("restir", sc, seed=4)
    imgs = run_frames(m, sc, [v], 4)
    assert np.isfinite(imgs[-1]).all() and imgs[-1].max() > 0
    r = m.reservoirs(0)
    on = (r["light"] == idx) & (r["W"] > 0)
    assert on.sum() > 0
    x = r["y"][on, 0]
    assert np.all((x > 1.0 - 0.4 - 1e-3) & (x < 1.0 + 0.4 + 1e-3))


# ---------------------------------------------------------------- delta and environment lights


def test_point_and_environment_lights_unbiased():
    """A point light (stored as a position) and a constant environment
    (stored as directions), no initial visibility: mean over pixels of an
    8-frame average within 3% of the 2048-spp reference."""
    b = SceneBuilder("point_env")
    _slab(b, [-3, -0.1, -3], [3, 0, 3])
    b.add_box([-0.5, 0, -0.5], [0.5, 1.0, 0.5], bsdf=diffuse([0.6, 0.5, 0.4]))
    b.add_point_light([1.0, 2.0, 1.0], [6.0, 6.0, 6.0])
    b.add_envmap(rgb=[0.3, 0.35, 0.4])
    sc = b.build([])
    cam = Camera(np.array([2.5, 2.0, 3.0]), np.array([0.0, 0.3, 0.0]), fov=60)
    v = Viewer("v", lambda f: cam)
    gbs = frame_gbuffers(sc, [v], 0, W, H)
    gt = to_image(gbs[0], direct_mis(sc.mi_scene, gbs[0], 2048))
    imgs = run_frames(methods.create("restir:visibility=0", sc, seed=1), sc, [v], 8, gbs=gbs)
    avg = np.mean(imgs, axis=0)
    assert np.isfinite(avg).all()
    assert abs(avg.mean() / gt.mean() - 1.0) < 0.03, (avg.mean(), gt.mean())


# ---------------------------------------------------------------- determinism, memory, settings


def test_identical_seeds_identical_images(cornell):
    vs = views.single(cornell)
    a = run_frames(methods.create("restir", cornell, seed=9), cornell, vs, 3)
    b = run_frames(methods.create("restir", cornell, seed=9), cornell, vs, 3)
    c = run_frames(methods.create("restir", cornell, seed=10), cornell, vs, 3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[-1], c[-1])


def test_memory_reset_and_reallocation(cornell):
    m = methods.create("restir", cornell)
    assert m.memory_bytes() == 0
    vs2 = views.independent(cornell, 2)
    run_frames(m, cornell, vs2, 2)
    mem2 = m.memory_bytes()
    # the stored reservoirs, measured from their arrays: RESERVOIR_BYTES per pixel and viewer
    from slc.methods.restir.method import RESERVOIR_BYTES
    held = 0
    for r, _ in m.state.values():
        for k in ("y", "n", "light", "W", "M"):
            a = np.array(getattr(r, k))
            held += a.nbytes
    assert held == RESERVOIR_BYTES * W * H * 2
    assert m.stats()["temporal_reuse"] > 0.2
    run_frames(m, cornell, vs2[:1], 1, width=48, height=27)   # new resolution and viewer count
    assert m.memory_bytes() * (2 * W * H) == mem2 * (48 * 27)  # scales with pixels x viewers
    assert len(m.state) == 1
    assert m.stats()["temporal_reuse"] == 0.0
    m.reset()
    assert m.memory_bytes() == 0 and not m.state


def test_settings_and_presets(cornell):
    f = methods.create("restir:preset=falcor", cornell)
    assert (f.n_local, f.n_env, f.n_bsdf) == (24, 8, 1)
    d = methods.create("restir", cornell)
    assert (d.n_local, d.n_env, d.n_bsdf, d.spatial, d.mcap, d.bias) == (8, 1, 1, 1, 20.0, "pairwise")
    c = methods.create("restir:local=16,bsdf=1,spatial=5,bias=off", cornell)
    assert (c.n_local, c.spatial, c.bias) == (16, 5, "off")
    for bad in ("restir:bias=maybe", "restir:preset=nope", "restir:foo=1"):
        with pytest.raises(MethodError):
            methods.create(bad, cornell)


def test_neighbour_count_limit(cornell):
    """Accepted neighbours are kept in a 32-bit mask between the two spatial
    passes: more than 32 neighbours is a setting error."""
    assert methods.create("restir:spatial=32,boost=32", cornell).boost == 32
    for bad in ("restir:spatial=33", "restir:boost=40"):
        with pytest.raises(MethodError):
            methods.create(bad, cornell)


@pytest.mark.fresh_process
def test_no_kernel_recompilation_after_warmup(cornell):
    """Per-frame values (seeds, camera origin) are opaque: after two
    warm-up frames with temporal history, rendering compiles no new JIT
    kernel (every launched kernel is a cache hit)."""
    import drjit as dr
    vs = views.single(cornell)
    m = methods.create("restir:spatial=5", cornell, seed=7)
    for f in range(3):
        m.render(FrameContext(f), frame_gbuffers(cornell, vs, f, W, H), NullTimer())
    gbs = frame_gbuffers(cornell, vs, 3, W, H)
    dr.sync_thread()
    dr.kernel_history()                                  # drop older entries
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        m.render(FrameContext(3), gbs, NullTimer())
        dr.sync_thread()
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [h for h in hist if h["type"] == dr.KernelType.JIT]
    assert jit, "no kernel launched"
    assert all(h["cache_hit"] for h in jit), [h.get("hash") for h in jit if not h["cache_hit"]]


# ---------------------------------------------------------------- per-pixel error, bias, spatial, presets


@pytest.fixture(scope="module")
def cornell_flat(cornell):
    """G-buffer of cornell's first camera and a 4096-sample reference, flattened (N x 3)."""
    gbs = frame_gbuffers(cornell, views.single(cornell), 0, W, H)
    gt = np.array(direct_mis(cornell.mi_scene, gbs[0], 4096), np.float64).T
    return gbs, gt, np.array(gbs[0].valid)


def _pix_err(imgs, gt, v):
    """Mean over runs of the per-pixel mean absolute error relative to the mean."""
    return float(np.mean([np.abs(i[v] - gt[v]).mean() for i in imgs]) / gt[v].mean())


@pytest.mark.slow
def test_per_pixel_error_spatial_and_falcor(cornell, cornell_flat):
    """Per-pixel error against the ground truth (one frame, no temporal reuse, 4
    seeds). Measured (64x36): 1 spatial neighbour 10.2%, 5 neighbours 7.9%, none
    11.8%; the falcor preset (24/8/1 candidates, no reuse) 9.3%; rt16 5.6%,
    rt8 8.0%. Asserted: each below 1.25x its measured figure, more spatial
    neighbours (0 -> 1 -> 5) and more candidates each lower the error by more
    than 10%."""
    gbs, gt, v = cornell_flat
    seeds = range(4)
    e = {spec: _pix_err(independent_runs(spec, cornell, gbs, seeds), gt, v) for spec in
         ("restir:temporal=0,spatial=0", "restir:temporal=0", "restir:temporal=0,spatial=5",
          "restir:preset=falcor,temporal=0,spatial=0")}
    print(e)
    assert e["restir:temporal=0,spatial=0"] < 1.25 * 0.118
    assert e["restir:temporal=0"] < 1.25 * 0.102
    assert e["restir:temporal=0,spatial=5"] < 1.25 * 0.079
    assert e["restir:preset=falcor,temporal=0,spatial=0"] < 1.25 * 0.093
    assert e["restir:temporal=0,spatial=5"] < 0.9 * e["restir:temporal=0"]
    assert e["restir:temporal=0"] < 0.9 * e["restir:temporal=0,spatial=0"]
    assert e["restir:preset=falcor,temporal=0,spatial=0"] < 0.9 * e["restir:temporal=0,spatial=0"]


def test_falcor_preset_candidates_and_check_mode(cornell, cornell_flat, monkeypatch):
    """The falcor preset runs with its 24/8/1 candidates in check mode (stage
    outputs and images finite, images >= 0) and its 16-seed average is within
    2% of the ground truth over the image (measured +0.1%)."""
    from slc.core import check
    monkeypatch.setenv(check.ENV, "1")
    gbs, gt, v = cornell_flat
    m = methods.create("restir:preset=falcor", cornell)
    assert (m.n_local, m.n_env, m.n_bsdf) == (24, 8, 1)
    from slc.run.pipeline import RunConfig, run_sequence
    run_sequence(cornell, m, views.single(cornell), RunConfig(width=W, height=H, frames=3, warmup=0,
                                                             eval_frames=[], measure_overlap=False))
    avg = independent_runs("restir:preset=falcor,temporal=0,spatial=0", cornell, gbs, range(16)).mean(axis=0)
    assert abs(avg[v].mean() / gt[v].mean() - 1) < 0.02


def _half_black_plane():
    """A plane, left half diffuse 0.5, right half black (albedo 0), one light above:
    spatial neighbours across the seam pass the depth/normal tests, but on the black
    side every sample has target 0."""
    b = SceneBuilder("half_black")
    b.add_quad([-1, 0, 0], [1, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="lit")
    b.add_quad([1, 0, 0], [1, 0, 0], [0, 0, -2], bsdf=diffuse([0.0] * 3), name="black")
    b.add_quad([0, 1.5, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]), emission=[10] * 3, name="light")
    sc = b.build([])
    cam = Camera(np.array([0.0, 2.0, 1.2]), np.array([0.0, 0.0, -0.4]), fov=70)
    return sc, Viewer("top", lambda f: cam)


def test_bias_off_darkens_next_to_zero_target_neighbours():
    """bias=off normalizes by the sum of M of all merged reservoirs (1/M); bias=basic
    counts only those whose surface has p_hat(y) > 0 (1/Z). Next to the seam of a
    half-black plane, half the neighbours have p_hat = 0 for every sample, so
    bias=off is darker there while basic stays unbiased. 16 seeds, one frame,
    8 spatial neighbours, no initial visibility. Asserted: within two pixels of
    the seam bias=off is below 0.9x the ground truth and basic
    within 5%; away from the seam (10+ pixels) both within 5%. Measured (64x36):
    near the seam bias=off 0.825, basic 1.002; away 0.997 for both."""
    sc, v = _half_black_plane()
    gbs = frame_gbuffers(sc, [v], 0, W, H)
    gt = np.array(direct_mis(sc.mi_scene, gbs[0], 4096), np.float64).T
    p = np.array(gbs[0].si.p).T
    valid = np.array(gbs[0].valid)
    px = np.array(gbs[0].footprint)                     # pixel size on the surface
    lit = valid & (p[:, 0] < 0) & (gt.max(axis=1) > 0)
    near = lit & (p[:, 0] > -2 * px)                    # within 2 pixels of the seam x = 0
    far = lit & (p[:, 0] < -10 * px)
    ratios = {}
    for bias in ("off", "basic"):
        avg = independent_runs(f"restir:temporal=0,spatial=8,visibility=0,bias={bias}", sc, gbs, range(16)).mean(axis=0)
        ratios[bias] = (avg[near].mean() / gt[near].mean(), avg[far].mean() / gt[far].mean())
    print(ratios, near.sum(), far.sum())
    assert near.sum() > 20 and far.sum() > 100
    assert ratios["off"][0] < 0.9, ratios
    assert abs(ratios["basic"][0] - 1) < 0.05, ratios
    assert abs(ratios["off"][1] - 1) < 0.05 and abs(ratios["basic"][1] - 1) < 0.05, ratios


def test_envmap_light_against_ground_truth():
    """An HDR environment map (tests/test_emitters.py's 'envmap' scene): the mean
    over pixels of a 16-seed average, one frame, no reuse, within 3% of the ground
    truth. Measured (48x27): 0.1% after the fix; before it 0.002x (Mitsuba's envmap
    eval_direction reads the texel from ds.uv, which a stored direction does not
    have; ReSTIR now evaluates stored environment directions with eval())."""
    from test_emitters import ENVMAP, _scene
    if not ENVMAP.exists():
        pytest.skip("envmap not present in ../shared")
    sc = _scene("envmap")
    gbs = frame_gbuffers(sc, views.single(sc), 0, 48, 27)
    gt = np.array(direct_mis(sc.mi_scene, gbs[0], 1024), np.float64).T
    v = np.array(gbs[0].valid)
    avg = independent_runs("restir:temporal=0,spatial=0", sc, gbs, range(16)).mean(axis=0)
    assert abs(avg[v].mean() / gt[v].mean() - 1) < 0.03, (avg[v].mean(), gt[v].mean())


# ---------------------------------------------------------------- glossy plates, lights of very different sizes

SPHERES_FRAMES = 12


@pytest.fixture(scope="module")
def spheres_static():
    """The spheres scene (four spherical lights, radii 0.03-1 m, radiances
    1-1e4, over glossy plates), its first camera held still at 96x54, and
    the 2048-sample direct-illumination reference."""
    sc = scenes.load("spheres")
    gbs = frame_gbuffers(sc, views.single(sc), 0, 96, 54)
    return sc, gbs, to_image(gbs[0], direct_mis(sc.mi_scene, gbs[0], 2048))


def spheres_rel_mse(spec, spheres_static, seed=1):
    """relMSE against the reference of the last of SPHERES_FRAMES frames."""
    sc, gbs, gt = spheres_static
    img = run_frames(methods.create(spec, sc, seed=seed), sc, None, SPHERES_FRAMES, gbs=gbs)[-1]
    assert np.isfinite(img).all()
    return rel_mse(gt, img)


def test_glossy_plates_and_small_bright_lights(spheres_static):
    """Reuse on glossy plates lit by small, very bright lights: a neighbour's
    sample that its own target rates low must not get a large weight where
    the current target is large (the 1/Z weights of bias=basic give such
    samples p_c(y) W M and leave bright blotches). restir's relMSE after
    12 frames is below 0.05 and below 0.8x rt-48's in the same run
    (measured: restir 0.022, rt-48 0.036; bias=basic 0.147, bias=off 0.146)."""
    rt = spheres_rel_mse("rt48", spheres_static)
    rs = spheres_rel_mse("restir", spheres_static)
    assert rs < 0.05, (rs, rt)
    assert rs < 0.8 * rt, (rs, rt)
