"""Error bounds of every method family on built-in scenes (slc/run/bounds.py, docs/error-bounds.md).

Each scene is measured once per module (every method and its ratio partner in this
process, the scene loaded once) and every (scene, method) row is judged against
tests/data/error_bounds.json by slc.run.bounds.compare, the comparison the recording
tool prints: a figure more than 10% worse fails, more than 10% better warns
(re-record with ``python tools/record_error_bounds.py``).
"""
import math
import warnings

import pytest

from slc.run import bounds

TABLE = bounds.load_table()
RECORDED = TABLE.get("scenes", {})

# deliberately worsened methods: (scene, spec as run, recorded row it must fail against)
WORSENED = [("atrium", "slc:rays_new=11", "slc"),         # a third of a new entry's update rays
            ("cornell", "restir:bias=off", "restir")]     # no bias correction


class BoundImproved(UserWarning):
    """A method's error fell more than the tolerance below its recorded bound."""


@pytest.fixture(scope="module")
def measured(request):
    """{scene: measure_scene(scene, methods)}, filled on first use of each scene, with the
    methods that this session's tests of the scene ask for (in a whole run every method of
    bounds.METHODS and the worsened runs, which share the scene's load and partner runs; a
    test run alone measures its method and its partner)."""
    wanted = {}
    for item in request.session.items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        if item.module is request.module and "scene" in params and "spec" in params:
            wanted.setdefault(params["scene"], set()).add(params["spec"])
    cache = {}

    def get(scene):
        if scene not in cache:
            order = bounds.methods_for(scene) + tuple(spec for s, spec, _ in WORSENED if s == scene)
            cache[scene] = bounds.measure_scene(scene, tuple(m for m in order if m in wanted.get(scene, ())))
        return cache[scene]
    return get


# ----------------------------------------------------------------------------- the table itself (fast)

def test_table_covers_every_family_and_scene():
    assert TABLE.get("config") == bounds.CONFIG.key(), \
        "tests/data/error_bounds.json was recorded at another configuration: python tools/record_error_bounds.py"
    assert list(RECORDED) == list(bounds.SCENES), "re-record: python tools/record_error_bounds.py"
    for scene, rows in RECORDED.items():
        for spec in bounds.methods_for(scene):
            row = rows.get(spec)
            assert row is not None, f"{scene}/{spec} not recorded"
            for k in bounds.FIGURES:
                assert math.isfinite(row[k]) and row[k] > 0.0, (scene, spec, k, row[k])
            if row["partner"] is not None:
                assert row["partner"] in rows
                for k in bounds.FIGURES:
                    assert math.isclose(row[f"{k}_ratio"], row[k] / rows[row["partner"]][k], rel_tol=1e-4)
    assert set(bounds.PARTNERS.values()) <= set(bounds.METHODS)
    for scene, specs in bounds.SCENE_METHODS.items():
        assert scene in bounds.SCENES and set(specs) <= set(bounds.METHODS), (scene, specs)


def test_judge_rule():
    rec = {"partner": "rt48", "flip": 0.1, "rel_mse": 1.0, "flip_ratio": 0.8, "rel_mse_ratio": 2.0}
    same = {**rec, "flip": 0.109, "rel_mse_ratio": 1.81}
    assert {f.verdict for f in bounds.compare_row("s", "m", rec, same)} == {"same"}
    worse = {**rec, "rel_mse": 1.11}
    assert [f.figure for f in bounds.compare_row("s", "m", rec, worse) if f.verdict == "worse"] == ["rel_mse"]
    better = {**rec, "flip_ratio": 0.71}
    assert [f.figure for f in bounds.compare_row("s", "m", rec, better) if f.verdict == "better"] == ["flip_ratio"]
    nan = {**rec, "flip": float("nan")}
    assert [f.figure for f in bounds.compare_row("s", "m", rec, nan) if f.verdict == "worse"] == ["flip"]
    moved = {**rec, "partner": "pt"}
    assert "worse" in {f.verdict for f in bounds.compare_row("s", "m", rec, moved)}
    assert {f.verdict for f in bounds.compare({}, {"s": {"m": rec}})} == {"new"}
    assert {f.verdict for f in bounds.compare({"s": {"m": rec}}, {"s": {}})} == {"missing"}


# ----------------------------------------------------------------------------- the bounds (rendered)

@pytest.mark.slow
@pytest.mark.parametrize("spec,scene", [(spec, scene) for scene in bounds.SCENES
                                        for spec in bounds.methods_for(scene)])
def test_error_within_recorded_bound(measured, scene, spec):
    row = measured(scene)[spec]
    findings = bounds.compare_row(scene, spec, RECORDED.get(scene, {}).get(spec), row)
    bad = [f.line() for f in findings if f.verdict in ("worse", "new", "missing")]
    assert not bad, "\n".join(bad)
    for f in findings:
        if f.verdict == "better":
            warnings.warn(BoundImproved(f"{f.line()}: re-record with python tools/record_error_bounds.py"))


@pytest.mark.slow
@pytest.mark.parametrize("scene,spec,as_recorded", WORSENED)
def test_worsened_method_fails_its_bound(measured, scene, spec, as_recorded):
    """The recorded bound of ``as_recorded`` rejects a deliberately worsened run of it
    (its ratios are to the partner of the same run)."""
    row = measured(scene)[spec]
    assert row["partner"] == RECORDED[scene][as_recorded]["partner"]
    worse = [f for f in bounds.compare_row(scene, as_recorded, RECORDED[scene][as_recorded], row)
             if f.verdict == "worse"]
    assert worse, f"{spec} on {scene} is within the bound of {as_recorded}: {row}"
