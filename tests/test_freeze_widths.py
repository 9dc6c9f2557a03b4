"""A frozen function whose lane count happens to equal the width of
another input (an array of the scene) is not recorded again (``slc.core.freeze``:
such a call runs on a free width, its extra lanes copies of the last one).

Dr.Jit keys a recording on which inputs share a width; the atrium's active
entries once numbered 2,880, the length of one mesh's index buffer, and the
cone update was recorded again in a timed frame."""
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import slc.core.backend  # noqa: F401
from slc.core.freeze import FrozenFunction
from slc.core.leaves import input_widths as _input_widths


def _scene():
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "ball": {"type": "obj", "filename": _sphere_obj()},
        "light": {"type": "point", "position": [0, 0, 2], "intensity": {"type": "rgb", "value": 1.0}},
    })


def _sphere_obj(path=[]):
    """A small UV sphere written once (its face count sets the colliding width)."""
    if path:
        return path[0]
    import tempfile
    n_u, n_v = 12, 6
    lines = []
    for j in range(n_v + 1):
        th = np.pi * j / n_v
        for i in range(n_u):
            ph = 2 * np.pi * i / n_u
            lines.append(f"v {np.sin(th) * np.cos(ph):.6f} {np.cos(th):.6f} {np.sin(th) * np.sin(ph):.6f}")
    for j in range(n_v):
        for i in range(n_u):
            a, b = j * n_u + i + 1, j * n_u + (i + 1) % n_u + 1
            c, d = a + n_u, b + n_u
            lines += [f"f {a} {b} {d}", f"f {a} {d} {c}"]
    f = tempfile.NamedTemporaryFile("w", suffix=".obj", delete=False)
    f.write("\n".join(lines) + "\n")
    f.close()
    path.append(f.name)
    return f.name


def _kernel(scene, table, x, k):
    # per lane: a gather from a table that is not per lane, and the lane's own key
    return dr.gather(mi.Float, table, k % 7) + 2.0 * x, k + 1


def _calls(ff, scene, widths):
    table = dr.arange(mi.Float, 7) * 0.5
    outs = []
    for n in widths:
        x = dr.arange(mi.Float, n) * 0.25
        k = dr.arange(mi.UInt32, n) * 3
        outs.append([np.array(v) for v in ff(scene, table, x, k)])
    return outs


@pytest.mark.fresh_process
def test_colliding_lane_count_is_not_recorded_again():
    scene = _scene()
    taken = _input_widths(scene)
    ball = [s for s in scene.shapes() if s.face_count() == 144][0]
    w = 3 * int(ball.face_count())         # the ball's index buffer: 432 lanes
    assert w in taken
    widths = [500, 501, w, 503, w, 505]

    plain = FrozenFunction(_kernel)                          # no lanes declared: records again at w
    _calls(plain, scene, widths)
    guarded = FrozenFunction(_kernel, lanes=(2, 3))
    outs = _calls(guarded, scene, widths)

    assert plain.n_recordings > guarded.n_recordings, (plain.n_recordings, guarded.n_recordings)
    assert guarded.n_recordings <= 2 and guarded.frozen
    assert guarded.padded_calls == 2                         # both calls at width w ran padded
    ref = _calls(FrozenFunction(_kernel, freeze=False), scene, widths)
    for a, b in zip(outs, ref):                              # padded lanes cut: the same values
        for u, v in zip(a, b):
            assert u.shape == v.shape and np.array_equal(u, v)


def test_free_width_skips_every_taken_width():
    scene = _scene()
    ff = FrozenFunction(_kernel, lanes=(2, 3))
    table = dr.arange(mi.Float, 7)
    taken = _input_widths(scene) | {7, 0, 1}
    for n in (1, 7, 8, max(x for x in taken if x < 5000)):
        w = ff.free_width(n, (scene, table, None, None))
        assert w >= n and w not in taken
        assert all(m in taken for m in range(n, w))          # the first free width from n


def test_cone_update_declares_its_lanes():
    """The cone update's per-lane arguments are exactly those of one width per
    call (the lane order and the batch of per-entry inputs), so that padding
    touches nothing else."""
    import inspect

    from slc.methods.cones.update_kernel import ConeUpdate, _update_kernel
    names = list(inspect.signature(_update_kernel).parameters)
    lanes = ConeUpdate().lanes
    assert [names[i] for i in lanes] == ["order", "batch"]


@dataclass
class _Lanes:
    x: mi.Float
    k: mi.UInt32


def _kernel_named(scene, table, lanes: _Lanes):
    return _kernel(scene, table, lanes.x, lanes.k)


