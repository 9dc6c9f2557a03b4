"""random-viewers: 1-16 viewers on uncorrelated paths (SLC paper, Figs. 12-13).

Every viewer starts looking at the scene's centre of interest and then moves
on its own random path; the average measured overlap is reported.

    slc run random-viewers --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "random-viewers"
FULL = dict(scenes=["atrium", "sponza"], viewers=[1, 2, 4, 8, 16], width=320, height=180, frames=24, warmup=4,
            eval_frames=[11, 23], eval_viewers=2)
QUICK = dict(scenes=["atrium"], viewers=[1, 4, 16], width=96, height=54, frames=8, warmup=3, eval_frames=[7],
             eval_viewers=2)
METHODS = ["slc", "rt48", "restir"]


def add_arguments(p):
    from slc.experiment import add_viewer_arguments
    add_viewer_arguments(p)


def run(opts):
    from slc import experiment as ex
    from slc import views

    rows, names, specs, cfg, out, counts = ex.viewer_count_experiment(
        opts, NAME, QUICK, FULL, METHODS, "random", views.random_viewers,
        lambda name, cfg: f"{name}: random viewers ({cfg.width}x{cfg.height})")
    md = ex.markdown_table(rows, ex.MULTI_COLUMNS) + "\n\n## Targets (ratios measured in this run)\n\n"
    n = max(counts)
    for name in names:
        get = ex.at_viewers(rows, name, n)
        if "slc" in get and "rt48" in get:
            a, b = get["slc"], get["rt48"]
            md += (f"- {name}, {n} viewers (measured overlap {a.get('measured_overlap', 0):.0f}%): slc is "
                   f"{ex.ratio(b['time_ms'], a['time_ms']):.2f}x faster than rt48 (target >= 2x); FLIP slc "
                   f"{a['flip']:.4f} vs rt48 {b['flip']:.4f} (target: lower)\n")
        if "slc" in get and "restir" in get:
            md += (f"- {name}, {n} viewers: slc is {ex.ratio(get['restir']['time_ms'], get['slc']['time_ms']):.2f}x "
                   f"faster than restir; FLIP slc {get['slc']['flip']:.4f} vs restir {get['restir']['flip']:.4f}\n")
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"viewers": counts})


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
