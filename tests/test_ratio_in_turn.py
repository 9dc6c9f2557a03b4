"""`slc.run.experiment.ratio_in_turn`: two rigs timed again in alternating order, the ratio
taken within each repetition (the overlap experiment's target figure)."""
from types import SimpleNamespace

from slc.run import experiment, pipeline
from slc.scene import gbuffer

from slc import methods
from slc.run.pipeline import RunConfig


def test_ratio_in_turn_alternates_and_divides_within_each_repetition(monkeypatch):
    calls = []
    # fake sequence runs: the load doubles every time (a drifting machine); a ratio of rows
    # run far apart would follow the drift, a ratio within each repetition only partly
    times = iter([10.0, 15.0, 30.0, 20.0, 40.0, 60.0])

    def fake_run(scene, m, viewers, cfg):
        calls.append((viewers, cfg.eval_frames, cfg.keep_images))
        return SimpleNamespace(time_ms=next(times), compiled_after_warmup=int(len(calls) == 4),
                               recordings_after_warmup=0)

    monkeypatch.setattr(experiment, "run_sequence", fake_run)
    monkeypatch.setattr(methods, "create", lambda spec, scene, seed=0: object())
    r = experiment.ratio_in_turn(None, "slc", "one", "many", RunConfig(frames=4, warmup=1), repeats=3)
    assert [c[0] for c in calls] == ["one", "many", "many", "one", "one", "many"]
    assert all(c[1] == [] and c[2] is False for c in calls)      # timing only
    assert r["base_ms"] == [10.0, 20.0, 40.0] and r["top_ms"] == [15.0, 30.0, 60.0]
    assert r["ratios"] == [1.5, 1.5, 1.5] and r["ratio"] == 1.5
    assert r["compiled_after_warmup"] == 1


def test_run_sequence_walks_the_camera_path_in_steps(monkeypatch):
    """``frame_step``: frame i of a run is ``start_frame + i * frame_step`` (the crc
    experiment's moving volume walks 20 path frames per rendered frame)."""
    seen = []
    monkeypatch.setattr(gbuffer, "frame_gbuffers", lambda scene, viewers, f, w, h: seen.append(f) or [])

    class Fake:
        name, label, output = "fake", None, "direct"

        def reset(self):
            pass

        def render(self, ctx, gbs, timer):
            assert ctx.frame == seen[-1]
            return []

        def stats(self):
            return {}

        def memory_bytes(self):
            return 0
    cfg = RunConfig(frames=3, warmup=0, start_frame=5, frame_step=20, eval_frames=[], keep_images=False,
                    measure_overlap=False)
    pipeline.run_sequence(None, Fake(), [], cfg)
    assert seen == [5, 25, 45]
