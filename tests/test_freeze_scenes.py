"""Frozen functions (``slc.core.freeze.FrozenFunction``) record as often in a
process that loaded another scene before as in a fresh one.

Two causes were found and fixed: a released scene's emitters and emissive shapes
stayed alive in the per-scene tables (emitter table, BSDF flags), hence in Mitsuba's
object registry, which every frozen function traverses with its inputs; and a
replayed recording returned its literal outputs (the zero ``dn_du`` of a flat mesh's
interaction) with the width of the recording, which made the next frozen function's
input key change whenever the first one recorded anew."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import run_case
from slc.core.freeze import FrozenFunction

pytestmark = pytest.mark.slow      # fresh interpreters counting kernels

# One experiment-like process: scenes in turn (each released before the next, as the
# experiment runner does), every method with frozen functions on each, the
# recordings of every frozen function counted.
_RUN = """
import gc, json, sys
sys.path.insert(0, "tests")
import slc.core.backend  # noqa: F401
import slc.core.freeze as SF
from slc.methods import FrameContext, create
from slc.scene.gbuffer import frame_gbuffers
from slc.scene.scenes import load
from slc.core.timing import NullTimer
from slc.scene.views import single
from test_cones_update_freeze import _growing_scene
made = []
_init = SF.FrozenFunction.__init__
def init(self, *a, **k):
    _init(self, *a, **k)
    made.append(self)
SF.FrozenFunction.__init__ = init
scenes, methods, frames = sys.argv[1].split(","), sys.argv[2].split(","), int(sys.argv[3])
out = []
for name in scenes:
    sc = _growing_scene() if name == "growing" else load(name)
    for spec in methods:
        m = create(spec, sc)
        for f in range(frames):
            m.render(FrameContext(f), frame_gbuffers(sc, single(sc), f, 40, 30), NullTimer())
        for i, ff in enumerate(made):
            out.append(dict(scene=name, method=spec, fn=f"{i}:{type(ff).__name__}:{ff.fn.__name__}",
                            calls=ff.calls, recs=ff.n_recordings, frozen=ff.frozen, max=ff.max_recordings))
        made.clear()
        del m
        gc.collect()
    del sc
    gc.collect()
