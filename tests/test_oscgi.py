"""osc-gi (slc/oscgi): the hemisphere grid, the secondary hash table, convergence to the
multi-bound reference, light leaking between two rooms, sharing across viewers, determinism and
check mode; the multi-bounce reference against the closed form of a furnace box; the pt baseline."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.core import check

from slc import methods

from slc.reference import references

from slc.scene import scenes, views
from slc.scene.gbuffer import frame_gbuffers, to_image
from slc.methods import FrameContext, MethodError
from slc.methods.oscgi import HemiGrid, SecondaryCache
from slc.methods.oscgi.method import OSCGI
from slc.run.pipeline import RunConfig, run_sequence
from slc.scene.builder import SceneBuilder, box_mesh, diffuse, diffuse_cornell
from slc.scene.camera import CameraPath
from slc.core.timing import NullTimer


W, H = 64, 36


def create(spec, scene, seed=0, **fixed):
    """``methods.create(spec)``, with osc-gi's fixed choices (class attributes) ``fixed`` switched
    in a subclass: how the measured alternatives of those choices are run again."""
    if not fixed:
        return methods.create(spec, scene, seed=seed)
    name, settings = methods.parse_spec(spec)
    assert name == "osc-gi" and all(hasattr(OSCGI, k) for k in fixed), fixed
    return type("OSCGIVariant", (OSCGI,), dict(fixed))(scene, seed=seed, **settings)


def _run(scene, spec, viewers, frames, w=W, h=H, seed=0, **fixed):
    m = create(spec, scene, seed, **fixed)
    for f in range(frames):
        gbs = frame_gbuffers(scene, viewers, 0, w, h)       # a still camera: frame 0's view every frame
        with check.scope(spec, f, gbs):
            out = m.render(FrameContext(f), gbs, NullTimer())
            if check.enabled():
                check.images(out, gbs)
    return m, gbs, [references.image_of(m.output, gb, x) for gb, x in zip(gbs, out)]


@pytest.fixture(scope="module")
def dcornell():
    return diffuse_cornell()


# ----------------------------------------------------------------------------- pieces
def test_hemigrid_texels_round_trip_and_cover_pi():
    G = HemiGrid(8)
    k = dr.arange(mi.UInt32, G.n * 16) // 16
    s = mi.PCG32(size=G.n * 16)
    d = G.direction(k, mi.Point2f(s.next_float32(), s.next_float32()))
    assert np.array_equal(np.array(G.texel(d)), np.array(k))
    assert np.allclose(np.array(dr.norm(d)), 1.0, atol=1e-5) and np.all(np.array(d.z) >= 0.0)
    # projected solid angle of every texel: pi / R^2 (Monte Carlo over uniform directions)
    n = 1 << 18
    s = mi.PCG32(size=n)
    u = mi.warp.square_to_uniform_hemisphere(mi.Point2f(s.next_float32(), s.next_float32()))
    t = np.array(G.texel(u))
    w = np.array(u.z) * 2 * math.pi / n
    per = np.bincount(t, weights=w, minlength=G.n)
    assert np.allclose(per, math.pi / G.n, rtol=0.08), per


def test_secondary_table_insert_is_unique_and_deterministic():
    sc = mi.load_dict({"type": "scene"})
    tab = SecondaryCache(sc, 0.3, slots=1 << 8, probes=256)
    keys = mi.UInt32(np.repeat(np.arange(1, 151, dtype=np.uint32) * 2654435761 % 4000000000, 3))
    home = keys % 16                      # heavy contention: 150 keys, 16 home slots
    s1 = np.array(tab.find_or_insert(keys, home, mi.Bool(True)))
    assert (s1 != 0xFFFFFFFF).all() and tab.overflow == 0
    per_key = {}
    for k, s in zip(np.array(keys), s1):
        per_key.setdefault(int(k), set()).add(int(s))
    assert all(len(v) == 1 for v in per_key.values())                 # one slot per key
    assert len({next(iter(v)) for v in per_key.values()}) == 150       # distinct keys, distinct slots
    s2 = np.array(tab.find_or_insert(keys, home, mi.Bool(True)))       # found again, same slots
    assert np.array_equal(s1, s2)
    tab2 = SecondaryCache(sc, 0.3, slots=1 << 8, probes=256)
    assert np.array_equal(np.array(tab2.find_or_insert(keys, home, mi.Bool(True))), s1)


def test_eviction_keeps_a_small_table_from_overflowing_and_frees_unused_cells():
    """A table of 256 slots fed 64 new keys a frame for 30 frames (1,920 distinct cells): with
    eviction (unused for K = 2 frames, load cap 1/4) no request ever overflows; without it the
    table fills and requests overflow (the check can fail). A cell unused for K frames is freed,
    and a key inserted later into its slot starts from a reset state."""
    sc = mi.load_dict({"type": "scene"})

    def feed(tab, frames=30):
        for f in range(frames):
            tab.begin_frame(f)
            keys = mi.UInt32((np.arange(64, dtype=np.uint32) + 64 * f) * 2654435761 % 4000000000 + 1)
            slots = np.array(tab.find_or_insert(keys, keys % tab.slots, mi.Bool(True)))
            assert tab.used_cells() <= tab.slots
        return slots

    tab = SecondaryCache(sc, 0.3, slots=1 << 8, evict_after=2)
    feed(tab)
    assert tab.overflow == 0 and tab.used_cells() <= 64 + 64 + 64
    full = SecondaryCache(sc, 0.3, slots=1 << 8, evict_after=0)
    feed(full)
    assert full.overflow > 0 and full.used_cells() == 256

    # ------- key A used at frame 0 only: freed at frame K; key B with A's home reuses its slot -------
    tab = SecondaryCache(sc, 0.3, slots=1 << 8, evict_after=2)
    tab.begin_frame(0)
    a = mi.UInt32([12345])
    sa = tab.find_or_insert(a, mi.UInt32([7]), mi.Bool(True))
    assert np.array(sa)[0] == 7
    dr.scatter(tab.count, mi.UInt32(5), sa)
    dr.scatter(tab.layers, mi.Float(1.0), dr.arange(mi.UInt32, 3 * tab.B) + 7 * 3 * tab.B)
    tab.begin_frame(2)
    assert 12345 in np.array(tab.keys)                    # unused in frames 1, 2: kept
    tab.begin_frame(3)
    assert tab.evicted == 1 and 12345 not in np.array(tab.keys) and tab.used_cells() == 0
    sb = tab.find_or_insert(mi.UInt32([999]), mi.UInt32([7]), mi.Bool(True))
    assert np.array(sb)[0] == 7
    assert np.array(tab.count)[7] == 0 and not np.array(tab.layers)[7 * 3 * tab.B:8 * 3 * tab.B].any()


def test_eviction_moves_the_surviving_cells_with_their_data():
    """The rebuild after eviction keeps every survivor findable under its key, with its data."""
    sc = mi.load_dict({"type": "scene"})
    tab = SecondaryCache(sc, 0.3, slots=1 << 8, probes=64, evict_after=1, max_load=0.5)
    tab.begin_frame(0)
    old = mi.UInt32(np.arange(1, 41, dtype=np.uint32) * 7919)
    tab.find_or_insert(old, old % 16, mi.Bool(True))          # contended homes: long probe chains
    assert tab.overflow == 0 and tab.used_cells() == 40
    tab.begin_frame(1)
    keep = mi.UInt32(np.arange(1, 41, 2, dtype=np.uint32) * 7919)
    s_keep = tab.find_or_insert(keep, keep % 16, mi.Bool(True))
    dr.scatter(tab.count, keep, s_keep)                       # a value per cell to follow
    tab.begin_frame(2)                                        # the 20 others, unused in frame 1 (K = 1)
    assert tab.evicted == 20 and tab.used_cells() == 20
    s2 = tab.find_or_insert(keep, keep % 16, mi.Bool(True))
    assert tab.used_cells() == 20                             # found, not inserted again
    assert np.array_equal(np.array(dr.gather(mi.UInt32, tab.count, s2)), np.array(keep))


def test_budget_updates_the_least_sampled_cells_and_keeps_the_others(dcornell):
    """With a budget of 64 cell updates a frame, exactly 64 of the requested cells are updated,
    those with the lowest update counts; the other cells' layers and counts are unchanged."""
    m, _, (img,) = _run(dcornell, "osc-gi:secondary_budget=64", views.single(dcornell), 4)
    sec = m.secondary
    assert np.isfinite(img).all() and sec.requested > 64 and sec.updated == 64
    live = sec.keys != 0xFFFFFFFF
    req = dr.select(live, mi.UInt32(1), mi.UInt32(0xFFFF))   # request every cell as ring 1
    cnt0, lay0 = np.array(sec.count), np.array(sec.layers).reshape(-1, 3 * sec.B)
    sec.frame = 4
    done = np.array(sec.update(4, req))
    cnt1, lay1 = np.array(sec.count), np.array(sec.layers).reshape(-1, 3 * sec.B)
    assert done.size == 64
    changed = np.nonzero(cnt1 != cnt0)[0]
    assert np.array_equal(np.sort(changed), np.sort(done))
    others = np.setdiff1d(np.nonzero(np.array(live))[0], done)
    assert cnt0[done].max() <= cnt0[others].min()            # least-sampled first
    assert np.array_equal(lay1[others], lay0[others]) and np.array_equal(cnt1[others], cnt0[others])


