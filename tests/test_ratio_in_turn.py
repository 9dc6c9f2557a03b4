"""`slc.run.experiment.ratio_in_turn`: two rigs timed again in alternating order, the ratio
taken within each repetition (the overlap experiment's target figure)."""
from types import SimpleNamespace

from slc.run import experiment, pipeline

from slc import methods
from slc.run.pipeline import RunConfig


def test_ratio_in_turn_alternates_and_divides_within_each_repetition(monkeypatch):
    calls = []
    # fake sequence runs: the load doubles every time (a drifting machine); a ratio of rows
    # run far apart would follow the drift, a ratio within each repetition only partly
    times = iter([10.0, 15.0, 30.0, 20.0, 40.0, 60.0])

    def fake_run(scene, m, viewers, cfg):
        calls.append((viewers, cfg.eval_frames, cfg.keep_images))
        return SimpleNamespace(time_ms=next(times), compiled_after_warmup=int(len(calls) == 4))

    monkeypatch.setattr(pipeline, "run_sequence", fake_run)
    monkeypatch.setattr(methods, "create", lambda spec, scene, seed=0: object())
    r = experiment.ratio_in_turn(None, "slc", "one", "many", RunConfig(frames=4, warmup=1), repeats=3)
    assert [c[0] for c in calls] == ["one", "many", "many", "one", "one", "many"]
    assert all(c[1] == [] and c[2] is False for c in calls)      # timing only
    assert r["base_ms"] == [10.0, 20.0, 40.0] and r["top_ms"] == [15.0, 30.0, 60.0]
    assert r["ratios"] == [1.5, 1.5, 1.5] and r["ratio"] == 1.5
    assert r["compiled_after_warmup"] == 1