@pytest.mark.fresh_process
def test_lanes_named_by_parameter_may_be_a_structure():
    """Per-lane arguments are named by the function's parameters; a dataclass argument
    is per lane in every field: a colliding lane count runs padded, values unchanged."""
    scene = _scene()
    w = 3 * 144                                              # the ball's index buffer
    ff = FrozenFunction(_kernel_named, lanes=("lanes",))
    assert ff.lanes == (2,)
    table = dr.arange(mi.Float, 7) * 0.5
    for n in (500, w):
        x, k = dr.arange(mi.Float, n) * 0.25, dr.arange(mi.UInt32, n) * 3
        got, ref = ff(scene, table, _Lanes(x, k)), _kernel(scene, table, x, k)
        assert all(np.array_equal(np.array(u), np.array(v)) for u, v in zip(got, ref))
    assert ff.padded_calls == 1
    with pytest.raises(ValueError, match="no parameter nope"):
        FrozenFunction(_kernel, lanes=("nope",))


def _kernel_pair(scene, table, x, y):
    return dr.gather(mi.Float, table, mi.UInt32(y) % 7) + x * y


@pytest.mark.fresh_process
def test_literal_and_shared_lane_inputs_record_once():
    """Per-lane inputs that are literals in some calls (a field of the entries' interactions
    that is constant), or the same variable as another input in some calls and not in others,
    record once when their lanes are declared (each leaf made an array of its own); without,
    Dr.Jit records again as the pattern changes. Values as traced."""
    scene = _scene()
    table = dr.arange(mi.Float, 7) * 0.5

    def calls(ff):
        out = []
        for n, shared, literal in ((500, False, False), (503, True, False), (506, False, True), (509, True, True),
                                   (512, False, False)):
            x = dr.arange(mi.Float, n) * 0.25
            y = dr.full(mi.Float, 2.0, n) if literal else (x if shared else dr.arange(mi.Float, n) * 0.5)
            out.append(np.array(ff(scene, table, x, y)))
        return out

    plain, guarded = FrozenFunction(_kernel_pair), FrozenFunction(_kernel_pair, lanes=(2, 3))
    calls(plain)
    outs = calls(guarded)
    assert guarded.n_recordings == 1 and guarded.frozen, guarded.n_recordings
    assert plain.n_recordings > 1, plain.n_recordings
    for a, b in zip(outs, calls(FrozenFunction(_kernel_pair, freeze=False))):
        assert np.array_equal(a, b)


def _kernel_table(shape, table, k):
    # per lane: a lookup into a table whose length changes from call to call (the entries'
    # frames of the cones' shading); the shapes bring the scene's arrays in through the registry
    return dr.gather(mi.Float, table, k) + dr.select(shape != None, 1.0, 0.0)  # noqa: E711


@pytest.mark.fresh_process
def test_table_of_a_colliding_length_is_not_recorded_again():
    """A table argument whose length equals the width of an array of the scene (the ball's
    index buffer, reached through the shapes) is padded to a free width when declared in
    ``tables``: one recording, values as traced; undeclared, Dr.Jit records again."""
    scene = _scene()
    w = 3 * 144                                              # the ball's index buffer
    assert w in _input_widths(scene)
    shapes = dr.gather(mi.ShapePtr, scene.shapes_dr(), dr.arange(mi.UInt32, 500) % len(scene.shapes()))
    k = dr.arange(mi.UInt32, 500) % 300

    def calls(ff):
        return [np.array(ff(shapes, dr.arange(mi.Float, m) * 0.5, k)) for m in (400, 401, w, 403, w, 405)]

    plain = FrozenFunction(_kernel_table)
    calls(plain)
    guarded = FrozenFunction(_kernel_table, tables=("table",), scene=scene)
    outs = calls(guarded)
    assert plain.n_recordings > 1, plain.n_recordings
    assert guarded.n_recordings == 1 and guarded.frozen, guarded.n_recordings
    assert guarded.padded_calls == 2                         # both calls with a table of w elements
    for a, b in zip(outs, calls(FrozenFunction(_kernel_table, freeze=False))):
        assert np.array_equal(a, b)


def test_cone_shading_declares_its_table():
    """The cones' shading reads the entries' frames through each pixel's index: that argument,
    and only that one, is its table."""
    import inspect

    from slc.lib.cones.shading import ConeShading, shade_kernel
    names = list(inspect.signature(shade_kernel).parameters)
    assert [names[i] for i in ConeShading(3).tables] == ["entry_frames"]