def test_settings_are_checked(dcornell):
    with pytest.raises(MethodError):
        methods.create("osc-gi:output=direct", dcornell)
    with pytest.raises(MethodError):
        methods.create("osc-gi:secondary_cm=0", dcornell)
    assert methods.create("osc-gi", dcornell).output == "full"
    assert methods.create("osc-gi:output=indirect", dcornell).output == "indirect"


# ----------------------------------------------------------------------------- the reference
def furnace(albedo, radiance):
    """A closed sphere (icosphere, 1280 faces, facing in) whose inside emits ``radiance`` and
    reflects with ``albedo``. On a sphere cos(a) cos(b) / r^2 = 1 / (4 R^2) between any two
    points, so next-event estimation by area sampling has (almost) no variance there."""
    import trimesh
    b = SceneBuilder("furnace")
    tm = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    b.add_mesh(np.asarray(tm.vertices), np.asarray(tm.faces)[:, ::-1], bsdf=diffuse([albedo] * 3),
               emission=[radiance] * 3, name="sphere")
    cam = CameraPath([([0.0, 0.0, 0.3], [0.3, -0.2, -1.0])], frames=4, fov=80)
    return b.build([cam])


@pytest.mark.parametrize("bounces", [1, 3])
def test_indirect_reference_matches_the_furnace_closed_form(bounces):
    """Uniform emission E, albedo rho, closed sphere: every path of k reflections brings rho^k E, so
    direct light is rho E and the indirect reference (1..B bounces after the first reflection)
    is E sum_{k=2}^{B+1} rho^k."""
    rho, E = 0.5, 1.0
    s = furnace(rho, E)
    gb = frame_gbuffers(s, views.single(s), 0, 24, 16)[0]
    ind = to_image(gb, references.indirect_light(s.mi_scene, gb, spp=32, bounces=bounces)).mean()
    expect = E * sum(rho ** k for k in range(2, bounces + 2))
    assert abs(ind - expect) < 0.01 * expect, (ind, expect)      # measured: within 0.1%


