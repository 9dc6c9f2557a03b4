"""The report of the megaviews experiment (experiments/megaviews.py): the targets as
ratios, results.json and results.md, and the views and resolution figures. ``c`` is the
experiment's module (its constants)."""
from __future__ import annotations

import math
from pathlib import Path

from slc.core import io
from slc.run import experiment
from slc.run.plots import place_labels, pyplot


def write(c, out: Path, opts, preset: dict, modes: list, names: list, rows: list, notes: list) -> dict:
    """The targets as ratios, the plots, results.json and results.md; returns the results."""
    summary = _summary(c, names, rows)
    plots(c, out, rows)
    config = {"quick": bool(opts.quick), **{k: v for k, v in preset.items()}, "methods": modes,
              "seed": opts.seed, "scenes": names}
    results = experiment.results_object(c.NAME, config, rows)
    results["summary"] = summary
    results["notes"] = sorted(set(notes))
    md = _markdown(c, preset, rows, summary, notes)
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


def _markdown(c, preset: dict, rows: list, summary: list, notes: list) -> str:
    """results.md: the rows' table, the gathering table, the targets and the skipped runs."""
    cols = [("scene", "scene"), ("sweep", "sweep"), ("method", "method"), ("distribution", "views from"),
            ("views", "views"), ("resolution", "res"), ("depth", "depth"), ("time_ms", "t [ms]"),
            ("view_hierarchy_ms", "vh"), ("traverse_ms", "trav"), ("push_ms", "push"), ("fuse_ms", "fuse"),
            ("pairs", "pairs"), ("split_level", "mp level"),
            ("memory_mb", "memory [MB]"), ("pair_queue_mb", "pairs [MB]"), ("views_per_render", "views/render"),
            ("psnr", "PSNR"), ("flip", "FLIP"), ("mean_err", "mean err"), ("med_err", "median err")]
    gcols = [("scene", "scene"), ("cull_level", "cull level"), ("cutoff", "cut-off [edge]"), ("samples", "samples"),
             ("gather_ms", "gather [ms]"), ("psnr", "PSNR"), ("flip", "FLIP"), ("mean_err", "mean err"),
             ("med_err", "median err")]
    main_rows = [r for r in rows if r.get("sweep") != "gather"]
    g_rows = [r for r in rows if r.get("sweep") == "gather"]
    return (f"# {c.NAME}\n\nShadow-map time ({preset['reps']} timed run(s) after a warm-up per method and setting: "
            f"view hierarchy (vh) + traversal (trav) + push + fusion, ms), pairs processed, multi-pass level (the "
            f"paper's view-root split), memory (pair-queue peak + maps + hierarchies), and indirect-light quality "
            f"of the gathered image against the {preset['ref_spp']}-spp indirect reference (slc.reference.references, the "
            f"VPLs' bounce count) at {preset['gres']}^2 G-buffer points: PSNR, FLIP, relative error of the mean "
            f"(worst channel) and median per-pixel relative luminance error. Scene/view octree depth "
            f"{preset['scene_depth']} unless the depth column says otherwise. Sweeps: see experiments/megaviews.py. "
            f"Rows of sweep 'pipeline': whole frames through slc.run.pipeline, {preset['seq_frames']} frames "
            f"(1 warm-up), quality of the last one.\n\n"
            + experiment.markdown_table(main_rows, cols)
            + ("\n\n## Gathering: culling level and distance cut-off (Fig. 16; no filter)\n\n"
               + experiment.markdown_table(g_rows, gcols) if g_rows else "")
            + "\n\n## Targets and ratios (same run)\n\n" + "\n".join(f"- {x}" for x in summary)
            + ("\n\n## Skipped\n\n" + "\n".join(f"- {x}" for x in sorted(set(notes))) if notes else "") + "\n")


