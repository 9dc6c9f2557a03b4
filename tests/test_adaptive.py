"""The adaptive cache (slc/adaptive): the choice of representation per entry
and its accuracy against ground truth and closed forms, switching, the pool
allocator and the header packing. Small images (32x32) on planes."""
import math

import mitsuba as mi
import numpy as np
import pytest

from slc.scene import emitter_sampling

from slc import methods
from slc.methods.adaptive import choice as ch
from slc.methods.adaptive import sh_rep
from slc.methods.adaptive.lanes import tally
from slc.methods.adaptive.pool import Pool
from slc.reference.groundtruth import ground_truth
from slc.core.keys import INVALID
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath, Viewer

from helpers import plane_under_rect_light, rect_irradiance, render_frames

W = H = 32


def _still(scene):
    cam = scene.path(0).at(0)
    return Viewer("v0", lambda f: cam)


def _plane(name, light):
    b = SceneBuilder(name)
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    light(b)
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=64, fov=60)
    return b.build([cam, cam, cam])


def _valid(gb):
    return np.array(gb.valid).reshape(H, W)


def test_point_light_chooses_visibility_and_matches_ground_truth():
    """Started as cones (not the scene's prior), the entries' delta-light share
    is 1, so they switch to VISIBILITY; the shading is then exact up to the
    8-bit visibility (1 here: the plane is unoccluded)."""
    scene = _plane("adaptive_point", lambda b: b.add_point_light([0.2, 1.0, 0.1], [3.0] * 3))
    m = methods.create("adaptive:start=cones", scene, seed=1)
    imgs, gbs = render_frames(scene, m, [_still(scene)], 12, W, H)
    st = m.stats()
    assert st["share_visibility"] == 1.0 and st["records_cones"] == 0, st
    gt = ground_truth(scene, gbs[0], 11, "v0", spp=64, use_cache=False)   # a point light: exact per sample
    ok = _valid(gbs[0])
    err = np.abs(imgs[0][ok] - gt[ok]).mean() / gt[ok].mean()
    assert err < 0.01, err                                   # measured 4e-6


@pytest.mark.parametrize("early,share", [(4, 1.0), (0, 0.0)])
def test_early_frames_switch_in_every_frame(early, share):
    """In the cache's first ``switch_early`` frames every frame is a switch frame: entries started
    as cones under a point light reach VISIBILITY in frame 2 (their third update asking for it),
    not in the next ``switch_period``-th frame (4); without early frames none has switched after
    frames 0-3 (frame 0 is a switch frame, but its entries have one update of statistics)."""
    scene = _plane("adaptive_early", lambda b: b.add_point_light([0.2, 1.0, 0.1], [3.0] * 3))
    m = methods.create(f"adaptive:start=cones,switch_early={early}", scene, seed=1)
    render_frames(scene, m, [_still(scene)], 4, W, H)
    assert m.stats()["share_visibility"] == share, m.stats()


def test_large_area_light_chooses_cones():
    """Without polygon lights, the choice rule's statistics move a large square light's entries
    from SH to cones."""
    scene = plane_under_rect_light(half=1.0, height=1.0, radiance=2.0, name="adaptive_area")
    m = methods.create("adaptive:start=sh,polygon_lights=off", scene, seed=1)   # the statistics move it to cones
    imgs, gbs = render_frames(scene, m, [_still(scene)], 24, W, H)
    st = m.stats()
    assert st["share_cones"] > 0.9, st
    # and the cones converge to the closed-form irradiance (mean over the image)
    p = np.array(gbs[0].si.p).T
    ok = np.array(gbs[0].valid)
    E = rect_irradiance(p[ok, 0], p[ok, 2], -1.0, 1.0, -1.0, 1.0, 1.0, 2.0)
    Lo = imgs[0].reshape(-1, 3)[ok, 0]
    assert abs(Lo.mean() - (0.5 / math.pi * E).mean()) / (0.5 / math.pi * E).mean() < 0.03