# ----------------------------------------------------------------------------- the method
@pytest.mark.slow
def test_converges_to_the_indirect_reference(dcornell):
    """Diffuse Cornell box, still camera, 2 bounces: after 24 frames the mean indirect light is
    within 10% of the 256-path reference and the mean absolute pixel error within 25% of the mean
    (measured: 0.961 of the reference, 0.151)."""
    m, gbs, imgs = _run(dcornell, "osc-gi:output=indirect", views.single(dcornell), 24)
    ref = references.reference_for("indirect", dcornell, gbs[0], 0, "test", spp=256,
                                   bounces=references.reference_bounces(m))
    img = imgs[0]
    assert np.isfinite(img).all()
    assert abs(img.mean() / ref.mean() - 1.0) < 0.10, (img.mean(), ref.mean())
    assert np.abs(img - ref).mean() < 0.25 * ref.mean()
    assert m.secondary.overflow == 0 and m.secondary.used_cells() > 0


@pytest.mark.slow
def test_glossy_hits_bring_the_light_reflected_by_metal():
    """The Cornell box with its rough-aluminium block, still camera, 12 frames at 32x18: cache rays
    hitting the metal read its cell's diffuse radiance (0) without ``OSCGI.glossy_hits``; with it (NEE +
    one BSDF ray there) the mean indirect light is within 15% of the reference and closer to it
    than without (measured on the moving quick path: 0.97 vs 0.68 of the reference)."""
    s = scenes.load("cornell")
    ratio = {}
    for g in (1, 0):
        m, gbs, imgs = _run(s, "osc-gi:output=indirect", views.single(s), 12, 32, 18, glossy_hits=bool(g))
        ref = references.reference_for("indirect", s, gbs[0], 0, "test", spp=128, bounces=m.bounces)
        assert np.isfinite(imgs[0]).all()
        ratio[g] = imgs[0].mean() / ref.mean()
    assert abs(ratio[1] - 1.0) < 0.15, ratio
    assert abs(ratio[1] - 1.0) < abs(ratio[0] - 1.0) - 0.05, ratio


