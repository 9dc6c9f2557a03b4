"""Frozen functions in animated scenes (``slc.core.freeze``, "Host data that changes between
calls"): a mesh moved by :meth:`slc.scene.scenes.Scene.set_frame` keeps a frozen function's
recording, and its replays see the moved geometry, bit for bit the traced function's values.

Before the moved meshes' vertex buffers were copied into memory that Dr.Jit allocates, a
buffer made from numpy was mapped: its alignment changed the recording's key from frame to
frame (a recording in every frame on the street), and a replay read the first frame's buffer
through the pointer a virtual call had captured (``compute_surface_interaction`` returned the
mesh where it stood when the function was recorded)."""
import gc

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import plane_under_rect_light
from slc.core import freeze as fz
from slc.core.freeze import FrozenFunction, device_array
from slc.scene.camera import FPS
from slc.scene.builder import translate


def _moving(frames_to_stop=12):
    def T(t):
        return translate([0.05 * min(t * FPS, frames_to_stop), 0.0, 0.0])
    return plane_under_rect_light(half=0.1, radiance=20.0, light_transform=T, name="freeze_moving")


def _probe(scene, shape_idx, b, o, d):
    """Points on a shape at barycentrics ``b`` (a virtual call reading its vertex buffer) and
    whether rays (o, d) hit anything (the acceleration structure)."""
    pi = dr.zeros(mi.PreliminaryIntersection3f)
    pi.t, pi.valid = mi.Float(1.0), mi.Bool(True)
    pi.prim_uv, pi.prim_index, pi.shape_index = mi.Point2f(b), mi.UInt32(0) * shape_idx, shape_idx
    pi.shape = dr.gather(mi.ShapePtr, scene.shapes_dr(), shape_idx)
    si = pi.compute_surface_interaction(mi.Ray3f(mi.Point3f(0.0), mi.Vector3f(0.0, 0.0, 1.0)), mi.RayFlags.All)
    return si.p, scene.ray_test(mi.Ray3f(o, d))


def test_device_array_is_a_copy():
    """A numpy array made into a Dr.Jit array maps its memory; ``device_array`` copies it."""
    a = np.arange(8, dtype=np.float32)
    mapped, copied = mi.Float(a), device_array(mi.Float, a)
    a[3] = 100.0
    assert float(mapped[3]) == 100.0            # the mapping (what device_array avoids)
    assert float(copied[3]) == 3.0 and np.array_equal(np.array(copied)[[0, 7]], [0.0, 7.0])


def test_frozen_function_follows_a_moving_mesh():
    """A light moved 5 cm a frame: one recording over 6 frames, and every replay returns the
    points on the light where it is now and the shadow rays it blocks now, as the traced
    function does (before: a recording in most frames, and replays that read the first
    frame's vertex buffer)."""
    gc.collect()
    sc = _moving()
    ms = sc.mi_scene
    k = [i for i, sh in enumerate(ms.shapes()) if sh.id() == sc.animated[0].shape_id][0]
    idx, b = mi.UInt32([k, k, k]), mi.Point2f([0.2, 0.5, 0.1], [0.3, 0.1, 0.6])
    # rays up from the plane at x = 0.12: blocked by the light once it moved 2.5 cm or more
    o = mi.Point3f([0.12, 0.12, 0.12], [0.01, 0.01, 0.01], [0.0, 0.05, -0.05])
    d = mi.Vector3f(0.0, 1.0, 0.0)
    f = FrozenFunction(_probe)
    hits = []
    for frame in range(6):
        sc.set_frame(frame)
        p, hit = f(ms, idx, b, o, d)
        p_ref, hit_ref = _probe(ms, idx, b, o, d)
        assert np.array_equal(np.array(p), np.array(p_ref)), frame
        assert np.array_equal(np.array(hit), np.array(hit_ref)), frame
        hits.append(bool(np.array(hit)[0]))
    assert f.frozen and f.n_recordings == 1, f.n_recordings
    # the light spans x in [-0.1, 0.1] + 0.05 frame: over the rays in frames 1-4 (the replays saw it move)
    assert hits == [False, True, True, True, True, False], hits


def test_recordings_are_counted():
    """``recordings()`` counts the recordings of every frozen function: a call with a new
    input type records once more, a replay does not."""
    f = FrozenFunction(lambda x: x * 2)
    n0 = fz.recordings()
    f(dr.arange(mi.Float, 4))
    f(dr.arange(mi.Float, 5))
    assert fz.recordings() - n0 == 1
    f(dr.arange(mi.UInt32, 5))
    assert fz.recordings() - n0 == 2


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["slc", "adaptive"])
def test_methods_frozen_in_an_animated_scene(spec):
    """slc and adaptive on a moving light, 10 frames at 40x30: the same images bit for bit
    as with every frozen function traced, no recording after the third frame
    (``recordings_after_warmup`` 0) and every frozen function still frozen."""
    from slc.methods import create
    from slc.run.pipeline import RunConfig, run_sequence
    from slc.scene.views import single

    sc = _moving()
    cfg = RunConfig(width=40, height=30, frames=10, warmup=3, eval_frames=[], measure_overlap=False)

    made = []
    init = FrozenFunction.__init__

    def run(freeze):
        def tracked(self, fn, freeze_=True, *a, **k):
            init(self, fn, freeze_ and freeze, *a, **k)
            made.append(self)
        FrozenFunction.__init__ = tracked
        try:
            m = create(spec, sc, seed=0)
            return m, run_sequence(sc, m, single(sc), cfg)
        finally:
            FrozenFunction.__init__ = init

    _, ref = run(False)
    made.clear()
    m, res = run(True)
    for f, x in res.last.items():
        assert np.array_equal(np.asarray(x), np.asarray(ref.last[f])), f
    assert res.recordings_after_warmup == 0, [fr["recordings"] for fr in res.frames_ms]
    called = [ff for ff in made if ff.calls > 0]
    assert called and all(ff.frozen for ff in called), [(ff.fn.__name__, ff.n_recordings) for ff in made]