def test_constant_environment_chooses_sh_and_matches_closed_form():
    """A constant sky of radiance L over an open diffuse plane, SH a candidate
    (``sh_when=environment``; by default it is not) and the sky not listed
    (``env_lights=off``): L_o = rho L."""
    L = np.array([0.8, 0.85, 1.0])
    scene = _plane("adaptive_env", lambda b: b.add_envmap(rgb=list(L)))
    m = methods.create("adaptive:start=cones,sh_when=environment,env_lights=off", scene, seed=1)
    imgs, gbs = render_frames(scene, m, [_still(scene)], 64, W, H)
    st = m.stats()
    assert st["share_sh"] > 0.9, st
    ok = _valid(gbs[0])
    mean = imgs[0][ok].mean(axis=0)
    rel = np.abs(mean - 0.5 * L) / (0.5 * L)
    assert rel.max() < 0.02, rel


@pytest.mark.slow
def test_constant_environment_lists_the_sky_exactly():
    """The same sky by default: every entry lists the sky (VISIBILITY, its irradiance pi L in
    closed form, visible fraction 1 over the open plane), so L_o = rho L per pixel with no noise
    (measured: the largest per-pixel error 4e-6 relative)."""
    L = np.array([0.8, 0.85, 1.0])
    scene = _plane("adaptive_env_sky", lambda b: b.add_envmap(rgb=list(L)))
    m = methods.create("adaptive", scene, seed=1)
    imgs, gbs = render_frames(scene, m, [_still(scene)], 12, W, H)
    assert m.stats()["share_visibility"] == 1.0, m.stats()
    ok = _valid(gbs[0])
    rel = np.abs(imgs[0][ok] - 0.5 * L) / (0.5 * L)
    assert rel.max() < 1e-4, rel.max()


@pytest.mark.slow
@pytest.mark.fresh_process
def test_frozen_sh_shading_matches_unfrozen_and_records_once():
    """The SH shading is traced once and replayed (dr.freeze): the images equal
    those of the unfrozen shading bit for bit, and 8 frames record it once."""
    scene = _plane("adaptive_env_frozen", lambda b: b.add_envmap(rgb=[0.8, 0.85, 1.0]))
    out = {}
    for frozen in (True, False):
        m = methods.create("adaptive:force=sh", scene, seed=1)
        rep = m.rep(ch.SH)
        rep.shade_fn = sh_rep.SHShading(m.encoding, m.seed, m.glossy_samples, freeze=frozen)
        imgs, _ = render_frames(scene, m, [_still(scene)], 8, W, H)
        out[frozen] = (imgs[0], rep.shade_fn.recordings, rep.shade_fn.frozen)
    assert out[True][2] and out[True][1] == 1, out[True][1:]
    assert np.array_equal(out[True][0], out[False][0])


@pytest.mark.fresh_process
@pytest.mark.slow
def test_frozen_cones_update_matches_unfrozen_as_entries_change():
    """The CONES update is traced once and replayed (dr.freeze): under an area
    light (no delta light: the statistics' delta share is a literal zero in the
    trace) with a moving camera, so that the number of CONES entries changes
    from frame to frame, every frame equals the unfrozen update's bit for bit,
    and the update stays frozen with at most the warm-up's two recordings."""
    from slc.methods.adaptive import cones_rep
    b = SceneBuilder("adaptive_cones_frozen")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_quad([0, 1, 0], [0.5, 0, 0], [0, 0, 0.5], bsdf=diffuse([0, 0, 0]), emission=[4.0] * 3, name="light")
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0]), ([0.6, 0.5, 0.6], [0.3, 0.0, -0.2])], frames=10, fov=60)
    scene = b.build([cam, cam, cam])
    _assert_frozen_matches_unfrozen(scene, "adaptive:force=cones", ch.CONES,
                                    lambda m, frozen: cones_rep.ConesUpdate(m.cone_params, m.seed, m.sph, m.env,
                                                                            freeze=frozen))


