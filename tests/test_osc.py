"""On-surface cache: islands, atlas, requests/dedupe/allocation, texel
surface points, update queue, eviction, mip levels, memory."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from slc.scene.gbuffer import render_gbuffer
from slc.osc import INVALID, OnSurfaceCache, build_mesh_islands, charts_overlap, island_deviation
from slc.osc.islands import face_adjacency
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import Camera, CameraPath
from slc.scene.scenes import load
from slc.core.timing import StageTimer

W, H = 96, 64


def cam(o, t, fov=45.0):
    return Camera(np.array(o, float), np.array(t, float), fov=fov)


@pytest.fixture(scope="module")
def cornell():
    return load("cornell")


@pytest.fixture(scope="module")
def icosphere_mesh():
    import trimesh
    tm = trimesh.creation.icosphere(subdivisions=6, radius=1.0)   # 81920 triangles, closed
    return np.asarray(tm.vertices), np.asarray(tm.faces)


@pytest.fixture(scope="module")
def sphere_scene():
    b = SceneBuilder("osc_sphere")
    b.add_sphere([0, 0, 0], 1.0, subdivisions=6, bsdf=diffuse([0.6, 0.6, 0.6]))
    b.add_quad([0, 3, 0], [0.5, 0, 0], [0, 0, 0.5], bsdf=diffuse([0, 0, 0]), emission=[5, 5, 5],
               name="light")
    c = CameraPath([([0, 0.5, 3.5], [0, 0, 0])], frames=8, fov=40)
    return b.build([c, c, c])


def flipped(g):
    """The same G-buffer with the image turned by 180 degrees (same surface
    points and footprints, other pixels)."""
    import dataclasses
    idx = mi.UInt32(np.arange(g.size)[::-1].copy())
    kw = {}
    for f in dataclasses.fields(g):
        v = getattr(g, f.name)
        if f.name in ("width", "height", "camera", "viewer") or v is None or isinstance(v, int):
            kw[f.name] = v     # (layers: none attached to a single G-buffer)
        else:
            kw[f.name] = dr.gather(type(v), v, idx)
    return type(g)(**kw)


def gb(scene, o, t, w=W, h=H, fov=45.0):
    return render_gbuffer(scene, cam(o, t, fov), w, h)


# ----------------------------------------------------------------------------- islands

def test_icosphere_islands_bounds_and_speed(icosphere_mesh):
    V, F = icosphere_mesh
    assert len(F) == 81920
    # (no timing assertion: about 0.8 s on 2 cores, see docs/osc.md)
    isl = build_mesh_islands(V, F, texel_size=0.004, max_angle=30.0, max_triangles=128)
    fi = isl.face_island
    # every triangle in exactly one island
    assert fi.shape == (len(F),) and fi.min() >= 0 and fi.max() == isl.n_islands - 1
    counts = np.bincount(fi)
    assert counts.min() >= 1 and counts.max() <= 128
    # normal bound, recomputed independently: angle to the area-weighted mean normal
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    S = np.zeros((isl.n_islands, 3))
    np.add.at(S, fi, n)
    m = S / np.linalg.norm(S, axis=1, keepdims=True)
    nu = n / np.linalg.norm(n, axis=1, keepdims=True)
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(nu, m[fi]), axis=1), (nu * m[fi]).sum(1)))
    assert ang.max() <= 30.0 + 1e-6
    dev, _ = island_deviation(V, F, fi)
    assert np.allclose(dev, isl.max_deviation)
    # islands are connected
    E = face_adjacency(V, F)
    inner = E[fi[E[:, 0]] == fi[E[:, 1]]]
    g = sp.coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(len(F), len(F)))
    ncomp, _ = connected_components(g, directed=False)
    assert ncomp == isl.n_islands
    # islands are not trivially small: the matching merges most of them
    assert np.median(counts) >= 32


def test_atlas_charts_do_not_overlap(icosphere_mesh):
    V, F = icosphere_mesh
    isl = build_mesh_islands(V, F, texel_size=0.004)
    assert not charts_overlap(isl)
    ca = isl.corner_atlas
    off = isl.atlas_offset[isl.face_island]
    d = isl.dims[isl.face_island]
    # every corner lies in its own chart, every chart in the atlas
    assert np.all(ca >= off[:, None, :] - 1e-6)
    assert np.all(ca <= (off + d)[:, None, :] + 1e-6)
    assert np.all(isl.atlas_offset + isl.dims <= np.array(isl.atlas_size))
    # the projection keeps orientation (no flipped triangles) and about the texel scale
    uv = isl.corner_uv
    area2d = 0.5 * np.abs((uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1])
                          - (uv[:, 2, 0] - uv[:, 0, 0]) * (uv[:, 1, 1] - uv[:, 0, 1]))
    area3d = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    ratio = area2d * 0.004 ** 2 / area3d
    assert ratio.min() >= math.cos(math.radians(30)) - 1e-6 and ratio.max() <= 1 + 1e-6


def test_closed_icosphere_cache_does_not_crash(sphere_scene):
    cache = OnSurfaceCache(sphere_scene)
    assert cache.layout.n_triangles == 81920 + 2
    g = gb(sphere_scene, [0, 0.5, 3.5], [0, 0, 0])
    fr = cache.begin_frame(0, [g], StageTimer())
    assert fr.n_active > 100
    assert np.all(np.array(fr.si.is_valid()))


# ----------------------------------------------------------------------------- requests

def _pixel_points(g, fr, v=0):
    slot = np.array(fr.pixel_slot[v])
    ok = slot != INVALID
    idx = np.array(fr.pixel_index[v])
    return ok, slot, idx


def test_dedupe_unique_sorted_and_pixel_index(cornell):
    cache = OnSurfaceCache(cornell)
    g1 = gb(cornell, [0, 1, 3.4], [0, 1, 0])
    g2 = gb(cornell, [0.4, 1.1, 3.0], [0, 0.9, 0])
    fr = cache.begin_frame(0, [g1, g2], StageTimer())
    act = np.array(fr.active)
    assert len(act) > 0 and np.all(np.diff(act.astype(np.int64)) > 0)
    allslots = np.concatenate([np.array(s) for s in fr.pixel_slot])
    assert np.array_equal(np.unique(allslots[allslots != INVALID]), act)
    for v, g in enumerate([g1, g2]):
        ok, slot, idx = _pixel_points(g, fr, v)
        assert np.array_equal(ok, np.array(g.valid))
        assert np.array_equal(act[idx[ok]], slot[ok])
        assert np.all(idx[~ok] == INVALID)
    s = cache.stats()
    assert s["entries_requested"] == len(act)
    assert 0 < s["fill_ratio"] <= 1
    assert s["entries_allocated"] == s["blocks"] * 64
    assert 0 < s["measured_overlap"] < 100


def test_same_surface_same_slot_and_viewer_independent_point(cornell):
    a, b = [0, 1, 3.4], [0.05, 1.0, 3.4]          # a small sideways step: same footprints
    ga, gb_ = gb(cornell, a, [0, 1, 0]), gb(cornell, b, [0.05, 1, 0])
    # one cache, both viewers: identical G-buffers give identical slots
    cache = OnSurfaceCache(cornell)
    fr = cache.begin_frame(0, [ga, ga, gb_], StageTimer())
    assert np.array_equal(np.array(fr.pixel_slot[0]), np.array(fr.pixel_slot[1]))
    # a viewer that sees the same surface points at other pixels (the image
    # flipped) gets the same slots for the same points
    flip = flipped(ga)
    fr = cache.begin_frame(1, [ga, flip], StageTimer())
    sa, sf = np.array(fr.pixel_slot[0]), np.array(fr.pixel_slot[1])
    assert np.array_equal(sf, sa.reshape(H, W)[::-1, ::-1].ravel())
    assert cache.stats()["measured_overlap"] == 100.0
    # two caches, one viewer each: the entry (by its texel key) has the same point
    c1, c2 = OnSurfaceCache(cornell), OnSurfaceCache(cornell)
    f1 = c1.begin_frame(0, [ga], StageTimer())
    f2 = c2.begin_frame(0, [gb_], StageTimer())

    def keyed(c, f):
        info = c.entry_info(f.active)
        keys = info["island"].astype(np.int64) << 40 | info["level"].astype(np.int64) << 35 | \
            info["tx"].astype(np.int64) << 17 | info["ty"].astype(np.int64)
        return dict(zip(keys.tolist(), np.array(f.si.p).T.tolist())), dict(zip(keys.tolist(), np.array(f.si.n).T.tolist()))
    p1, n1 = keyed(c1, f1)
    p2, n2 = keyed(c2, f2)
    common = set(p1) & set(p2)
    assert len(common) > 0.5 * min(len(p1), len(p2))
    assert all(p1[k] == p2[k] for k in common)       # bit-identical
    assert all(n1[k] == n2[k] for k in common)


def test_texel_point_on_surface_and_near_pixels(sphere_scene, cornell):
    for scene, o, t in ((cornell, [0.3, 1.2, 3.0], [0, 0.8, 0]), (sphere_scene, [0, 0.5, 3.5], [0, 0, 0])):
        cache = OnSurfaceCache(scene)
        g = gb(scene, o, t)
        fr = cache.begin_frame(0, [g], StageTimer())
        si = fr.si
        # on the triangle: barycentrics inside, distance to the triangle plane ~ 0
        tri = np.array(dr.gather(mi.UInt32, cache.points.slot_tri, fr.active))
        b = np.array(dr.gather(mi.Point2f, cache.points.slot_b, fr.active)).T
        info = cache.entry_info(fr.active)
        assert np.all(b >= -1e-6) and np.all(b.sum(1) <= 1 + 1e-6)
        p = np.array(si.p).T
        shapes = np.array(cache.layout.d_isl_shape)[info["island"]]
        dist = np.zeros(len(p))
        for k in np.unique(shapes):
            V, F = cache.layout.mesh_data[int(k)]
            sel = shapes == k
            f = F[tri[sel] - cache.layout._np_tri_base[k]].astype(np.int64)
            n = np.cross(V[f[:, 1]] - V[f[:, 0]], V[f[:, 2]] - V[f[:, 0]])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            dist[sel] = np.abs(((p[sel] - V[f[:, 0]]) * n).sum(1))
        assert dist.max() < 1e-5
        # the entry point is within about a texel of every pixel hit that asked for it
        ok, slot, idx = _pixel_points(g, fr)
        pp = np.array(g.si.p).T[ok]
        tw = info["texel_world"][idx[ok]]
        d = np.linalg.norm(pp - p[idx[ok]], axis=1) / tw
        assert np.percentile(d, 99) <= 1.0, np.percentile(d, [50, 99, 100])
        assert d.max() <= 1.5
        # the texel point's normal is the surface's (the pixel's triangle side)
        assert np.all(np.array(si.is_valid()))
        assert all(x is not None for x in si.bsdf())


def test_update_queue_new_entries_and_stages(cornell):
    cache = OnSurfaceCache(cornell)
    g = gb(cornell, [0, 1, 3.4], [0, 1, 0])
    timer = StageTimer()
    for f in range(3):
        timer.begin_frame()
        fr = cache.begin_frame(f, [g], timer)
        stages = timer.end_frame()
        assert np.all(np.array(fr.is_new) == (f == 0))
        assert set(stages) >= {"requests", "allocate", "queue"}
    # keys are the texels' own: the same in a second cache that allocated other blocks first
    other = OnSurfaceCache(cornell)
    other.begin_frame(0, [gb(cornell, [0.4, 0.3, 1.2], [0.4, 0.3, 0.35])], None)
    fr2 = other.begin_frame(1, [g], None)
    k1 = dict(zip(np.array(cache.entry_keys(fr.active)).tolist(), np.array(fr.si.p).T.tolist()))
    k2 = dict(zip(np.array(fr2.keys).tolist(), np.array(fr2.si.p).T.tolist()))
    assert np.array_equal(np.array(fr.keys), np.array(cache.entry_keys(fr.active)))
    common = set(k1) & set(k2)
    assert len(common) > 0.9 * len(k1) and all(k1[k] == k2[k] for k in common)


def test_eviction_frees_blocks_and_memory(cornell):
    K = 3
    cache = OnSurfaceCache(cornell, evict_after=K)
    ga = gb(cornell, [0, 1, 3.4], [0, 1, 0])            # the whole box
    gs = gb(cornell, [0.4, 0.3, 1.2], [0.4, 0.3, 0.35])  # the short block only, close up
    fr0 = cache.begin_frame(0, [ga], None)
    m_full = cache.memory_bytes()
    b_full = cache.stats()["blocks"]
    # blocks counted from the slots handed out (every allocated block is requested in frame 0)
    blocks = len(_blocks_of(cache, fr0))
    assert b_full == blocks and m_full - cache.pool.table_bytes() == blocks * 8 * 8 * 16
    evicted = 0
    for f in range(1, K + 2):
        cache.begin_frame(f, [gs], None)
        evicted += cache.stats()["evicted"]
    assert evicted > 0
    s = cache.stats()
    assert s["blocks"] < b_full
    assert cache.memory_bytes() < m_full
    # evicted entries come back as new
    fr = cache.begin_frame(K + 2, [ga], None)
    assert np.array(fr.is_new).any()
    cache.reset()
    assert cache.stats()["blocks"] == 0


def test_mip_level_grows_with_distance(cornell):
    cache = OnSurfaceCache(cornell)
    med = []
    for z in (0.2, 1.0, 3.0):
        g = gb(cornell, [0, 1, z], [0, 1, -1], fov=30)     # looking at the back wall
        fr = cache.begin_frame(0, [g], None)
        lv = np.array(cache.pixel_levels(g))[np.array(g.valid)]
        med.append(np.median(lv))
    assert med[0] < med[1] < med[2]
    # the formula
    fp = mi.Float([cache.texel_size * 0.7, cache.texel_size * 4, cache.texel_size * 1e6])
    isl = mi.UInt32(0, 0, 0)
    lv = np.array(cache.layout.level_of(fp, isl))
    maxl = int(np.array(cache.layout.d_isl_maxl)[0])
    assert lv[0] == 0 and lv[1] == min(2, maxl) and lv[2] == maxl


def test_lod_seed_from_coarser_entry(cornell):
    cache = OnSurfaceCache(cornell)
    far = gb(cornell, [0, 1, 3.4], [0, 1, -1], fov=30)
    near = gb(cornell, [0, 1, 1.0], [0, 1, -1], fov=30)
    cache.begin_frame(0, [far], None)
    fr = cache.begin_frame(1, [near], None)
    new = np.array(fr.is_new)
    seed = np.array(fr.seed_slot)
    assert new.any()
    assert np.all(seed[~new] == INVALID)
    has = new & (seed != INVALID)
    assert has.sum() > 0.5 * new.sum()
    a = cache.entry_info(np.array(fr.active)[has])
    s = cache.entry_info(seed[has])
    d = s["level"].astype(np.int64) - a["level"]
    assert np.all(d >= 1) and np.array_equal(s["island"], a["island"])
    assert np.array_equal(s["tx"], a["tx"] >> d) and np.array_equal(s["ty"], a["ty"] >> d)


def test_memory_independent_of_identical_viewers(cornell):
    g = gb(cornell, [0, 1, 3.4], [0, 1, 0])
    c1, c2 = OnSurfaceCache(cornell), OnSurfaceCache(cornell)
    c1.begin_frame(0, [g], None)
    c2.begin_frame(0, [g, g], None)
    assert c1.memory_bytes() == c2.memory_bytes() > 0
    assert c1.stats()["measured_overlap"] == 0.0
    assert c2.stats()["measured_overlap"] == 100.0


def test_block_size_two_and_pool_growth(cornell):
    g = gb(cornell, [0, 1, 3.4], [0, 1, 0])
    c8 = OnSurfaceCache(cornell)
    c8.begin_frame(0, [g], None)
    c2 = OnSurfaceCache(cornell, block_size=2, max_blocks=16)
    fr = c2.begin_frame(0, [g], None)
    assert c2.capacity > 16 * 4 and c2.capacity >= fr.n_active
    s2, s8 = c2.stats(), c8.stats()
    assert s2["entries_requested"] == s8["entries_requested"]
    assert s2["fill_ratio"] > s8["fill_ratio"]
    assert s2["entries_allocated"] < s8["entries_allocated"]
    # a fixed pool that is too small reports the overflow instead
    with pytest.warns(UserWarning):
        c = OnSurfaceCache(cornell, max_blocks=4, grow=False)
        fr = c.begin_frame(0, [g], None)
    assert c.stats()["overflow_blocks"] > 0 and c.stats()["blocks"] == 4
    slots = np.array(fr.pixel_slot[0])
    assert np.all(slots[slots != INVALID] < c.capacity)


def test_nothing_in_view(cornell):
    cache = OnSurfaceCache(cornell)
    fr = cache.begin_frame(0, [], None)
    assert fr.n_active == 0 and cache.stats()["blocks"] == 0
    sky = gb(cornell, [0, 1, 5], [0, 1, 10])            # looking out of the open box
    fr = cache.begin_frame(1, [sky], None)
    assert fr.n_active == 0 and np.all(np.array(fr.pixel_slot[0]) == INVALID)


# ----------------------------------------------------------------------------- eviction (public API only)

K_EVICT = 3
VIEW_ALL = ([0, 1, 3.4], [0, 1, 0])                 # the whole box
VIEW_BLOCK = ([0.4, 0.3, 1.2], [0.4, 0.3, 0.35])    # the short block only, close up


def _blocks_of(cache, fr):
    """Physical blocks holding this frame's requested entries (from the slots)."""
    act = np.array(fr.active).astype(np.int64)
    return set((act // cache.layout.block_texels).tolist())


def test_eviction_exact_k_frame_timing(cornell):
    """evict_after=K: a block last requested in frame f is still there in frame
    f + K (an entry requested again then is not new) and freed at the start of
    frame f + K + 1 (requested again then, it comes back new). Counted: no
    eviction in frames 1..K, all of view A's blocks not also used by view B in
    frame K + 1, and the blocks left are exactly those B uses."""
    ga, gbk = gb(cornell, *VIEW_ALL), gb(cornell, *VIEW_BLOCK)
    # requested again after K unused frames: survives
    c = OnSurfaceCache(cornell, evict_after=K_EVICT)
    c.begin_frame(0, [ga], None)
    for f in range(1, K_EVICT):
        c.begin_frame(f, [gbk], None)
    fr = c.begin_frame(K_EVICT, [ga], None)
    assert c.stats()["evicted"] == 0 and not np.array(fr.is_new).any()
    # after K + 1 unused frames: freed, comes back new
    c = OnSurfaceCache(cornell, evict_after=K_EVICT)
    fa = c.begin_frame(0, [ga], None)
    blocks_a = _blocks_of(c, fa)
    evicted = []
    for f in range(1, K_EVICT + 2):
        fb = c.begin_frame(f, [gbk], None)
        evicted.append(c.stats()["evicted"])
    blocks_b = _blocks_of(c, fb)
    assert evicted[:K_EVICT] == [0] * K_EVICT
    assert evicted[K_EVICT] == len(blocks_a - blocks_b) > 0
    assert c.stats()["blocks"] == len(blocks_b)
    fr = c.begin_frame(K_EVICT + 2, [ga], None)
    new = np.array(fr.is_new)
    blk = np.array(fr.active).astype(np.int64) // c.layout.block_texels
    assert new.any() and not new[np.isin(blk, list(blocks_b))].any()


def test_block_in_use_survives(cornell):
    """A view requested every frame keeps its slots for 4K frames (nothing of it is
    evicted, nothing becomes new again) while the blocks of another view, no longer
    requested, are evicted."""
    ga, gbk = gb(cornell, *VIEW_ALL), gb(cornell, *VIEW_BLOCK)
    c = OnSurfaceCache(cornell, evict_after=K_EVICT)
    c.begin_frame(0, [ga, gbk], None)
    f1 = c.begin_frame(1, [gbk], None)
    slots = np.array(f1.pixel_slot[0])
    total_evicted = 0
    for f in range(2, 4 * K_EVICT + 2):
        fr = c.begin_frame(f, [gbk], None)
        total_evicted += c.stats()["evicted"]
        assert np.array_equal(np.array(fr.pixel_slot[0]), slots)
        assert not np.array(fr.is_new).any()
    assert total_evicted > 0


@pytest.mark.slow
def test_reused_slot_starts_from_reset_state(cornell):
    """After view A's blocks are evicted, view C (the back wall up close: other
    texels) is allocated into the freed physical blocks (lowest free first). Every
    entry of C, reused slots included, is new in its first frame only (the payload
    must be reset), and a payload method restarts its ray policy there, exactly as
    in a fresh cache; its texel keys are C's, not A's."""
    ga, gbk = gb(cornell, *VIEW_ALL), gb(cornell, *VIEW_BLOCK)
    gc = gb(cornell, [0, 1, 0.6], [0, 1, -1], fov=30)
    from slc.methods.cones.method import SurfaceLightCones
    from slc.methods import FrameContext
    from slc.core.timing import NullTimer
    c = OnSurfaceCache(cornell, evict_after=K_EVICT)
    m = SurfaceLightCones(cornell, cache=c)
    m.render(FrameContext(0), [ga], NullTimer())
    fa = m.requests
    slots_a = np.array(fa.active)
    keys_a = c.entry_info(slots_a)
    for f in range(1, K_EVICT + 2):
        m.render(FrameContext(f), [gbk], NullTimer())
    fresh = SurfaceLightCones(cornell, cache=OnSurfaceCache(cornell, evict_after=K_EVICT))
    seq, seq_fresh = [], []
    for i in range(10):
        m.render(FrameContext(K_EVICT + 2 + i), [gbk, gc], NullTimer())
        fresh.render(FrameContext(i), [gc], NullTimer())
        fr, ff = m.requests, fresh.requests
        act = np.array(fr.active)
        c_slots = np.unique(np.array(fr.pixel_slot[1])[np.array(gc.valid)])
        idx = np.searchsorted(act, c_slots)
        if i == 0:
            reused = np.isin(c_slots, slots_a)
            assert reused.sum() > 100, reused.sum()
            assert np.all(np.array(fr.is_new)[idx])
            # a reused slot holds another texel now
            ka = {k: v[np.isin(slots_a, c_slots[reused])] for k, v in keys_a.items()}
            kc = c.entry_info(c_slots[reused])
            same = (ka["island"] == kc["island"]) & (ka["level"] == kc["level"]) & \
                (ka["tx"] == kc["tx"]) & (ka["ty"] == kc["ty"])
            assert not same.all()
        else:
            assert not np.array(fr.is_new)[idx].any()
        # the policy state (updates so far) of C's entries, as in the fresh cache
        seq.append(sorted(set((np.array(m.policy_state)[c_slots] & 0xFFFF).tolist())))
        seq_fresh.append(sorted(set((np.array(fresh.policy_state)[np.array(ff.active)] & 0xFFFF).tolist())))
    assert seq == seq_fresh
    assert seq[0] == [1] and seq[-1] == [10]


@pytest.mark.parametrize("n_vblocks", [1, 63, 64, 65, 5000, 300_000])
def test_requested_blocks_equal_one_flag_per_block(n_vblocks):
    """The two-level request flags (pages of 64 blocks, then blocks of the
    requested pages) give the same blocks in the same order as one flag per
    virtual block, for several viewers with invalid pixels and repeats."""
    from slc.osc.requests import requested_blocks
    rng = np.random.default_rng(n_vblocks)
    reqs = []
    for n in (0, 1, 257, 4096):
        vb = rng.integers(0, n_vblocks, n).astype(np.uint32)
        if n > 1:   # clusters, as pixels of one surface request neighbouring blocks
            vb[: n // 2] = np.minimum(vb[0] + rng.integers(0, 70, n // 2), n_vblocks - 1)
        valid = rng.random(n) < 0.8
        reqs.append((mi.Bool(valid), mi.UInt32(vb), None, None))
    flag = np.zeros(n_vblocks, bool)
    for valid, vb, _, _ in reqs:
        flag[np.array(vb)[np.array(valid)]] = True
    got = np.array(requested_blocks(reqs, n_vblocks))
    assert np.array_equal(got, np.flatnonzero(flag).astype(np.uint32))


@pytest.mark.fresh_process
def test_requested_blocks_build_no_kernel_for_one_page():
    """A frame whose pixels fall in one page of 64 blocks runs the kernels of
    a frame with many pages (a width-1 list would load as a scalar and build
    new kernels after warm-up)."""
    from slc.osc.requests import requested_blocks
    n = 100_000

    def run(vbs):
        # from a Python list: Dr.Jit may keep a numpy array's memory, whose alignment (the
        # allocator's state) changes the kernels (tests/test_megaviews_compile.py)
        vb = mi.UInt32([int(v) for v in vbs])
        return np.array(requested_blocks([(dr.full(mi.Bool, True, len(vbs)), vb, None, None)], n))

    rng = np.random.default_rng(1)
    for _ in range(2):   # warm-up: many pages
        run(rng.integers(0, n, 300))
    from slc.core.timing import KernelCounter
    with KernelCounter() as kc:
        kc.take()
        got = run([640, 641, 700, 641, 650, 640] * 50)          # one page (10), four blocks
        n_built = kc.take()
    assert list(got) == [640, 641, 650, 700]
    assert n_built == 0, f"{n_built} kernels built for a one-page frame"
