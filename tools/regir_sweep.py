"""regir's settings swept against rtN at the single-viewer quick preset (160x90, 24 frames, warm-up 10,
FLIP on frames 15 and 23): one JSON line per run (scene, spec, FLIP, rel. MSE, median ms per frame, build
and shade ms, kernels after warm-up), and with --md a Markdown table per scene.

    PYTHONPATH=. python tools/regir_sweep.py [--scenes atrium sponza] [--shared /work/shared] [--md out.md]
"""
import argparse
import itertools
import json
import statistics
import sys
from pathlib import Path

from slc.run import experiment as ex

from slc import methods

from slc.scene import scenes, views
from slc.run.pipeline import RunConfig, run_sequence

ap = argparse.ArgumentParser()
ap.add_argument("--scenes", nargs="+", default=["atrium", "sponza"])
ap.add_argument("--shared", help="folder holding scenes/sponza (default: the repository's ../shared)")
ap.add_argument("--cells", nargs="*", type=float, default=[1.0, 2.0, 4.0])
ap.add_argument("--slots", nargs="+", type=int, default=[32, 128])
ap.add_argument("--taps", nargs="+", type=int, default=[4, 8])
ap.add_argument("--samples", nargs="+", type=int, default=[8])
ap.add_argument("--rt", nargs="*", default=["rt8", "rt16", "rt32", "rt48"])
ap.add_argument("--extra", nargs="*", default=[], help="further method specs")
ap.add_argument("--base", default="", help="settings appended to every swept regir spec, e.g. temporal=0")
ap.add_argument("--md", help="write the tables to this Markdown file")
ap.add_argument("--in-turn", nargs="*", default=[], dest="turn",
                help="specs timed again side by side (3 repetitions in turn, alternating order; median time)")
opts = ap.parse_args()
if opts.shared:
    scenes.SHARED_DIR = Path(opts.shared)

cfg = RunConfig(width=160, height=90, frames=24, warmup=10, eval_frames=[15, 23], seed=0, measure_overlap=False,
                keep_images=False)
base = f",{opts.base}" if opts.base else ""
specs = list(opts.rt) + [f"regir:cell={c:g},slots={s},taps={t},samples={n}{base}"
                         for c, s, t, n in itertools.product(opts.cells, opts.slots, opts.taps, opts.samples)]
specs += list(opts.extra)
rows = []
for name in opts.scenes:
    sc = scenes.load(name)
    for spec in specs:
        r = run_sequence(sc, methods.create(spec, sc, seed=0), views.single(sc), cfg)
        row = {"scene": name, "spec": spec, "flip": r.metrics["flip"], "rel_mse": r.metrics["rel_mse"],
               "time_ms": r.time_ms, "cells_ms": r.stages.get("cells", 0.0), "build_ms": r.stages.get("build", 0.0),
               "shade_ms": r.stages.get("shade", 0.0), "compiled_after_warmup": r.compiled_after_warmup,
               "memory_mb": r.memory_mb, "cells_built": r.stats.get("cells_built", 0.0),
               "cell_load": r.stats.get("cell_load", 0.0)}
        rows.append(row)
        print(json.dumps(row), flush=True)

turn = []
for name in opts.scenes if opts.turn else []:
    sc = scenes.load(name)
    res = ex.runs_in_turn(sc, [(spec, views.single(sc)) for spec in opts.turn], cfg, repeats=3)
    for spec, runs in zip(opts.turn, res):
        row = {"scene": name, "spec": spec, "flip": runs[0].metrics["flip"], "rel_mse": runs[0].metrics["rel_mse"],
               "times_ms": [r.time_ms for r in runs], "time_ms": statistics.median(r.time_ms for r in runs),
               "compiled_after_warmup": max(r.compiled_after_warmup for r in runs)}
        turn.append(row)
        print(json.dumps(row), flush=True)

if opts.md:
    out = ["# regir: settings swept against rtN", "",
           "Single viewer, 160x90, 24 frames (warm-up 10), FLIP and relative MSE against the 2048-sample ground "
           "truth on frames 15 and 23, median ms per frame (wall, machine shared: compare ratios). Command:", "",
           "    PYTHONPATH=. python tools/regir_sweep.py " + " ".join(sys.argv[1:]), ""]
    for name in opts.scenes:
        out += [f"### {name}", "", "| method | FLIP | rel. MSE | ms/frame | cells ms | build ms | shade ms | memory MB | "
                "kernels after warm-up |", "|---|---|---|---|---|---|---|---|---|"]
        for r in sorted((r for r in rows if r["scene"] == name), key=lambda r: r["time_ms"]):
            out.append(f"| {r['spec']} | {r['flip']:.4f} | {r['rel_mse']:.4f} | {r['time_ms']:.1f} | "
                       f"{r['cells_ms']:.1f} | {r['build_ms']:.1f} | {r['shade_ms']:.1f} | {r['memory_mb']:.1f} | "
                       f"{r['compiled_after_warmup']} |")
        out.append("")
    if turn:
        out += ["### Side by side", "", "The same specs run again in turn (3 repetitions, alternating order), "
                "median ms per frame:", "", "| scene | method | FLIP | rel. MSE | median ms/frame | ms/frame per "
                "repetition | kernels after warm-up |", "|---|---|---|---|---|---|---|"]
        for r in turn:
            out.append(f"| {r['scene']} | {r['spec']} | {r['flip']:.4f} | {r['rel_mse']:.4f} | {r['time_ms']:.1f} | "
                       f"{', '.join(f'{t:.0f}' for t in r['times_ms'])} | {r['compiled_after_warmup']} |")
        out.append("")
    Path(opts.md).write_text("\n".join(out) + "\n")
