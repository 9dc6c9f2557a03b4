"""On-surface cache fed by the frame's layered G-buffer: the requests of all
viewers in one launch give the same frame as unattached G-buffers (laid out
by the cache), the overlap measure without atomics equals the one counted
from the viewers' slots, and the frozen entry interactions are the traced
ones bit for bit."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.scene import gbuffer
from slc.scene.gbuffer import render_gbuffer
from slc.osc import INVALID, OnSurfaceCache
from slc.osc.surface import EntryInteractions
from slc.scene.camera import Camera
from slc.scene.scenes import load

W, H = 64, 40


def _gb(scene, o, t, fov=45.0):
    return render_gbuffer(scene, Camera(np.array(o, float), np.array(t, float), fov=fov), W, H)


def _cams(n):
    return [([0.3 * k - 0.4, 1.0 + 0.05 * k, 3.4 - 0.2 * k], [0.1 * k, 1.0, 0.0]) for k in range(n)]


@pytest.fixture(scope="module")
def cornell():
    return load("cornell")


@pytest.fixture(scope="module")
def sphere_scene():
    """An analytic sphere (Mitsuba's ``sphere`` shape, not a mesh) on a floor."""
    import types
    sc = mi.load_dict({
        "type": "scene",
        "ball": {"type": "sphere", "center": [0, 0, 0], "radius": 1.0,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, -1, 0])
                  .rotate([1, 0, 0], -90).scale(2.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
        "light": {"type": "point", "position": [0, 3, 0], "intensity": {"type": "rgb", "value": [5, 5, 5]}},
    })
    return types.SimpleNamespace(mi_scene=sc)


def _frame(fr):
    out = [np.array(fr.active), np.array(fr.is_new), np.array(fr.seed_slot), np.array(fr.keys),
           np.array(fr.si.p), np.array(fr.si.n)]
    return out + [np.array(x) for x in fr.pixel_slot] + [np.array(x) for x in fr.pixel_index]


def test_layered_requests_equal_unattached(cornell):
    """Three frames of three viewers: a cache fed the attached layers and one fed
    the same G-buffers without them (laid out inside begin_frame) give the same
    frames; the per-viewer slots are the layered ones' slices."""
    c1, c2 = OnSurfaceCache(cornell), OnSurfaceCache(cornell)
    for f in range(3):
        gbs = [_gb(cornell, np.array(o) + [0.1 * f, 0, 0], t) for o, t in _cams(3)]
        plain = [gbuffer.GBuffer(**{k: v for k, v in vars(g).items() if k not in ("layers", "layer")}) for g in gbs]
        lay = gbuffer.attach_layers(gbs)
        assert lay is not None and all(g.layers is lay for g in gbs) and all(g.layers is None for g in plain)
        a, b = c1.begin_frame(f, gbs), c2.begin_frame(f, plain)
        for x, y in zip(_frame(a), _frame(b)):
            assert np.array_equal(x, y)
        ls = np.array(a.layer_slot)
        for v, off in enumerate(lay.offsets):
            assert np.array_equal(ls[off:off + lay.sizes[v]], np.array(a.pixel_slot[v]))
        assert c1.stats() == c2.stats()


def test_overlap_measure_equals_slot_sets(cornell):
    """The share of active entries that two or more viewers asked for, from the
    plain-scatter owner test, equals the one counted from the viewers' slot sets."""
    cache = OnSurfaceCache(cornell)
    gbs = [_gb(cornell, o, t) for o, t in _cams(4)]
    gbuffer.attach_layers(gbs)
    fr = cache.begin_frame(0, gbs)
    sets = [set(np.array(s)[np.array(s) != INVALID].tolist()) for s in fr.pixel_slot]
    count = {}
    for s in sets:
        for x in s:
            count[x] = count.get(x, 0) + 1
    act = np.array(fr.active)
    assert sorted(count) == act.tolist()
    shared = sum(1 for c in count.values() if c > 1)
    assert 0 < shared < len(act)
    assert cache.stats()["measured_overlap"] == pytest.approx(100.0 * shared / len(act), abs=1e-9)
    assert cache.stats()["pixels"] == sum(int(np.array(g.valid).sum()) for g in gbs)


@pytest.mark.fresh_process
@pytest.mark.slow
@pytest.mark.parametrize("scene_name", ["cornell", "sphere"])
def test_frozen_interactions_equal_traced(scene_name, cornell, sphere_scene):
    """The frozen entry interactions are the traced ones bit for bit (meshes and
    an analytic sphere), for active lists of changing length, recorded once."""
    scene = cornell if scene_name == "cornell" else sphere_scene
    cache = OnSurfaceCache(scene)
    frozen = EntryInteractions()
    o = [0, 1, 3.4] if scene_name == "cornell" else [0, 0.5, 3.5]
    t = [0, 1, 0] if scene_name == "cornell" else [0, 0, 0]
    for f in range(4):
        fr = cache.begin_frame(f, [_gb(scene, np.array(o) * (1.0 - 0.1 * f), t, fov=45.0 - 5 * f)])
        isl = cache.pool.entry_texels(fr.active)[0]
        a = cache.points.interactions(fr.active, isl)
        b = cache.points.interactions(fr.active, isl, frozen)
        for k in ("p", "n", "uv", "dp_du", "dp_dv", "t", "prim_index"):
            assert np.array_equal(np.array(getattr(a, k)), np.array(getattr(b, k))), k
        for k in ("s", "t", "n"):
            assert np.array_equal(np.array(getattr(a.sh_frame, k)), np.array(getattr(b.sh_frame, k))), k
    assert frozen.n_recordings == 1 and frozen.frozen
    if scene_name == "sphere":
        assert cache.layout.has_analytic
