"""megaviews: scaling of many-view rendering (MegaViews Figs. 10, 12, 15).

For 1-bounce VPL sets of growing size (views sweep, 16x16 maps) and for
growing map resolution (resolution sweep), shadow maps are rendered by
``megaviews`` (concurrent scene-view traversal), ``manylods`` (scene
hierarchy per view) and ``brute`` (every scene leaf into every view, only
where leaves x views stays under a pair limit); time is the median over
repetitions (after a warm-up) of view-hierarchy build + traversal + push +
fusion; memory is the pair-queue peak + all maps + hierarchies. Every row
also gathers the VPLs at a G-buffer and compares the indirect light with the
one-bounce indirect reference at the same points (PSNR, SSIM, FLIP;
:func:`slc.references.reference_for`). The sweeps call the methods' own
steps (``lights``, ``shadow_maps``, ``gather``, ``memory``) so that one VPL
set is shared by the three methods; a "pipeline" block then runs each
method for whole frames through :func:`slc.pipeline.run_sequence`. A last
block times glowing particles (omnidirectional views).

    python experiments/megaviews.py --quick
    slc run megaviews --quick [--scene cornell]
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "megaviews"

FULL = dict(scenes=["cornell"], views=[1024, 4096, 16384, 65536], res=[16, 32, 64, 128], res_views=4096,
            particles=[4096, 16384], gres=128, reps=3, scene_depth=7, view_depth=7, brute_pairs=3e8,
            ref_spp=512, seq_views=4096, seq_frames=4)
QUICK = dict(scenes=["cornell"], views=[1024, 4096, 16384], res=[16, 32, 64], res_views=1024,
             particles=[4096], gres=64, reps=2, scene_depth=6, view_depth=6, brute_pairs=6e7,
             ref_spp=256, seq_views=1024, seq_frames=3)
METHODS = ["megaviews", "manylods", "brute"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--methods", nargs="+", help="subset of megaviews manylods brute")
    p.add_argument("--views", nargs="+", type=int, help="view counts of the views sweep")
    p.add_argument("--res", nargs="+", type=int, help="map resolutions of the resolution sweep")
    p.add_argument("--scene-depth", type=int, help="scene octree depth")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/megaviews)")
    p.add_argument("--seed", type=int, default=0)


def _time_maps(m, vpls, reps, phi=math.pi / 2):
    """(median ms, maps, octree view hierarchy) of the method's shadow-map
    rendering (view hierarchy + traversal + push + fusion) of ``vpls``."""
    import drjit as dr
    times, maps, tree = [], None, None
    for _ in range(reps + 1):  # first run: warm-up (kernel compilation)
        maps = None
        dr.sync_thread()
        t0 = time.perf_counter()
        maps, tree = m.shadow_maps(vpls, phi=phi)
        dr.eval(maps.depth)
        dr.sync_thread()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times[1:]), maps, tree


def run(opts) -> dict:
    import numpy as np

    from slc import experiment, io, methods, metrics, references, views
    from slc.megaviews import vpl as vp
    from slc.pipeline import RunConfig, gbuffers_for

    preset = dict(QUICK if opts.quick else FULL)
    if opts.views:
        preset["views"] = opts.views
    if opts.res:
        preset["res"] = opts.res
    if opts.scene_depth:
        preset["scene_depth"] = opts.scene_depth
    modes = opts.methods or METHODS
    for m in modes:
        if m not in METHODS:
            raise experiment.ExperimentError(f"unknown method '{m}' (megaviews: {', '.join(METHODS)})")
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    # every method and sweep setting is checked (one-line error) before any work
    base = dict(scene_depth=preset["scene_depth"], view_depth=preset["view_depth"])
    specs = [dict(views=n, res=16) for n in preset["views"]]
    specs += [dict(views=preset["res_views"], res=r) for r in preset["res"]]
    out = Path(opts.out) / NAME
    rows, notes = [], []
    for s in experiment.each_scene(names):
        s.set_frame(0)
        first = {mode: methods.create(mode, s, seed=opts.seed, **base) for mode in modes}
        for m in first.values():
            for sp in specs:
                m.variant(**sp)
        sh = next(iter(first.values())).scene_hierarchy()
        for m in first.values():
            m.use_scene_hierarchy(sh)
        n_leaves = int(sh.size - sh.tree.level_start[sh.depth])
        gres = preset["gres"]
        gb = gbuffers_for(s, views.single(s), 0, gres, gres)[0]
        ref = references.reference_for("indirect", s, gb, 0, gb.viewer, spp=preset["ref_spp"], bounces=1)
        exposure = references.exposure_for("indirect", s, ref)
        io.write_hdr_and_png(out / "images" / f"{s.name}_reference", ref, exposure)

        def measure(kind, res, mode, vpls, views_count):
            if mode == "brute" and n_leaves * vpls.n > preset["brute_pairs"]:
                notes.append(f"{s.name}: brute skipped at {vpls.n} views, {res}^2 "
                             f"({n_leaves} leaves x {vpls.n} views > {preset['brute_pairs']:.0e} pairs)")
                return None
            m = first[mode].variant(views=views_count, res=res)
            ms, maps, tree = _time_maps(m, vpls, preset["reps"])
            st = maps.stats.as_dict()
            img = vp.to_image(gb, m.gather(gb, vpls, maps, tree, opts.seed))
            q = metrics.evaluate(ref, img, exposure)
            io.write_hdr_and_png(out / "images" / f"{s.name}_{kind}_{mode}_{vpls.n}_{res}", img, exposure)
            mem = {k: v / 2 ** 20 for k, v in m.memory().items()}
            row = {"scene": s.name, "method": mode, "label": m.label or m.name, "viewers": 1, "sweep": kind,
                   "distribution": "vpl1", "views": int(vpls.n), "resolution": int(res), "time_ms": ms,
                   "memory_mb": m.memory_bytes() / 2 ** 20,
                   "pair_queue_mb": mem["pair_queue"], "maps_mb": mem["maps"],
                   "leaf_maps_mb": maps.leaf_maps_bytes() / 2 ** 20,
                   "hierarchy_mb": mem["scene_hierarchy"] + mem["view_hierarchy"],
                   "views_per_render": st["views_per_render"], "pairs": st["pairs"], "rendered": st["rendered"],
                   "multi_pixel": st["multi_pixel"], "passes": st["passes"], "scene_leaves": n_leaves,
                   "flip": q["flip"], "psnr": q["psnr"], "ssim": q["ssim"]}
            rows.append(row)
            print(f"{s.name} {kind} {mode} views={vpls.n} res={res}: {ms:.1f} ms, {row['memory_mb']:.1f} MB, "
                  f"{st['views_per_render']:.2f} views/render, PSNR {q['psnr']:.2f}", flush=True)
            return row

        # ----------------------------- views sweep -----------------------------
        lead = next(iter(first.values()))
        for n in preset["views"]:
            vpls = lead.variant(views=n).lights(opts.seed)
            for mode in modes:
                measure("views", 16, mode, vpls, n)
        # -------------------------- resolution sweep --------------------------
        vpls = lead.variant(views=preset["res_views"]).lights(opts.seed)
        for res in preset["res"]:
            for mode in modes:
                measure("resolution", res, mode, vpls, preset["res_views"])
        # -------------------- glowing particles (omnidirectional) --------------------
        rs = np.random.default_rng(opts.seed + 5)
        for n in preset["particles"]:
            P = rs.uniform(s.bbox_min + 0.05 * (s.bbox_max - s.bbox_min),
                           s.bbox_max - 0.05 * (s.bbox_max - s.bbox_min), (n, 3))
            part = vp.VPLSet(None, None, P, np.tile([0.0, 1.0, 0.0], (n, 1)), np.zeros(n))
            for mode in [x for x in modes if x != "brute"]:
                m = first[mode].variant(views=n, res=16)
                ms, maps, _ = _time_maps(m, part, preset["reps"], phi=math.pi)
                st = maps.stats.as_dict()
                rows.append({"scene": s.name, "method": mode, "label": m.label or m.name, "viewers": 1,
                             "sweep": "particles", "distribution": "particles", "views": n, "resolution": 16,
                             "time_ms": ms, "memory_mb": m.memory_bytes() / 2 ** 20,
                             "pair_queue_mb": st["pair_queue_mb"], "views_per_render": st["views_per_render"]})
                print(f"{s.name} particles {mode} views={n}: {ms:.1f} ms", flush=True)
        # ------------- whole frames through the common pipeline (slc.pipeline) -------------
        cfg = RunConfig(width=gres, height=gres, frames=preset["seq_frames"], warmup=1, seed=opts.seed,
                        eval_frames=[preset["seq_frames"] - 1], ref_spp=preset["ref_spp"], keep_images=False)
        for mode in modes:
            if mode == "brute" and n_leaves * preset["seq_views"] > preset["brute_pairs"]:
                continue
            spec = (f"{mode}:views={preset['seq_views']},scene_depth={preset['scene_depth']},"
                    f"view_depth={preset['view_depth']}")
            row = experiment.run_case(s, spec, views.single(s), cfg, seed=opts.seed, sweep="pipeline",
                                      distribution="vpl1", views=preset["seq_views"], resolution=16)
            row.pop("_result")
            rows.append(row)
            print(f"{s.name} pipeline {mode} views={preset['seq_views']}: {row['time_ms']:.1f} ms per frame, "
                  f"PSNR {row['psnr']:.2f} vs the indirect reference", flush=True)

    # ------------------------------ targets as ratios ------------------------------
    summary = []
    for name in names:
        vr = [r for r in rows if r["scene"] == name and r["sweep"] == "views"]
        mv = sorted([r for r in vr if r["method"] == "megaviews"], key=lambda r: r["views"])
        ml = {r["views"]: r for r in vr if r["method"] == "manylods"}
        if len(mv) >= 2:
            a, b = mv[0], mv[-1]
            summary.append(f"{name}: megaviews {b['views'] / a['views']:.0f}x views cost "
                           f"{b['time_ms'] / max(a['time_ms'], 1e-9):.2f}x time "
                           f"(target <= {(b['views'] / a['views']) ** (2 / 3):.1f}x, i.e. 64x views -> 16x time, exponent 2/3; "
                           f"measured exponent {math.log(b['time_ms'] / a['time_ms']) / math.log(b['views'] / a['views']):.2f})")
        for r in mv:
            if r["views"] in ml:
                o = ml[r["views"]]
                summary.append(f"{name} {r['views']} views: megaviews {o['time_ms'] / max(r['time_ms'], 1e-9):.2f}x "
                               f"faster than manylods, peak memory {r['memory_mb']:.1f} vs {o['memory_mb']:.1f} MB "
                               f"(pair queue {r['pair_queue_mb']:.1f} vs {o['pair_queue_mb']:.1f} MB)")
    _plots(out, rows)
    config = {"quick": bool(opts.quick), **{k: v for k, v in preset.items()}, "methods": modes,
              "seed": opts.seed, "scenes": names}
    results = experiment.results_object(NAME, config, rows)
    results["summary"] = summary
    results["notes"] = sorted(set(notes))
    cols = [("scene", "scene"), ("sweep", "sweep"), ("method", "method"), ("views", "views"),
            ("resolution", "res"), ("time_ms", "t [ms]"), ("memory_mb", "memory [MB]"),
            ("pair_queue_mb", "pairs [MB]"), ("views_per_render", "views/render"), ("psnr", "PSNR"),
            ("ssim", "SSIM"), ("flip", "FLIP")]
    md = (f"# {NAME}\n\nShadow-map time (median of {preset['reps']} after a warm-up: view hierarchy + traversal + "
          f"push + fusion), memory (pair-queue peak + maps + hierarchies), indirect-light quality vs the "
          f"{preset['ref_spp']}-spp one-bounce indirect reference (slc.references) at {preset['gres']}^2 G-buffer "
          f"points. Scene octree depth {preset['scene_depth']}, view octree depth {preset['view_depth']}. "
          f"Rows of sweep 'pipeline': whole frames (VPLs + maps + gathering) through slc.pipeline, "
          f"{preset['seq_frames']} frames (1 warm-up), quality of the last one.\n\n"
          + experiment.markdown_table(rows, cols) + "\n\n## Targets\n\n" + "\n".join(f"- {x}" for x in summary)
          + ("\n\n## Skipped\n\n" + "\n".join(f"- {x}" for x in sorted(set(notes))) if notes else "") + "\n")
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


def _plots(out: Path, rows: list) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc import io
    for sweep, x, xl in [("views", "views", "views"), ("resolution", "resolution", "map resolution")]:
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        for scene in sorted({r["scene"] for r in rows}):
            for m in METHODS:
                rs = sorted([r for r in rows if r["scene"] == scene and r["sweep"] == sweep and r["method"] == m],
                            key=lambda r: r[x])
                if not rs:
                    continue
                for ax, y in zip(axs, ["time_ms", "memory_mb"]):
                    ax.plot([r[x] for r in rs], [r[y] for r in rs], "o-", label=f"{scene}/{m}")
                    if m == "megaviews" and y == "time_ms":
                        for r in rs:
                            ax.annotate(f"{r['views_per_render']:.1f}", (r[x], r[y]), fontsize=7,
                                        textcoords="offset points", xytext=(3, 3))
        for ax, yl in zip(axs, ["shadow-map time [ms]", "memory [MB]"]):
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        axs[0].set_title("labels: views sharing a rendered node")
        fig.tight_layout()
        io.write_figure(out / f"{sweep}.png", fig, dpi=110)
        plt.close(fig)


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
