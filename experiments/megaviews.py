"""megaviews: scaling of many-view rendering (MegaViews Figs. 10, 11, 12, 13, 16).

Shadow maps of VPL sets are rendered by ``megaviews`` (concurrent scene-view
traversal), ``manylods`` (scene hierarchy per view) and ``brute`` (every
scene leaf into every view, only where leaves x views stays under a pair
limit). Time is view-hierarchy build + traversal + push + fusion (one
timed run after a warm-up of the same method and size class; ``reps``
timed runs, median), broken down by stage (Fig. 10b/c); memory is the
pair-queue peak + all maps + hierarchies. Every row also gathers the VPLs
at a G-buffer and compares the indirect light with the indirect reference
(:func:`slc.reference.references.reference_for`, the VPLs' own bounce count) at the
same points: PSNR/SSIM/FLIP and the relative error of the mean (``mean_err``,
worst channel) and the median per-pixel relative luminance error
(``med_err``), the measures of ``tests/test_megaviews.py``.

Sweeps (``sweep`` column):

* ``views``: 1-bounce VPLs of growing count, 16^2 maps (Fig. 10a);
* ``distribution``: one view count with 1-bounce, 4-bounce and uniformly
  random views (Figs. 10a, 11);
* ``culling``: megaviews without pair culling (Fig. 10b, culling off);
* ``view-only``: view hierarchy without scene hierarchy (Sec. 4.1), small
  view counts, next to megaviews at the same counts;
* ``depth``: scene = view octree depth (Fig. 13; pairs, multi-pass level,
  time, error per depth), with the paper's view-root multi-pass split;
* ``resolution``: map resolution (Figs. 12, 14);
* ``gather``: gathering with culling down to level 0 / the paper's level 6
  and with a distance cut-off, at equal samples without the filter (Fig. 16);
* ``particles``: omnidirectional views (Sec. 5.2), time only;
* ``pipeline``: whole frames through :func:`slc.run.pipeline.run_sequence`.

    python experiments/megaviews.py --quick
    slc run megaviews --quick [--scene cornell] [--scene sponza]
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
METHODS = ["megaviews", "manylods", "brute"]

FULL = dict(scenes=["cornell", "sponza"], views=[1024, 4096, 16384, 65536], res=[16, 32, 64], res_views=4096,
            dist_views=16384, viewonly=[64, 256], depths=[5, 6, 7, 8], depth_views=4096, particles=[4096, 16384],
            gres=64, reps=1, scene_depth=7, view_depth=7, brute_pairs=3e8, ref_spp=512, seq_views=4096,
            seq_frames=3, gather_samples=16, seq_methods=METHODS)
QUICK = dict(scenes=["cornell"], views=[1024, 4096, 16384], res=[], res_views=1024,
             dist_views=4096, viewonly=[64], depths=[5, 7], depth_views=1024, particles=[],
             gres=32, reps=1, scene_depth=6, view_depth=6, brute_pairs=6e7, ref_spp=256, seq_views=1024,
             seq_frames=2, gather_samples=16, seq_methods=["megaviews"])
STAGES = ["view_hierarchy", "traverse", "push", "fuse"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--methods", nargs="+", help="subset of megaviews manylods brute")
    p.add_argument("--views", nargs="+", type=int, help="view counts of the views sweep")
    p.add_argument("--res", nargs="+", type=int, help="map resolutions of the resolution sweep")
    p.add_argument("--depths", nargs="+", type=int, help="octree depths of the depth sweep")
    p.add_argument("--scene-depth", type=int, help="scene (and view) octree depth")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/megaviews)")
    p.add_argument("--seed", type=int, default=0)


def _time_maps(m, vpls, reps, phi=math.pi / 2):
    """(median ms, stage medians, maps, octree view hierarchy) of the
    method's shadow-map rendering of ``vpls`` (one untimed warm-up run when
    this method and setting have not run yet: kernel compilation)."""
    from slc.core.timing import StageTimer
    key = (m.name, m.res, m.cull, m.scene_h, phi)   # sizes and depths build no new kernels
    timer = StageTimer()
    if key not in _WARM:
        _WARM.add(key)
        m.shadow_maps(vpls, phi=phi)
    for _ in range(reps):
        timer.begin_frame()
        maps, tree = m.shadow_maps(vpls, timer, phi=phi)   # every stage ends evaluated and synced
        timer.end_frame()
    summ = timer.summary(0)
    return summ["total"], {k: summ.get(k, 0.0) for k in STAGES}, maps, tree


_WARM: set = set()


def _errors(gb, img, ref):
    """(worst-channel relative error of the image mean, median per-pixel
    relative luminance error), as tests/test_megaviews.py measures them."""
    import numpy as np
    valid = np.array(gb.valid, bool).reshape(gb.height, gb.width)
    x, r = img[valid], ref[valid]
    mean_err = np.abs(x.mean(0) - r.mean(0)) / np.maximum(r.mean(0), 1e-12)
    lx, lr = x.mean(1), r.mean(1)
    e = np.abs(lx - lr) / np.maximum(lr, 0.1 * lr.mean())
    return float(np.max(mean_err)), float(np.median(e))


def _random_views(s, n, seed):
    """``n`` views at uniform random surface points of the scene, each
    looking along its normal (Fig. 11's random distribution)."""
    import numpy as np

    from slc.methods.megaviews import vpl as vp
    from slc.methods.megaviews.hierarchy import sample_surface
    P, N, _, _ = sample_surface(s.mi_scene, n, seed=seed + 11)
    k = np.random.default_rng(seed).choice(len(P), n, replace=len(P) < n)
    return vp.VPLSet(None, None, P[k] + 1e-3 * N[k], N[k], np.zeros(n))


def run(opts) -> dict:
    import numpy as np

    from slc.run import experiment

    from slc.core import io

    from slc import methods

    from slc.reference import metrics, references

    from slc.scene import views
    from slc.methods.megaviews import vpl as vp
    from slc.run.pipeline import RunConfig, gbuffers_for, run_case

    preset = dict(QUICK if opts.quick else FULL)
    if opts.views:
        preset["views"] = opts.views
    if opts.res:
        preset["res"] = opts.res
    if opts.depths:
        preset["depths"] = opts.depths
    if opts.scene_depth:
        preset["scene_depth"] = preset["view_depth"] = opts.scene_depth
    modes = opts.methods or METHODS
    for m in modes:
        if m not in METHODS:
            raise experiment.ExperimentError(f"unknown method '{m}' (megaviews: {', '.join(METHODS)})")
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    # every method and sweep setting is checked (one-line error) before any work
    base = dict(scene_depth=preset["scene_depth"], view_depth=preset["view_depth"])
    specs = [dict(views=n, res=16) for n in preset["views"]]
    specs += [dict(views=preset["res_views"], res=r) for r in preset["res"]]
    specs += [dict(scene_depth=d, view_depth=d) for d in preset["depths"]]
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
        refs = {}

        def ref_for(bounces):
            if bounces not in refs:
                refs[bounces] = references.reference_for("indirect", s, gb, 0, gb.viewer, spp=preset["ref_spp"],
                                                         bounces=bounces)
                io.write_hdr_and_png(out / "images" / f"{s.name}_reference_b{bounces}", refs[bounces],
                                     references.exposure_for("indirect", s, refs[bounces]))
            return refs[bounces]

        def quality(img, bounces, tag):
            ref = ref_for(bounces)
            exposure = references.exposure_for("indirect", s, ref)
            q = metrics.evaluate(ref, img, exposure)
            me, md = _errors(gb, img, ref)
            io.write_hdr_and_png(out / "images" / f"{s.name}_{tag}", img, exposure)
            return {"flip": q["flip"], "psnr": q["psnr"], "ssim": q["ssim"], "mean_err": me, "med_err": md}

        def measure(kind, mode, vpls, dist="vpl1", gather=True, phi=math.pi / 2, **setting):
            bounces = 4 if dist == "vpl4" else 1
            if mode == "brute" and n_leaves * vpls.n > preset["brute_pairs"]:
                notes.append(f"{s.name}: brute skipped at {vpls.n} views ({kind}) "
                             f"({n_leaves} leaves x {vpls.n} views > {preset['brute_pairs']:.0e} pairs)")
                return None
            m = first[mode].variant(views=max(vpls.n, 1), bounces=bounces, **setting)
            ms, stages, maps, tree = _time_maps(m, vpls, preset["reps"], phi)
            st = maps.stats.as_dict()
            mem = {k: v / 2 ** 20 for k, v in m.memory().items()}
            lsh = m.scene_hierarchy()
            row = {"scene": s.name, "method": mode, "label": m.label or m.name, "viewers": 1, "sweep": kind,
                   "distribution": dist, "views": int(vpls.n), "resolution": int(m.res), "depth": m.scene_depth,
                   "time_ms": ms, **{f"{k}_ms": v for k, v in stages.items()},
                   "memory_mb": m.memory_bytes() / 2 ** 20,
                   "pair_queue_mb": mem["pair_queue"], "maps_mb": mem["maps"],
                   "leaf_maps_mb": maps.leaf_maps_bytes() / 2 ** 20,
                   "hierarchy_mb": mem["scene_hierarchy"] + mem["view_hierarchy"],
                   "views_per_render": st["views_per_render"], "pairs": st["pairs"], "rendered": st["rendered"],
                   "culled": st["culled"], "multi_pixel": st["multi_pixel"], "passes": st["passes"],
                   "split_level": st["split_level"], "wasted_pairs": st["wasted_pairs"],
                   "scene_leaves": int(lsh.size - lsh.tree.level_start[lsh.depth]),
                   "cull": int(m.cull), "scene_h": int(m.scene_h)}
            if gather and vpls.si is not None:
                L = m.gather(gb, vpls, maps, tree, opts.seed)
                tag = f"{kind}_{mode}_{dist}_{vpls.n}_{m.res}_d{m.scene_depth}" + ("" if m.cull else "_nocull")
                row.update(quality(vp.to_image(gb, L), bounces, tag))
            rows.append(row)
            print(f"{s.name} {kind} {mode} {dist} views={vpls.n} res={m.res} depth={m.scene_depth}: {ms:.1f} ms "
                  f"({', '.join(f'{k} {v:.0f}' for k, v in stages.items())}), {row['memory_mb']:.1f} MB, "
                  f"{st['pairs']:.3g} pairs, {st['views_per_render']:.2f} views/render"
                  + (f", PSNR {row['psnr']:.2f}, mean err {row['mean_err']:.3f}" if "psnr" in row else ""),
                  flush=True)
            return row

        lead = next(iter(first.values()))
        # ------------------------------ views sweep (Fig. 10a) ------------------------------
        for n in preset["views"]:
            vpls = lead.variant(views=n).lights(opts.seed)
            for mode in modes:
                measure("views", mode, vpls)
        # -------------------- view distributions (Figs. 10a, 11), culling off --------------------
        nd = preset["dist_views"]
        sets = {"vpl1": lead.variant(views=nd).lights(opts.seed),
                "vpl4": lead.variant(views=nd, bounces=4).lights(opts.seed),
                "random": _random_views(s, nd, opts.seed)}
        for dist in ("vpl4", "random"):
            for mode in [x for x in modes if x != "brute"]:
                measure("distribution", mode, sets[dist], dist)
        if "megaviews" in modes:
            measure("culling", "megaviews", sets["vpl1"], cull=False)
            # ---------------- view hierarchy without scene hierarchy (Sec. 4.1) ----------------
            for n in preset["viewonly"]:
                vpls = lead.variant(views=n).lights(opts.seed)
                measure("view-only", "megaviews", vpls, scene_h=False)
                measure("view-only", "megaviews", vpls)
            # ------------- hierarchy depth with the view-root multi-pass (Fig. 13) -------------
            vpls = lead.variant(views=preset["depth_views"]).lights(opts.seed)
            for d in preset["depths"]:
                measure("depth", "megaviews", vpls, scene_depth=d, view_depth=d)
        # ---------------------------- resolution sweep (Figs. 12, 14) ----------------------------
        vpls = lead.variant(views=preset["res_views"]).lights(opts.seed)
        for res in preset["res"]:
            for mode in modes:
                measure("resolution", mode, vpls, res=res)
        # ------------------ gathering: culling level and cut-off (Fig. 16) ------------------
        if "megaviews" in modes:
            vpls = sets["vpl1"]
            m = first["megaviews"].variant(views=vpls.n)
            maps, tree = m.shadow_maps(vpls)
            for cl, cut in ((0, 0.0), (2, 0.0), (6, 0.0), (6, 0.25)):
                g = m.variant(views=vpls.n, cull_level=cl, cutoff=cut, filter=0, samples=preset["gather_samples"])
                import drjit as dr
                for _ in range(2):   # the first call compiles
                    dr.sync_thread()
                    t0 = time.perf_counter()
                    L = g.gather(gb, vpls, maps, tree, opts.seed)
                    dr.eval(L)
                    dr.sync_thread()
                row = {"scene": s.name, "method": "megaviews", "label": g.label or g.name, "viewers": 1,
                       "sweep": "gather", "distribution": "vpl1", "views": vpls.n, "resolution": 16,
                       "cull_level": cl, "cutoff": cut, "samples": g.samples,
                       "gather_ms": (time.perf_counter() - t0) * 1e3,
                       **quality(vp.to_image(gb, L), 1, f"gather_cull{cl}_cut{cut}")}
                rows.append(row)
                print(f"{s.name} gather cull_level={cl} cutoff={cut}: PSNR {row['psnr']:.2f}, "
                      f"median err {row['med_err']:.3f}", flush=True)
        # -------------------- glowing particles (omnidirectional) --------------------
        rs = np.random.default_rng(opts.seed + 5)
        for n in preset["particles"]:
            P = rs.uniform(s.bbox_min + 0.05 * (s.bbox_max - s.bbox_min),
                           s.bbox_max - 0.05 * (s.bbox_max - s.bbox_min), (n, 3))
            part = vp.VPLSet(None, None, P, np.tile([0.0, 1.0, 0.0], (n, 1)), np.zeros(n))
            for mode in [x for x in modes if x != "brute"]:
                measure("particles", mode, part, "particles", gather=False, phi=math.pi)
        # ------------- whole frames through the common pipeline (slc.run.pipeline) -------------
        cfg = RunConfig(width=gres, height=gres, frames=preset["seq_frames"], warmup=1, seed=opts.seed,
                        eval_frames=[preset["seq_frames"] - 1], ref_spp=preset["ref_spp"], keep_images=False)
        for mode in [x for x in modes if x in preset["seq_methods"]]:
            if mode == "brute" and n_leaves * preset["seq_views"] > preset["brute_pairs"]:
                continue
            spec = (f"{mode}:views={preset['seq_views']},scene_depth={preset['scene_depth']},"
                    f"view_depth={preset['view_depth']}")
            row = run_case(s, spec, views.single(s), cfg, seed=opts.seed, sweep="pipeline",
                                      distribution="vpl1", views=preset["seq_views"], resolution=16)
            row.pop("_result")
            rows.append(row)
            print(f"{s.name} pipeline {mode} views={preset['seq_views']}: {row['time_ms']:.1f} ms per frame, "
                  f"PSNR {row['psnr']:.2f} vs the indirect reference", flush=True)

    # ------------------------------ targets as ratios ------------------------------
    summary = _summary(names, rows)
    _plots(out, rows)
    config = {"quick": bool(opts.quick), **{k: v for k, v in preset.items()}, "methods": modes,
              "seed": opts.seed, "scenes": names}
    results = experiment.results_object(NAME, config, rows)
    results["summary"] = summary
    results["notes"] = sorted(set(notes))
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
    md = (f"# {NAME}\n\nShadow-map time ({preset['reps']} timed run(s) after a warm-up per method and setting: "
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
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


def _summary(names, rows) -> list:
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
                   for k in STAGES if a.get(f"{k}_ms", 0) > 0.05 and b.get(f"{k}_ms", 0) > 0.05}
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


def _plots(out: Path, rows: list) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc.core import io
    from slc.run.plots import place_labels
    for sweep, x, xl in [("views", "views", "views"), ("resolution", "resolution", "map resolution")]:
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        marks = []
        for scene in sorted({r["scene"] for r in rows}):
            for m in METHODS:
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


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