def _assert_frozen_matches_unfrozen(scene, spec, tag, make):
    """Render 10 frames of ``scene`` with the method ``spec`` whose representation ``tag``'s
    update (made by ``make(method, frozen)``) is frozen, then unfrozen: the
    entry count changes after the warm-up (replays at other widths), the frozen
    update stays frozen with 1-2 recordings, and every frame is equal bit for bit."""
    from slc.methods import FrameContext
    from slc.scene.gbuffer import frame_gbuffers
    from slc.core.timing import NullTimer
    v = Viewer("v0", lambda f: scene.path(0).at(f))
    out = {}
    for frozen in (True, False):
        m = methods.create(spec, scene, seed=1)
        rep = m.rep(tag)
        rep.update_fn = make(m, frozen)
        imgs, counts = [], []
        for f in range(10):
            gbs = frame_gbuffers(scene, [v], f, W, H)
            imgs.append(np.array(m.render(FrameContext(f), gbs, NullTimer())[0]))
            counts.append(m.stats()["active_entries"])
        out[frozen] = (imgs, counts, rep.update_fn.recordings, rep.update_fn.frozen)
    assert len(set(out[True][1][2:])) > 1, out[True][1]          # replayed at other widths
    assert out[True][3] and 1 <= out[True][2] <= 2, out[True][2:]
    for a, c in zip(out[True][0], out[False][0]):
        assert np.array_equal(a, c)


@pytest.mark.fresh_process
@pytest.mark.slow
def test_frozen_sh_update_matches_unfrozen_as_entries_change():
    """The SH update is traced once and replayed (dr.freeze): under a constant
    sky (no delta light: the statistics' delta share is a literal zero in the
    trace) with a moving camera, so that the number of SH entries changes from
    frame to frame, every frame equals the unfrozen update's bit for bit, and
    the update stays frozen with at most the warm-up's two recordings."""
    b = SceneBuilder("adaptive_sh_frozen")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_envmap(rgb=[0.8, 0.85, 1.0])
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0]), ([0.6, 0.5, 0.6], [0.3, 0.0, -0.2])], frames=10, fov=60)
    scene = b.build([cam, cam, cam])
    _assert_frozen_matches_unfrozen(scene, "adaptive:force=sh", ch.SH,
                                    lambda m, frozen: sh_rep.SHUpdate(m.encoding, m.seed, m.sh_count, m.sph, m.env,
                                                                      freeze=frozen))


def _plane_points(scene, n=64):
    """Interactions on the plane of ``scene`` at n points (rays straight down)."""
    import drjit as dr
    rng = np.random.default_rng(3)
    xz = rng.uniform(-1.5, 1.5, (n, 2))
    o = mi.Point3f(xz[:, 0], np.full(n, 0.5), xz[:, 1])
    si = scene.mi_scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(0.0, -1.0, 0.0)))
    dr.eval(si)
    return si