@pytest.mark.fresh_process
@pytest.mark.slow
def test_frozen_kernels_give_the_traced_images():
    """``freeze`` (the kernels with shape/BSDF/emitter calls replayed) changes no pixel: a moving
    camera (the entry and ray counts change every frame) on the Cornell box with its metal block."""
    s = scenes.load("cornell")
    vs = views.single(s)
    out = {}
    for fz in (1, 0):
        m = methods.create(f"osc-gi:freeze={fz}", s)
        imgs, recs = [], []
        for f in range(6):
            gbs = frame_gbuffers(s, vs, f, 32, 18)
            imgs.append(np.array(m.render(FrameContext(f), gbs, NullTimer())[0]))
            recs.append(m.secondary._k_trace.n_recordings)
        out[fz] = (imgs, m, recs)
    for a, b in zip(out[1][0], out[0][0]):
        assert np.array_equal(a, b)
    # replayed after the warm-up frames (the first frame's all-new entries lay the inputs out
    # otherwise: measured 3 + 2 recordings for the primary, secondary and glossy-hit rays)
    k, recs = out[1][1].secondary._k_trace, out[1][2]
    assert k.frozen and k.calls >= 15 and recs[2] == recs[-1], (k.calls, recs)


def test_full_output_is_direct_plus_indirect(dcornell):
    m, gbs, imgs = _run(dcornell, "osc-gi", views.single(dcornell), 16)
    ref = references.reference_for("full", dcornell, gbs[0], 0, "test", spp=256, bounces=2)
    valid = np.array(gbs[0].valid).reshape(H, W)
    assert abs(imgs[0][valid].mean() / ref[valid].mean() - 1.0) < 0.10, (imgs[0][valid].mean(), ref[valid].mean())
    assert np.abs(imgs[0] - ref)[valid].mean() < 0.25 * ref[valid].mean()


