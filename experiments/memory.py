"""memory: method memory against the number of viewers (SLC paper, Fig. 14).

Cache methods report allocated blocks x packed bytes per entry ("allocated")
and the entries requested this frame x bytes ("active"); per-viewer methods
report their buffers (ReSTIR: reservoirs, bytes per pixel x pixels x
viewers; RT-N: its output buffer). Scene data, G-buffers and output images
common to all methods are excluded. Rigs: 100% overlap and random viewers.

    slc run memory --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "memory"
FULL = dict(scenes=["atrium"], viewers=[1, 2, 4, 8, 16], width=320, height=180, frames=12, warmup=2,
            eval_frames=[], eval_viewers=1)
QUICK = dict(scenes=["atrium"], viewers=[1, 4, 16], width=96, height=54, frames=6, warmup=2, eval_frames=[],
             eval_viewers=1)
METHODS = ["slc", "rt16", "rt48", "restir"]


def add_arguments(p):
    from slc.experiment import add_viewer_arguments
    add_viewer_arguments(p)


def run(opts):
    from slc import experiment as ex
    from slc import views

    pr, specs, names, cfg = ex.setup(opts, QUICK, FULL, METHODS)
    counts = opts.viewers or pr["viewers"]
    def cases(s):
        return [c for spec in specs for n in counts for c in (
            (spec, views.overlap_rig(s, n, 1.0), {"rig": "overlap", "overlap": 100}),
            (spec, views.random_viewers(s, n), {"rig": "random"}))]

    rows = ex.run_per_scene(names, cases, cfg, NAME, opts.seed)
    for r in rows:
        if "active_mb" in r:
            continue
        r["active_mb"] = r.get("memory_active_mb", r["memory_mb"])
    out = Path(opts.out) / NAME
    for name in names:
        for rig in ("overlap", "random"):
            ex.time_vs_viewers_plot(out / f"memory_{name}_{rig}.png",
                                    [r for r in rows if r["scene"] == name and r["rig"] == rig],
                                    f"{name}: memory, {rig} rig", y="memory_mb", ylabel="memory [MB]")
    cols = [("scene", "scene"), ("method", "method"), ("rig", "rig"), ("viewers", "viewers"),
            ("measured_overlap", "measured overlap %"), ("memory_mb", "allocated [MB]"), ("active_mb", "active [MB]"),
            ("time_ms", "t [ms]")]
    md = ex.markdown_table(rows, cols) + "\n\n## Targets (ratios measured in this run)\n\n"
    n = max(counts)
    for name in names:
        for spec in specs:
            g = {(r["rig"], r["viewers"]): r for r in rows if r["scene"] == name and r["setting"] == spec}
            a, b = g.get(("overlap", 1)), g.get(("overlap", n))
            if a and b:
                md += (f"- {name} {spec}: memory at 100% overlap, {n} viewers = "
                       f"{ex.ratio(b['memory_mb'], a['memory_mb']):.2f}x one viewer's"
                       + (" (target <= 1.1x)\n" if spec == "slc" else "\n"))
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"viewers": counts})


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