@pytest.mark.slow
def test_cone_pool_update_is_slc_update_bit_for_bit():
    """The adaptive cone pool runs slc's own update cycle (slc.lib.cones.cycle.update_cycle
    through a SampleObserver): from the same records, keys, rays, policy state and seed
    its new records equal those of slc's update_entries word for word, over cycles of
    the ray ramp (stratified samples from first_sample) and a moving cycle (C capped,
    a second sequence), and the observer's statistics are those of the samples."""
    import drjit as dr

    from slc.methods.adaptive import cones_rep
    from slc.lib.cones.packing import words_per_entry
    from slc.lib.cones.update import ConeParams
    from slc.methods.cones.update_kernel import update_entries
    from slc.methods.cache_method import RayPolicy

    scene = _plane("adaptive_cone_bits", lambda b: (b.add_quad([0, 1.0, 0], [0.3, 0, 0], [0, 0, 0.3],
                                                             bsdf=diffuse([0, 0, 0]), emission=[4.0] * 3,
                                                             name="lamp"),
                                                  b.add_point_light([0.8, 0.7, 0.2], [1.0] * 3)))
    si = _plane_points(scene)
    n = dr.width(si)
    assert bool(dr.all(si.is_valid()))
    p, K = ConeParams(max_cones=3), 3
    Wd = words_per_entry(K)
    keys = dr.arange(mi.UInt32, n) * 7 + 11
    policy = RayPolicy(new=32, new_updates=20, halve_every=4, settled=1, moving=8)
    # opaque (evaluated) inputs, every frame: the same kernels in every frame (a literal zero in
    # the first frame, or each frame's unevaluated chain of policy steps, would trace new ones)
    storage = dr.opaque(mi.UInt32, 0, n * Wd)
    recs = [dr.opaque(mi.UInt32, 0, n) for _ in range(Wd)]
    state = dr.opaque(mi.UInt32, 0, n)
    slots = dr.arange(mi.UInt32, n)
    stats_sum = 0.0
    for f in range(6):
        is_new = dr.opaque(mi.Bool, f == 0, n)             # opaque: one kernel for every frame
        motion_in = dr.opaque(mi.Bool, f == 4, n)        # frame 5: every entry in its moving phase
        rays, unsettled = policy.rays(state)
        moving = (state >> 16) > 0
        first = policy.samples_before(state)
        storage, _ = update_entries(scene.mi_scene, storage, slots, si, rays, unsettled, is_new,
                                    dr.full(mi.UInt32, INVALID, n), keys, f, 5, p, moving=moving,
                                    first_sample=first, strata=~moving)
        recs, mo, st = cones_rep.update(scene.mi_scene, recs, si, keys, rays, unsettled, moving, first, is_new,
                                        dr.full(mi.Bool, True, n), f, 5, p)
        dr.eval(recs, st)
        ref = np.array(storage).reshape(n, Wd)
        ours = np.stack([np.array(w) for w in recs], axis=1)
        assert np.array_equal(ref, ours), f
        ed, en = np.array(st[0]), np.array(st[1])
        assert np.isfinite(ed).all() and (ed >= 0).all() and (en >= 0).all()
        assert (ed > 0).any() and (en > 0).any()          # both kinds of light are seen
        stats_sum += float(ed.sum() + en.sum())
        state = policy.advance(state, mo | motion_in)
        dr.make_opaque(state)
    assert stats_sum > 0


SWITCH_FRAMES = 50       # frames after the light change by which 90% of the entries have chosen cones
JUMP = 0.03              # bound on the frame-to-frame change of the image mean once the light has changed


def _point_then_area():
    def lights(b):
        b.add_point_light([0.0, 1.0, 0.0], [2.0] * 3, name="bulb")
        b.add_quad([0, 1.0, 0], [0.6, 0, 0], [0, 0, 0.6], bsdf=diffuse([0, 0, 0]), emission=[0.0] * 3,
                   name="panel")
    return _plane("adaptive_switch", lights)


def _set_lights(scene, point, area):
    params = mi.traverse(scene.mi_scene)
    for k in params.keys():
        if k.endswith("intensity.value"):
            params[k] = mi.Color3f(point)
        elif k.endswith("emitter.radiance.value"):
            params[k] = mi.Color3f(area)
    params.update()
    emitter_sampling.forget(id(scene.mi_scene))   # this scene's table only (others are shared)
    emitter_sampling.for_scene(scene.mi_scene)


@pytest.mark.slow
def test_point_to_area_switch_changes_the_choice_without_energy_jumps():
    scene = _point_then_area()
    _set_lights(scene, 2.0, 0.0)
    # the square light as an area light of the cones (a listed polygon light would keep every
    # entry in VISIBILITY: test_square_light_is_listed_with_its_exact_irradiance)
    m = methods.create("adaptive:polygon_lights=off", scene, seed=3)
    v = _still(scene)
    render_frames(scene, m, [v], 16, W, H)
    assert m.stats()["share_visibility"] > 0.95
    _set_lights(scene, 0.0, 2.0)
    means, shares, sw = [], [], []
    for f in range(16, 16 + SWITCH_FRAMES + 10):
        imgs, gbs = render_frames(scene, m, [v], 1, W, H, start=f)
        ok = _valid(gbs[0])
        means.append(imgs[0][ok].mean())
        st = m.stats()
        shares.append(st["share_cones"])
        sw.append(st["switches"])
    first = next((i for i, s in enumerate(shares) if s >= 0.9), None)
    assert first is not None and first < SWITCH_FRAMES, shares
    assert sum(sw) > 0
    # no jump: once the residual has picked up the new light (the first frames converge towards
    # it), the image mean changes by less than JUMP per frame, also in the frames with switches
    jumps = np.abs(np.diff(means)) / np.array(means[1:])
    assert jumps[8:].max() < JUMP, (jumps.max(), np.argmax(jumps))
    gt = ground_truth(scene, gbs[0], f, "v0", spp=256, use_cache=False)
    assert abs(means[-1] - gt[ok].mean()) / gt[ok].mean() < 0.05


