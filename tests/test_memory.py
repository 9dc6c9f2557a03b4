"""experiments/memory.py: the "active [MB]" column is computed from the
entries the viewers request, not a copy of "allocated"."""
import importlib.util
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from slc import methods

from slc.scene import random_walks, scenes, views
from slc.methods import FrameContext
from slc.run.pipeline import RunConfig
from slc.scene.gbuffer import frame_gbuffers
from slc.core.timing import StageTimer

ROOT = Path(__file__).resolve().parents[1]


def _memory_module():
    spec = importlib.util.spec_from_file_location("exp_memory", ROOT / "experiments" / "memory.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_entry_bytes_match_the_arrays():
    """Bytes per entry from the method's memory report equal the bytes of its
    arrays per entry of capacity: payload words and policy state measured from
    the storage arrays (width x 4 B), plus the cache's surface point and seen
    flag (16 B, slc.osc.cache.OnSurfaceCache.memory_bytes)."""
    pytest.importorskip("slc.osc")
    mem = _memory_module()
    sc = scenes.load("cornell")
    m = methods.create("slc", sc)
    vs = views.single(sc)
    for f in range(3):
        m.render(FrameContext(f), frame_gbuffers(sc, vs, f, 48, 27), StageTimer())
    cap = int(m.cache.capacity)
    arrays = (dr.width(m.storage) * 4 + dr.width(m.policy_state) * 4) / cap
    assert mem.entry_bytes_of(m) == pytest.approx(arrays + 16, rel=1e-9)
    assert mem.entry_bytes_of(methods.create("rt16", sc)) == 0.0


@pytest.mark.slow
def test_active_column_is_computed():
    """On the cornell box (48x27, 6 frames): active < allocated for slc (blocks
    are partly filled and the table is not active), equal for 1 and 2 viewers
    at 100% overlap (the same entries), larger for 2 random viewers than for
    one; no active figure for rt16 (its buffer is used in full)."""
    pytest.importorskip("slc.osc")
    mem = _memory_module()
    sc = scenes.load("cornell")
    cfg = RunConfig(width=48, height=27, frames=6, warmup=2, eval_frames=[], keep_images=False)
    cases = [(sc, "slc", views.overlap_rig(sc, 1, 1.0), {"rig": "overlap"}),
             (sc, "slc", views.overlap_rig(sc, 2, 1.0), {"rig": "overlap"}),
             (sc, "slc", random_walks.random_viewers(sc, 2), {"rig": "random"}),
             (sc, "rt16", views.overlap_rig(sc, 1, 1.0), {"rig": "overlap"})]
    rows = mem._run_cases(cases, cfg, "memory test", 0)
    one, two, rnd, rt = rows
    for r in (one, two, rnd):
        assert 0 < r["active_mb"] < r["memory_mb"], r
        assert r["entries_requested"] <= r["entries_allocated"], r
    assert one["active_mb"] < 0.95 * one["memory_mb"], one
    assert two["active_mb"] == pytest.approx(one["active_mb"], rel=0.01), (one, two)
    assert rnd["active_mb"] > one["active_mb"], (one, rnd)
    assert "active_mb" not in rt
    # not proportional to allocation: the ratios differ between the rigs
    assert not np.isclose(one["active_mb"] / one["memory_mb"], rnd["active_mb"] / rnd["memory_mb"], rtol=1e-3)
