"""random-viewers: 1-16 viewers on uncorrelated paths (SLC paper, Figs. 12-13).

Every viewer starts at its own point looking towards the scene's centre of
interest and then walks its own random route (``slc.scene.random_walks.random_viewers``).
Each row reports the overlap at the start (``overlap_start``, frame 0), over
the rig's first 4 s (``overlap_4s``, every 0.5 s) and over the timed frames
(``measured_overlap``); the paper's regime is about 50% at the start and
about 20% on average.

    slc run random-viewers --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.core.timing import stage_table  # noqa: E402 (after the path of a standalone run)
from slc.run import experiment as ex  # noqa: E402
from slc.run.experiment import add_viewer_arguments  # noqa: E402
from slc.scene.gbuffer import frame_gbuffers  # noqa: E402
from slc.scene import random_walks, views  # noqa: E402

NAME = "random-viewers"
FULL = dict(scenes=["atrium", "sponza"], viewers=[1, 4, 16], width=320, height=180, frames=240, warmup=10,
            eval_frames=[79, 239], eval_viewers=2)
QUICK = dict(scenes=["atrium"], viewers=[1, 4, 16], width=96, height=54, frames=24, warmup=10, eval_frames=[23],
             eval_viewers=2)
OVERLAP_FRAMES = list(range(0, 241, 30))   # the rig's overlap over its first 4 s (60 Hz), every 0.5 s
METHODS = ["slc", "adaptive", "rt48", "restir", "regir"]
TARGET = 6.0        # rt48's time over a cache method's at the most viewers (at a lower FLIP)
CACHES = ("slc", "adaptive")


def add_arguments(p):
    add_viewer_arguments(p)


def run(opts):
    overlaps = {}

    def make(s, n):
        vs = random_walks.random_viewers(s, n, seed=opts.seed)
        if n > 1 and (s.name, n) not in overlaps:
            w, h = opts_res(opts)
            m = [views.measure_overlap(frame_gbuffers(s, vs, f, w, h)) for f in OVERLAP_FRAMES]
            overlaps[(s.name, n)] = (m[0], sum(m) / len(m))
        return vs

    rows, names, specs, cfg, out, counts = ex.viewer_count_experiment(
        opts, NAME, QUICK, FULL, METHODS, "random", make,
        lambda name, cfg: f"{name}: random viewers ({cfg.width}x{cfg.height})")
    for r in rows:
        if (r["scene"], r["viewers"]) in overlaps:
            r["overlap_start"], r["overlap_4s"] = overlaps[(r["scene"], r["viewers"])]
    ex.add_startup(rows)
    cols = ex.MULTI_COLUMNS[:4] + [("overlap_start", "overlap at start %"), ("overlap_4s", "overlap over 4 s %"),
                                   ("measured_overlap", "overlap in timed frames %"), ("time_ms", "t [ms]"),
                                   ("startup_ms", "start-up t [ms]"), ("compiled_after_warmup", "kernels after warm-up"),
                                   ("recordings_after_warmup", "recordings after warm-up")] + ex.MULTI_COLUMNS[6:]
    md = ex.markdown_table(rows, cols) + "\n\n## Targets (ratios measured in this run)\n\n"
    n = max(counts)
    for name in names:
        get = ex.at_viewers(rows, name, n)
        for c in [k for k in CACHES if k in get]:
            if "rt48" in get:
                a, b = get[c], get["rt48"]
                md += (f"- {name}, {n} viewers (overlap {a.get('overlap_start', 0):.0f}% at the start, "
                       f"{a.get('overlap_4s', 0):.0f}% over 4 s; paper about 50% and 20%): {c} is "
                       f"{ex.ratio(b['time_ms'], a['time_ms']):.2f}x faster than rt48 (target >= {TARGET:g}x); "
                       f"FLIP {c} {a['flip']:.4f} vs rt48 {b['flip']:.4f} (target: lower)\n")
            if "restir" in get:
                md += (f"- {name}, {n} viewers: {c} is {ex.ratio(get['restir']['time_ms'], get[c]['time_ms']):.2f}x "
                       f"faster than restir; FLIP {c} {get[c]['flip']:.4f} vs restir {get['restir']['flip']:.4f}\n")
    md += ("\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host time)\n\n"
           + stage_table(rows, ("scene", "label", "viewers")))
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"viewers": counts})


def opts_res(opts):
    """The run's resolution (the preset's unless --res)."""
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    return pr["width"], pr["height"]


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