def _summary(c, names, rows) -> list:
    out = []
    for name in names:
        vr = [r for r in rows if r["scene"] == name and r["sweep"] == "views"]
        mv = sorted([r for r in vr if r["method"] == "megaviews"], key=lambda r: r["views"])
        ml = {r["views"]: r for r in vr if r["method"] == "manylods"}
        if len(mv) >= 2:
            a, b = mv[0], mv[-1]
            e = math.log(b["time_ms"] / a["time_ms"]) / math.log(b["views"] / a["views"])
            ep = math.log(b["pairs"] / a["pairs"]) / math.log(b["views"] / a["views"])
            out.append(f"{name}: megaviews {b['views'] / a['views']:.0f}x views ({a['views']}->{b['views']}) cost "
                       f"{b['time_ms'] / max(a['time_ms'], 1e-9):.2f}x time: exponent {e:.2f} (target <= 0.5: "
                       f"{'met' if e <= 0.5 else 'missed'}); pairs exponent {ep:.2f}")
            lg = math.log(b["views"] / a["views"])
            per = {k: math.log(max(b[f"{k}_ms"], 1e-6) / max(a[f"{k}_ms"], 1e-6)) / lg
                   for k in c.STAGES if a.get(f"{k}_ms", 0) > 0.05 and b.get(f"{k}_ms", 0) > 0.05}
            out.append(f"{name}: megaviews exponent per stage: " + ", ".join(f"{k} {v:.2f}" for k, v in per.items())
                       + "; traversal time per pair " + ", ".join(
                           f"{r['views']}: {1e3 * r['traverse_ms'] / max(r['pairs'], 1):.2f} us" for r in mv))
            if len(ml) >= 2:
                mls = sorted(ml.values(), key=lambda r: r["views"])
                e2 = math.log(mls[-1]["time_ms"] / mls[0]["time_ms"]) / math.log(mls[-1]["views"] / mls[0]["views"])
                out.append(f"{name}: manylods time exponent {e2:.2f} over the same views")
        for r in mv:
            if r["views"] in ml:
                o = ml[r["views"]]
                sp = o["time_ms"] / max(r["time_ms"], 1e-9)
                out.append(f"{name} {r['views']} views: megaviews {sp:.2f}x faster than manylods "
                           f"({o['pairs'] / max(r['pairs'], 1):.2f}x fewer pairs; target >= 10x at the largest count: "
                           f"{'met' if sp >= 10 else 'missed'}" + (")" if r is not mv[-1] else ", largest count)")
                           + f", peak memory {r['memory_mb']:.1f} vs {o['memory_mb']:.1f} MB; error vs reference: "
                           f"mean {r.get('mean_err', float('nan')):.3f} vs {o.get('mean_err', float('nan')):.3f}, "
                           f"median {r.get('med_err', float('nan')):.3f} vs {o.get('med_err', float('nan')):.3f}")
        c = [r for r in rows if r["scene"] == name and r["sweep"] == "culling"]
        if c:
            ref = next((r for r in vr if r["method"] == "megaviews" and r["views"] == c[0]["views"]), None)
            if ref is None:
                ref = next((r for r in rows if r["scene"] == name and r["sweep"] == "distribution"
                            and r["method"] == "megaviews"), None)
            if ref is not None:
                out.append(f"{name} {c[0]['views']} views: culling off costs {c[0]['time_ms'] / ref['time_ms']:.2f}x "
                           f"time, {c[0]['pairs'] / ref['pairs']:.2f}x pairs (paper: culling saves up to 20%)")
        d = sorted([r for r in rows if r["scene"] == name and r["sweep"] == "depth"], key=lambda r: r["depth"])
        for a, b in zip(d, d[1:]):
            out.append(f"{name} depth {a['depth']}->{b['depth']}: {b['pairs'] / a['pairs']:.2f}x pairs, "
                       f"{b['time_ms'] / a['time_ms']:.2f}x time, multi-pass level {b['split_level']}, "
                       f"median error {a.get('med_err', float('nan')):.3f} -> {b.get('med_err', float('nan')):.3f}")
        vo = [r for r in rows if r["scene"] == name and r["sweep"] == "view-only"]
        for r in [x for x in vo if not x["scene_h"]]:
            o = next((x for x in vo if x["scene_h"] and x["views"] == r["views"]), None)
            if o is not None:
                out.append(f"{name} {r['views']} views: view hierarchy without scene hierarchy costs "
                           f"{r['time_ms'] / o['time_ms']:.1f}x megaviews' time ({r['pairs'] / o['pairs']:.1f}x pairs)")
    return out


def plots(c, out: Path, rows: list) -> None:
    """The views and resolution sweeps' figures: time and memory per scene and method (``OUT/views.png``,
    ``OUT/resolution.png``)."""
    plt = pyplot()

    for sweep, x, xl in [("views", "views", "views"), ("resolution", "resolution", "map resolution")]:
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        marks = []
        for scene in sorted({r["scene"] for r in rows}):
            for m in c.METHODS:
                rs = sorted([r for r in rows if r["scene"] == scene and r["sweep"] == sweep and r["method"] == m],
                            key=lambda r: r[x])
                if not rs:
                    continue
                for ax, y in zip(axs, ["time_ms", "memory_mb"]):
                    ax.plot([r[x] for r in rs], [r[y] for r in rs], "o-", label=f"{scene}/{m}")
                    if m == "megaviews" and y == "time_ms":
                        marks += [(r[x], r[y], f"{r['views_per_render']:.1f}") for r in rs]
        for ax, yl in zip(axs, ["shadow-map time [ms]", "memory [MB]"]):
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        axs[0].set_title("labels: views sharing a rendered node")
        fig.tight_layout()
        place_labels(fig, axs[0], marks)
        io.write_figure(out / f"{sweep}.png", fig, dpi=110)
        plt.close(fig)