@pytest.mark.slow
def test_still_camera_frame_to_frame_change_is_bounded():
    """Two emitters (a point light and a square light): mixed choices, still
    camera; after start-up the image mean moves by less than 2% a frame."""
    def lights(b):
        b.add_point_light([0.6, 0.8, 0.0], [1.0] * 3)
        b.add_quad([-0.5, 1.0, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]), emission=[4.0] * 3,
                   name="panel")
    scene = _plane("adaptive_still", lights)
    m = methods.create("adaptive", scene, seed=2)
    v = _still(scene)
    render_frames(scene, m, [v], 16, W, H)
    means = []
    for f in range(16, 40):
        imgs, gbs = render_frames(scene, m, [v], 1, W, H, start=f)
        means.append(imgs[0][_valid(gbs[0])].mean())
    jumps = np.abs(np.diff(means)) / np.array(means[1:])
    assert jumps.max() < 0.02, jumps.max()


def test_pool_allocates_unique_slots_and_reuses_freed_ones():
    p = Pool("t", 2, initial=4)
    a = np.array(p.acquire(mi.Bool([True, False, True, True])))
    assert a[1] == INVALID and len(set(a[[0, 2, 3]])) == 3 and p.used == 3
    p.release(mi.UInt32(a), mi.Bool([True, False, False, True]))
    assert p.used == 1
    b = np.array(p.acquire(mi.Bool([True] * 100)))          # grows
    assert len(set(b)) == 100 and a[2] not in set(b) and p.capacity >= 101


def test_tally_counts_every_mask_with_one_read_back():
    a, b = mi.Bool([True, False, True, True]), mi.Bool([False] * 4)
    assert tally([a, b, ~b]) == [3, 0, 4]
    assert tally([mi.Bool([True])]) == [1]


def test_header_round_trip():
    h = ch.Header(tag=mi.UInt32([1, 3]), streak=mi.UInt32([2, 63]), count=mi.UInt32([5, 63]),
                  e=mi.Float([0.25, 1e6]), slot=mi.UInt32([7, INVALID]), s_delta=mi.Float([1.0, 0.3]),
                  m=mi.Vector3f([0.0, 0.5], [0.0, -0.2], [1.0, 0.6]))
    g = ch.unpack_header(ch.pack_header(h))
    assert list(g.tag) == [1, 3] and list(g.streak) == [2, 63] and list(g.count) == [5, 63]
    assert list(g.slot) == [7, INVALID]
    assert np.allclose(np.array(g.e), [0.25, 1e6], rtol=1e-3)
    assert np.allclose(np.array(g.s_delta), [1.0, 0.3], atol=1 / 255)
    assert np.allclose(np.array(g.m), np.array(h.m), atol=1 / 127)


