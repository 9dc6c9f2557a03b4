"""memory: method memory against the number of viewers (SLC paper, Fig. 14).

Cache methods report allocated blocks x bytes per entry plus the block
table ("allocated") and the entries requested per frame (mean over the
timed frames) x bytes per entry ("active": the entries that the viewers
actually use, without the unused texels of their blocks and the table; the
paper's blocks are about half filled); per-viewer
methods report their buffers (ReSTIR: reservoirs, bytes per pixel x pixels x
viewers; RT-N: its output buffer), which every frame uses in full, so they
have no separate active figure. Scene data, G-buffers and output images
common to all methods are excluded. Rigs: 100% overlap and random viewers.

    slc run memory --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402 (after the path of a standalone run)

from slc import methods  # noqa: E402
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_viewer_arguments  # noqa: E402
from slc.run.pipeline import run_sequence  # noqa: E402
from slc.scene import random_walks, views  # noqa: E402

NAME = "memory"
FULL = dict(scenes=["atrium"], viewers=[1, 4, 16], width=320, height=180, frames=240, warmup=10,
            eval_frames=[], eval_viewers=1)
QUICK = dict(scenes=["atrium"], viewers=[1, 4, 16], width=96, height=54, frames=24, warmup=10, eval_frames=[],
             eval_viewers=1)
METHODS = ["slc", "rt16", "rt48", "restir"]


def add_arguments(p):
    add_viewer_arguments(p)


def run(opts):
    pr, specs, names, cfg = ex.setup(opts, QUICK, FULL, METHODS)
    counts = opts.viewers or pr["viewers"]
    def cases(s):
        return [c for spec in specs for n in counts for c in (
            (spec, views.overlap_rig(s, n, 1.0), {"rig": "overlap", "overlap": 100}),
            (spec, random_walks.random_viewers(s, n), {"rig": "random"}))]

    rows = []
    for s in ex.each_scene(names):
        rows += _run_cases([(s, *c) for c in cases(s)], cfg, f"{NAME} {s.name}", opts.seed)
    ex.add_startup(rows)
    out = Path(opts.out) / NAME
    for name in names:
        for rig in ("overlap", "random"):
            plots.time_vs_viewers_plot(out / f"memory_{name}_{rig}.png",
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


def _run_cases(cases, cfg, desc, seed):
    """Like ``slc.run.experiment.run_cases``, and for cache methods ``active_mb``
    = mean entries requested per timed frame x bytes per entry
    (:func:`entry_bytes_of`, read from the method after the run)."""
    rows = []
    with tqdm(total=len(cases) * cfg.frames, desc=desc, unit="frame", disable=None) as bar:
        for s, spec, vs, extra in cases:
            m = methods.create(spec, s, seed=seed)
            bar.set_postfix_str(f"{s.name}/{spec}/{len(vs)}v")
            res = run_sequence(s, m, vs, cfg, progress=bar)
            row = {"scene": s.name, **res.row(), "setting": spec, "label": m.label or m.name,
                   "resolution": f"{cfg.width}x{cfg.height}", **extra}
            entry_bytes = entry_bytes_of(m)
            if entry_bytes and "entries_requested" in row:
                row["active_mb"] = row["entries_requested"] * entry_bytes / 2 ** 20
            rows.append(row)
    return rows


def entry_bytes_of(m) -> float:
    """Bytes per cache entry of a cache method, from its own memory report:
    (memory_bytes - the block table) / allocated entries, i.e. the payload
    (packed cones / coefficients and the ray-policy state) plus the cache's
    surface point and seen flag. 0 for methods without an on-surface cache
    (their buffers are used in full every frame: no separate active figure)."""
    cache = getattr(m, "cache", None)
    if cache is None or not hasattr(cache, "entries_allocated") or not hasattr(cache, "pool"):
        return 0.0
    n = int(cache.entries_allocated())
    if n == 0:
        return 0.0
    return (int(m.memory_bytes()) - int(cache.pool.table_bytes())) / n


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