@pytest.mark.slow
def test_no_light_leaks_into_the_closed_dark_room():
    """two_rooms: one viewer in the lit room, one in the closed dark room beside it (its reference is
    exactly 0). With the cells keyed by shape the dark room stays exactly dark; without (cells of
    30 cm straddle the 10 cm wall) light leaks, which shows that the check can fail."""
    s = scenes.load("two_rooms")
    vs = views.single(s, 0) + views.single(s, 1)
    m, gbs, imgs = _run(s, "osc-gi", vs, 8, 48, 27)
    lit, dark = imgs
    ref_dark = references.reference_for("full", s, gbs[1], 0, "dark", spp=16, bounces=2, use_cache=False)
    assert ref_dark.max() == 0.0
    assert lit.mean() > 0.05
    assert dark.max() <= 1e-4 * lit.mean(), dark.max()             # measured: 0
    # 30 cm cells: the wall is placed so that one straddles it
    _, _, (lit2, dark2) = _run(s, "osc-gi:secondary_cm=30", vs, 8, 48, 27, shape_key=False)
    assert dark2.mean() > 1e-3 * lit2.mean()                          # the leak the shape key removes


@pytest.mark.slow
def test_entries_and_cells_are_shared_across_viewers(dcornell):
    v1 = views.single(dcornell)
    m1, _, (a,) = _run(dcornell, "osc-gi", v1, 4)
    m2, _, (b, c) = _run(dcornell, "osc-gi", v1 + v1, 4)
    assert np.array_equal(a, b) and np.array_equal(b, c)
    assert m1.memory_bytes() == m2.memory_bytes()
    assert m1.secondary.used_cells() == m2.secondary.used_cells()
    # a second, different viewer adds entries and cells, but far fewer than a second cache would
    m3, _, _ = _run(dcornell, "osc-gi", v1 + views.single(dcornell, 1), 4)
    assert m1.secondary.used_cells() < m3.secondary.used_cells() < 2 * m1.secondary.used_cells()


def test_deterministic_and_seeded(dcornell):
    v = views.single(dcornell)
    _, _, (a,) = _run(dcornell, "osc-gi", v, 3)
    _, _, (b,) = _run(dcornell, "osc-gi", v, 3)
    _, _, (c,) = _run(dcornell, "osc-gi", v, 3, seed=1)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_check_mode_finite(dcornell, monkeypatch):
    monkeypatch.setenv(check.ENV, "1")
    s = scenes.load("cornell")                   # with its glossy block: BSDF-sampled shading too
    _, _, (img,) = _run(s, "osc-gi", views.single(s), 3, 32, 18)
    assert np.isfinite(img).all() and img.min() >= 0.0


@pytest.mark.slow
def test_pipeline_compares_with_the_full_reference_and_reports_caches(dcornell):
    m = methods.create("osc-gi", dcornell)
    cfg = RunConfig(width=32, height=18, frames=3, warmup=1, ref_spp=16)
    r = run_sequence(dcornell, m, views.single(dcornell), cfg)
    assert np.isfinite(r.metrics["flip"])
    ref = references.reference_for("full", dcornell, frame_gbuffers(dcornell, views.single(dcornell), 2, 32, 18)[0],
                                   2, views.single(dcornell)[0].name, spp=16, bounces=2)
    assert np.array_equal(list(r.images.values())[0]["gt"], ref)
    for k in ("secondary_cells", "primary_mb", "secondary_mb", "secondary_reuse_mean"):
        assert r.stats[k] > 0
    h = m.secondary.reuse_histogram()
    assert sum(h["counts"]) == h["cells"] > 0


# ----------------------------------------------------------------------------- pt baseline
@pytest.mark.slow
def test_pt_converges_to_the_reference(dcornell):
    gb = frame_gbuffers(dcornell, views.single(dcornell), 0, 32, 18)[0]
    pt = methods.create("pt:spp=64,output=indirect", dcornell)
    img = references.image_of("indirect", gb, pt.render(FrameContext(0), [gb], NullTimer())[0])
    ref = references.reference_for("indirect", dcornell, gb, 0, "pt", spp=256, bounces=2)
    assert abs(img.mean() / ref.mean() - 1.0) < 0.05
    full = methods.create("pt:spp=16", dcornell)
    assert full.output == "full"
    a = full.render(FrameContext(0), [gb], NullTimer())[0]
    b = full.render(FrameContext(0), [gb], NullTimer())[0]
    assert np.array_equal(np.array(a), np.array(b))
