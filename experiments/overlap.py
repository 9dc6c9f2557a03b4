"""overlap: multi-viewer scaling under controlled overlap (SLC paper, Fig. 11).

All viewers share one position on one camera path and are turned about the
up axis so that the share of visible surface cells seen by more than one
viewer reaches a target (the rig calibrates its yaw step on that measure
and narrows the views when 16 of them would wrap around the circle; see
``slc.scene.views.overlap_rig``); the overlap actually reached is measured again
in the run and reported next to the target. The cache is shared
by all viewers; the per-viewer baselines do not depend on the overlap, so
they are run at 0% and 100% only.

    slc run overlap --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.core.timing import stage_table  # noqa: E402 (after the path of a standalone run)
from slc.core.spec import parse_spec  # noqa: E402
from slc.run import experiment as ex  # noqa: E402
from slc.run import plots  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "overlap"
# warm-up 10 frames: kernel builds and the 8-ray start-up of the first frame's entries (startup_ms)
FULL = dict(scenes=["street", "atrium"], viewers=[1, 4, 16], overlaps=[0, 25, 50, 75, 100],
            width=320, height=180, frames=240, warmup=10, eval_frames=[239], eval_viewers=2)
QUICK = dict(scenes=["atrium"], viewers=[1, 4, 16], overlaps=[0, 50, 100],
             width=96, height=54, frames=24, warmup=10, eval_frames=[23], eval_viewers=1)
METHODS = ["slc", "adaptive", "rt48", "restir", "regir"]
CACHE_METHODS = ("slc", "sh", "adaptive")
TARGET = 1.25       # the most viewers at the largest overlap against one viewer, cache methods


def add_arguments(p):
    ex.add_viewer_arguments(p)
    p.add_argument("--overlaps", type=int, nargs="+", help="target overlaps in percent")
    p.add_argument("--retime", type=int, default=3,
                   help="after the rows, time one viewer and the most viewers at the largest overlap again in "
                        "turn this many times per cache method (the target's ratio; 0: off)")


def run(opts):
    pr, specs, names, cfg = ex.setup(opts, QUICK, FULL, METHODS)
    counts, overlaps = opts.viewers or pr["viewers"], opts.overlaps or pr["overlaps"]
    out = Path(opts.out) / NAME
    rows, retimed = [], []
    for s in ex.each_scene(names):
        rows += ex.run_cases(_cases(s, specs, counts, overlaps, cfg), cfg, f"{NAME} {s.name}", opts.seed)
        retimed += _retime(s, specs, counts, overlaps, cfg, opts)
    ex.add_startup(rows)
    _extend_one_viewer(rows, overlaps)
    _plots(out, rows, cfg)
    md = _markdown(rows, retimed, specs, counts, overlaps, cfg)
    config = {"quick": bool(opts.quick), "viewers": counts, "overlaps": overlaps, "methods": specs,
              "scenes": names, "width": cfg.width, "height": cfg.height,
              "frames": cfg.frames, "warmup": cfg.warmup, "eval_frames": cfg.evaluated(),
              "eval_viewers": cfg.eval_viewers, "seed": cfg.seed, "retime": opts.retime}
    results = ex.results_object(NAME, config, [r for r in ex.strip_private(rows)])
    results["ratio_in_turn"] = retimed
    ex.write_results(out, results, md)
    print(md)
    return results


def _cases(s, specs, counts, overlaps, cfg) -> list:
    """The runs of scene ``s``: every setting at every viewer count and target overlap (the
    per-viewer baselines at the smallest and largest overlap only, one viewer once)."""
    cases = []
    for spec in specs:
        cache = parse_spec(spec)[0] in CACHE_METHODS
        for o in (overlaps if cache else sorted({min(overlaps), max(overlaps)})):
            for n in counts:
                if n == 1 and o != max(overlaps):
                    continue  # one viewer has no overlap: run it once
                cases.append((s, spec, views.overlap_rig(s, n, o / 100.0, aspect=cfg.width / cfg.height),
                              {"rig": "overlap", "overlap": o}))
    return cases


def _retime(s, specs, counts, overlaps, cfg, opts) -> list:
    """The target's ratio, timed again in turn: one viewer and the most viewers at the largest
    overlap, per cache method (``--retime`` times; none when 0)."""
    retimed = []
    top_n, top_o = max(counts), max(overlaps)
    if opts.retime > 0 and top_n > 1:
        aspect = cfg.width / cfg.height
        for spec in [sp for sp in specs if parse_spec(sp)[0] in CACHE_METHODS]:
            turn = ex.ratio_in_turn(s, spec, views.overlap_rig(s, 1, top_o / 100.0, aspect=aspect),
                                    views.overlap_rig(s, top_n, top_o / 100.0, aspect=aspect), cfg,
                                    opts.retime, opts.seed)
            retimed.append({"scene": s.name, "setting": spec, "viewers": top_n, "overlap": top_o, **turn})
    return retimed


def _extend_one_viewer(rows, overlaps) -> None:
    """One viewer belongs to every overlap curve: its cache methods' rows are added at every
    other overlap, marked ``derived``."""
    for r in [r for r in rows if r["viewers"] == 1]:
        for o in overlaps:
            if o != r["overlap"] and parse_spec(r["setting"])[0] in CACHE_METHODS:
                rows.append({**r, "overlap": o, "derived": True})


def _plots(out, rows, cfg) -> None:
    """Time against viewers per scene, one curve per method and overlap."""
    for name in sorted({r["scene"] for r in rows}):
        plots.time_vs_viewers_plot(out / f"time_vs_viewers_{name}.png", [r for r in rows if r["scene"] == name],
                                f"{name}: controlled overlap ({cfg.width}x{cfg.height})",
                                group=("method", "overlap"))


def _markdown(rows, retimed, specs, counts, overlaps, cfg) -> str:
    """results.md: the rows, the overlap reached, the stage times and the targets."""
    md = [f"# {NAME}\n", f"{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up); time = median "
          f"DI ms per frame for all viewers; quality of the first {cfg.eval_viewers} viewer(s) on frames "
          f"{cfg.evaluated()}; measured overlap = % of visible surface cells seen by more than one viewer.\n",
          ex.markdown_table([r for r in rows if not r.get("derived")], ex.DEFAULT_COLUMNS[:3] + [
              ("overlap", "target overlap %"), ("measured_overlap", "measured %"), ("cache_overlap", "cache entries %")]
              + ex.DEFAULT_COLUMNS[3:4] + [("startup_ms", "start-up t [ms]"),
                                           ("compiled_after_warmup", "kernels after warm-up"),
                                           ("recordings_after_warmup", "recordings after warm-up")]
              + ex.DEFAULT_COLUMNS[4:]), "\n## Overlap reached\n", _reached(rows),
          "\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host time)\n",
          stage_table(rows, ("scene", "label", "viewers", "overlap")),
          "\n## Targets (ratios measured in this run)\n"]
    md += _targets(rows, retimed, specs, counts, overlaps)
    return "\n".join(md) + "\n"


def _targets(rows, retimed, specs, counts, overlaps) -> list:
    """One line per scene and setting: the most viewers at the largest overlap against one
    viewer, from the rows and as timed again in turn."""
    lines = []
    for name in sorted({r["scene"] for r in rows}):
        for spec in specs:
            one = [r for r in rows if r["scene"] == name and r["setting"] == spec and r["viewers"] == 1]
            top = [r for r in rows if r["scene"] == name and r["setting"] == spec and r["viewers"] == max(counts)
                   and r["overlap"] == max(overlaps)]
            turn = [t for t in retimed if t["scene"] == name and t["setting"] == spec]
            if one and top and max(counts) > 1:
                line = (f"- {name} {spec}: {max(counts)} viewers at {max(overlaps)}% overlap cost "
                        f"{ex.ratio(top[0]['time_ms'], one[0]['time_ms']):.2f}x one viewer (the rows above)")
                if turn:
                    t = turn[0]
                    line += (f"; timed again in turn {len(t['ratios'])} times: **{t['ratio']:.2f}x** (median; "
                             + ", ".join(f"{x:.2f}" for x in t["ratios"]) + f"; one viewer "
                             + ", ".join(f"{x:.1f}" for x in t["base_ms"]) + f" ms, {t['viewers']} viewers "
                             + ", ".join(f"{x:.1f}" for x in t["top_ms"])
                             + f" ms; kernels after warm-up {t['compiled_after_warmup']})")
                if parse_spec(spec)[0] in CACHE_METHODS:
                    line += f" (target <= {TARGET}x" + (", on the median in turn)" if turn else ")")
                lines.append(line)
    return lines


def _reached(rows) -> str:
    """Target against measured overlap per scene and viewer count (one row per rig)."""
    seen, lines = set(), []
    for r in rows:
        key = (r["scene"], r["viewers"], r["overlap"])
        if r["viewers"] < 2 or r.get("derived") or key in seen or r.get("measured_overlap") is None:
            continue
        seen.add(key)
        off = r["measured_overlap"] - r["overlap"]
        lines.append(f"| {r['scene']} | {r['viewers']} | {r['overlap']} | {r['measured_overlap']:.1f} | "
                     f"{off:+.1f}{'' if abs(off) <= 10 else ' (missed: target +-10)'} |")
    return ("| scene | viewers | target % | measured % | measured - target |\n|---|---|---|---|---|\n"
            + "\n".join(sorted(lines)) + "\n") if lines else ""


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