def test_hysteresis():
    p = ch.ChoiceParams()
    def hdr(tag, s, mz):
        return ch.Header(tag=mi.UInt32(tag), streak=mi.UInt32(0), count=mi.UInt32(10), e=mi.Float(1.0),
                         slot=mi.UInt32(0), s_delta=mi.Float(s), m=mi.Vector3f(0.0, 0.0, mz))
    # inside the band the current representation stays
    assert ch.target_of(hdr(ch.VIS, 0.45, 1.0), p)[0] == ch.VIS
    assert ch.target_of(hdr(ch.CONES, 0.55, 1.0), p)[0] == ch.CONES
    assert ch.target_of(hdr(ch.SH, 0.0, 0.78), p)[0] == ch.SH
    assert ch.target_of(hdr(ch.CONES, 0.0, 0.72), p)[0] == ch.CONES
    assert ch.target_of(hdr(ch.CONES, 0.0, 0.6), p)[0] == ch.SH
    # a glossy entry whose other light is narrow (R = 1 here) needs theta_glossy +- h_glossy:
    # 0.99 to enter VISIBILITY, 0.95 to stay; with wide other light (R = 0.6) theta_delta
    g = mi.Bool(True)
    assert ch.target_of(hdr(ch.CONES, 0.9, 1.0), p, g)[0] == ch.CONES
    assert ch.target_of(hdr(ch.CONES, 0.9, 1.0), p, mi.Bool(False))[0] == ch.VIS
    assert ch.target_of(hdr(ch.CONES, 0.995, 1.0), p, g)[0] == ch.VIS
    assert ch.target_of(hdr(ch.VIS, 0.96, 1.0), p, g)[0] == ch.VIS
    assert ch.target_of(hdr(ch.VIS, 0.9, 1.0), p, g)[0] == ch.CONES
    assert ch.target_of(hdr(ch.CONES, 0.9, 0.6), p, g)[0] == ch.VIS
    # a switch needs switch_after updates in a row
    h = hdr(ch.CONES, 0.9, 1.0)
    for k in range(p.switch_after):
        h, sw, t = ch.decide(h, p)
        assert bool(sw[0]) == (k == p.switch_after - 1)


def test_bad_settings():
    scene = _plane("adaptive_bad", lambda b: b.add_point_light([0, 1, 0], [1.0] * 3))
    for spec in ("adaptive:vis_lights=0", "adaptive:start=foo", "adaptive:theta_r=2"):
        with pytest.raises(methods.MethodError):
            methods.create(spec, scene)


def test_visibility_entries_whose_lights_are_listed_trace_a_share_of_the_rays():
    """traced_rays: an entry whose listed lights bring >= 95% of its light (or a new one, in a
    scene whose every light can be listed) traces vis_rays of the policy's rays, at least one;
    any other keeps them all."""
    import drjit as dr
    import mitsuba as mi
    from slc.methods.adaptive.visibility.lights import traced_rays
    rays = mi.UInt32([32, 32, 32, 1, 8, 8])
    s = mi.Float([0.99, 0.5, 0.0, 0.99, 0.95, 0.94])
    fresh = mi.Bool([False, False, True, False, False, False])
    assert traced_rays(rays, s, fresh, True, 0.5).numpy().tolist() == [16, 32, 16, 1, 4, 8]
    assert traced_rays(rays, s, fresh, False, 0.5).numpy().tolist() == [16, 32, 32, 1, 4, 8]
    assert traced_rays(rays, s, fresh, True, 1.0).numpy().tolist() == [32, 32, 32, 1, 8, 8]
    dr.eval()


def test_new_entries_start_in_the_representation_most_entries_hold():
    """A point light and a square light that is not listed: the scene's prior is cones (mixed
    emitters), but under the point light alone every entry chooses VISIBILITY, so new entries
    start there (``start=majority``, the default); ``start=prior`` keeps the prior."""
    scene = _point_then_area()
    _set_lights(scene, 2.0, 0.0)
    m = methods.create("adaptive:polygon_lights=off", scene, seed=3)
    assert m.prior == ch.CONES
    assert m._representation_of_new() == ch.CONES        # before the first update: the prior
    render_frames(scene, m, [_still(scene)], 8, W, H)
    assert m.stats()["share_visibility"] > 0.95
    assert m._representation_of_new() == ch.VIS
    p = methods.create("adaptive:polygon_lights=off,start=prior", scene, seed=3)
    render_frames(scene, p, [_still(scene)], 8, W, H)
    assert p._representation_of_new() == ch.CONES
