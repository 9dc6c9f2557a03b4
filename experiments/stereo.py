"""stereo: 16 single viewers, 8 stereo pairs, 16 stereo pairs (SLC paper, Figs. 15-16).

Eyes are 6.4 cm apart (in scene units); ``viewers`` counts images, so 16
stereo pairs are 32 viewers.

    slc run stereo --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.core.timing import stage_table  # noqa: E402 (after the path of a standalone run)
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "stereo"
FULL = dict(scenes=["atrium"], singles=16, pairs=[8, 16], width=320, height=180, frames=240, warmup=10,
            eval_frames=[239], eval_viewers=2)
QUICK = dict(scenes=["atrium"], singles=16, pairs=[8, 16], width=64, height=36, frames=20, warmup=10,
             eval_frames=[19], eval_viewers=1)
METHODS = ["slc", "adaptive", "rt48", "restir", "regir"]
STEADY_COLUMNS = [("scene", "scene"), ("method", "method"), ("rig", "rig"), ("viewers", "viewers"),
                  ("measured_overlap", "measured overlap %"), ("time_ms", "t [ms]"),
                  ("startup_ms", "start-up t [ms]"), ("compiled_after_warmup", "kernels after warm-up"),
                  ("recordings_after_warmup", "recordings after warm-up"),
                  ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]


def add_arguments(p):
    add_common_arguments(p)


def run(opts):
    pr, specs, names, cfg = ex.setup(opts, QUICK, FULL, METHODS)
    def cases(s):
        out = []
        for spec in specs:
            out.append((spec, views.independent(s, pr["singles"]), {"rig": "single", "pairs": 0}))
            out += [(spec, views.stereo(s, p), {"rig": "stereo", "pairs": p}) for p in pr["pairs"]]
        return out

    rows = ex.add_startup(ex.run_per_scene(names, cases, cfg, NAME, opts.seed))
    out = Path(opts.out) / NAME
    for name in names:
        plots.time_vs_viewers_plot(out / f"time_{name}.png", [r for r in rows if r["scene"] == name],
                                f"{name}: single viewers vs stereo pairs", group=("method", "rig"))
    md = ex.markdown_table(rows, STEADY_COLUMNS) + "\n\n## Targets (ratios measured in this run)\n\n"
    for name in names:
        for spec in specs:
            g = {(r["rig"], r["viewers"]): r for r in rows if r["scene"] == name and r["setting"] == spec}
            single = g.get(("single", pr["singles"]))
            for p in pr["pairs"]:
                st = g.get(("stereo", 2 * p))
                if single and st:
                    cache = spec in ("slc", "adaptive")
                    tgt = " (target <= 1.4x; paper 1.36x)" if p == 16 and cache else (
                        " (paper: about 0.74x)" if p == 8 and cache else "")
                    md += (f"- {name} {spec}: {p} stereo pairs ({2 * p} images) cost "
                           f"{ex.ratio(st['time_ms'], single['time_ms']):.2f}x of {pr['singles']} single viewers{tgt}\n")
    md += ("\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host "
           "time)\n\n" + stage_table(rows, ("scene", "label", "rig", "viewers")))
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"singles": pr["singles"], "pairs": pr["pairs"]})


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