print("RESULT " + json.dumps(dict(runs=out)))
"""

def _by_fn(runs, scene):
    return {(r["method"], r["fn"]): r for r in runs if r["scene"] == scene}


@pytest.mark.parametrize("second,methods,n_fns", [("growing", "slc,adaptive,sh,pt", 12), ("cornell", "osc-gi", 9)],
                         ids=["growing-cache", "osc-gi"])
def test_two_scenes_in_turn_record_as_in_fresh_processes(second, methods, n_fns):
    """atrium, then a second scene (one whose cache grows, from
    tests/test_cones_update_freeze.py; or the cornell box), in one process, 16
    frames of each frozen method: every frozen function of the second scene
    records exactly as often as in a process that never loaded the atrium, stays
    frozen, and stays within its policy's bound; so do those of the first scene
    (``n_fns``: the frozen functions the methods make: osc-gi's 3 primary, 5 secondary
    and the entries' interactions)."""
    both = run_case(_RUN, "atrium," + second, methods, 16)["runs"]
    fresh = run_case(_RUN, second, methods, 16)["runs"]
    after, alone = _by_fn(both, second), _by_fn(fresh, second)
    assert set(after) == set(alone) and len(alone) == n_fns, sorted(alone)
    # osc-gi's cached direct light kernel is made but not called with direct=rt (its default)
    assert sum(r["calls"] > 0 for r in after.values()) >= n_fns - 1
    for k, r in after.items():
        assert r["calls"] == alone[k]["calls"] and r["frozen"] and r["recs"] <= r["max"], r
        assert r["recs"] == alone[k]["recs"], (r, alone[k])
    first = _by_fn(both, "atrium")
    assert set(first) == set(alone), sorted(first)
    for r in first.values():
        assert r["frozen"] and r["recs"] <= r["max"], r


_REGISTRY = """
import gc, json, sys
sys.path.insert(0, "tests")
import drjit as dr
import mitsuba as mi
import slc.core.backend  # noqa: F401
from slc.scene import scenes
from helpers import plane_under_rect_light
if sys.argv[1]:
    scenes.load(sys.argv[1])          # loaded and released
gc.collect()
sc = plane_under_rect_light(name="after")
ids = dr.reinterpret_array(mi.UInt32, sc.mi_scene.emitters_dr())
print("RESULT " + json.dumps(dict(ids=[int(i) for i in ids])))
"""


def test_released_scene_leaves_mitsubas_registry():
    """A scene loaded and released frees its objects: the registry ids of a scene
    built afterwards are those of a fresh process (Mitsuba hands out the lowest free
    id). Before, the atrium's 4 area emitters stayed registered (held by the emitter
    table's cache) and the next scene's emitter got id 5."""
    after = run_case(_REGISTRY, "atrium")["ids"]
    fresh = run_case(_REGISTRY, "")["ids"]
    assert after == fresh, (after, fresh)


def _point(x):
    # the y component is a literal (zeros) of the width seen when recording
    return mi.Point3f(x + 1.0, dr.zeros(mi.Float, dr.width(x)), x * 2.0)


@pytest.mark.fresh_process
def test_replayed_literal_outputs_take_the_call_width():
    """Dr.Jit 1.5 returns a replayed recording's literal outputs with the width they
    had when recorded (5 lanes here when called with 7 or 9); FrozenFunction gives
    them the width of the other leaves, as the traced function would."""
    raw = dr.freeze(_point)
    raw(dr.arange(mi.Float, 5))
    stale = raw(dr.arange(mi.Float, 7))
    f = FrozenFunction(_point)
    for n in (5, 7, 9, 7):
        p = f(dr.arange(mi.Float, n))
        assert [dr.width(c) for c in p] == [n] * 3, (n, [dr.width(c) for c in p])
        ref = _point(dr.arange(mi.Float, n))
        assert np.array_equal(np.array(p), np.array(ref)), n
    assert f.frozen and f.n_recordings <= 2, f.n_recordings
    # the Dr.Jit behaviour this works around (if this fails, Dr.Jit fixed it)
    assert dr.width(stale.y) == 5


_ALIVE = """
import json, sys
sys.path.insert(0, "tests")
import drjit as dr
import mitsuba as mi
import slc.core.backend  # noqa: F401
import test_cones_update_freeze as F
from slc.scene import scenes
keep = scenes.load("atrium") if sys.argv[1] else None      # alive during the run
sizes = set()
for sh in (keep.mi_scene.shapes() if keep else []):
    params = mi.traverse(sh)
    for k in params.keys():
        try:
            sizes.add(dr.width(params[k]))
        except Exception:       # parameters that cannot be read alone
            pass
sizes = sorted(sizes)
sc = F._growing_scene()
m, _, _, active = F._run(sc, F.single(sc), 24, freeze=True, grow=True)
print("RESULT " + json.dumps(dict(recs=m.recordings_per_frame, active=active, sizes=sizes,
                                  frozen=m._cone_update.frozen)))
"""


def test_update_with_another_scene_alive_records_once_per_size_coincidence():
    """What is left (see slc/core/freeze.py): with the atrium alive during the run, the
    frozen update's key also holds the size classes of the atrium's arrays, so a
    frame whose entry count equals one of their sizes (486: a lamp sphere's vertex
    coordinates) records once more; later frames with the same count replay it.
    Recordings: those of a fresh process plus one per distinct coinciding count,
    still frozen."""
    alive = run_case(_ALIVE, "atrium")
    fresh = run_case(_ALIVE, "")
    assert alive["active"] == fresh["active"]
    hits = {n for n in alive["active"] if n in set(alive["sizes"])}
    assert len(hits) >= 1, (alive["active"], alive["sizes"])     # the case this test is about
    assert alive["frozen"] and fresh["frozen"]
    assert alive["recs"][-1] == fresh["recs"][-1] + len(hits), (alive["recs"], fresh["recs"], hits)
