"""single-viewer: Table 1 of the Surface Light Cones paper.

One viewer per scene on a camera path; every method shades the same
G-buffer points; caches are carried across frames; quality is measured
against 2048-sample ground truth on the evaluated frames and time is the
median DI time per frame after warm-up.

    python experiments/single_viewer.py --quick
    slc run single-viewer --quick [--scene atrium] [--methods rt16 rt48]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "single-viewer"

FULL = dict(scenes=["atrium", "street", "village", "garden", "sponza"], width=320, height=180,
            frames=32, warmup=4, eval_frames=[15, 23, 31], sweep=["rt4", "rt8", "rt32"])
QUICK = dict(scenes=["atrium"], width=160, height=90, frames=12, warmup=3, eval_frames=[7, 11],
             sweep=[])
BASE_METHODS = ["rt16", "rt48", "restir", "slc"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--methods", nargs="+", help="methods (default: rt16 rt48 and slc/restir when available)")
    p.add_argument("--sweep", nargs="*", help="extra settings for the speed-against-error plot")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/single-viewer)")
    p.add_argument("--res", help="WxH (default 320x180, quick 160x90)")
    p.add_argument("--frames", type=int, help="frames per sequence")
    p.add_argument("--seed", type=int, default=0)


def default_methods():
    from slc import methods
    avail = methods.available()
    return [m for m in BASE_METHODS if m.startswith("rt") or m in avail]


def run(opts) -> dict:
    from tqdm import tqdm

    from slc import experiment, io, methods, scenes, views
    from slc.pipeline import RunConfig, run_sequence

    preset = dict(QUICK if opts.quick else FULL)
    if opts.res:
        w, _, h = opts.res.lower().partition("x")
        preset["width"], preset["height"] = int(w), int(h)
    if opts.frames:
        preset["frames"] = opts.frames
        preset["eval_frames"] = [f for f in preset["eval_frames"] if f < opts.frames] or [opts.frames - 1]
        preset["warmup"] = min(preset["warmup"], max(opts.frames - 1, 0))
    scene_names = opts.scene or preset["scenes"]
    method_specs = opts.methods or default_methods()
    sweep = preset["sweep"] if opts.sweep is None else opts.sweep
    out = Path(opts.out) / NAME

    # ----------------- validate everything before any work -----------------
    loaded = []
    for name in scene_names:
        try:
            loaded.append(scenes.load(name))
        except scenes.SceneError as e:
            if name == "sponza" and not opts.scene:  # optional in the default list
                print(f"note: skipping sponza ({e})", file=sys.stderr)
                continue
            raise
    for s in loaded:
        for spec in method_specs + sweep:
            methods.create(spec, s)

    cfg = RunConfig(width=preset["width"], height=preset["height"], frames=preset["frames"],
                    warmup=preset["warmup"], eval_frames=preset["eval_frames"], seed=opts.seed)
    rows = []
    total = len(loaded) * len(method_specs + sweep) * cfg.frames
    with tqdm(total=total, desc=NAME, unit="frame", disable=None) as bar:
        for s in loaded:
            viewers = views.single(s)
            scene_rows = []
            for spec in method_specs + sweep:
                m = methods.create(spec, s, seed=opts.seed)
                bar.set_postfix_str(f"{s.name}/{spec}")
                res = run_sequence(s, m, viewers, cfg, progress=bar)
                row = {"scene": s.name, **res.row(), "rig": "single", "resolution": f"{cfg.width}x{cfg.height}",
                       "setting": spec, "label": m.label or m.name, "family": m.name.rstrip("0123456789") or m.name,
                       "sweep": spec in sweep and spec not in method_specs}
                rows.append(row)
                scene_rows.append(row)
                for vname, im in res.images.items():
                    stem = out / "images" / f"{s.name}_{(m.label or m.name).replace(':', '_')}"
                    io.write_hdr_and_png(stem, im["img"], s.exposure)
                    io.write_hdr_and_png(out / "images" / f"{s.name}_gt", im["gt"], s.exposure)
                    io.comparison_strip(stem.with_name(stem.name + "_strip.png"), im["gt"], im["img"],
                                        im["flip_map"], s.exposure)
                    break  # one viewer
            experiment.speed_error_plot(out / f"speed_error_{s.name}.png", scene_rows,
                                        f"{s.name}: time vs FLIP ({cfg.width}x{cfg.height})")

    config = {"quick": bool(opts.quick), "scenes": [s.name for s in loaded], "methods": method_specs,
              "sweep": sweep, "width": cfg.width, "height": cfg.height, "frames": cfg.frames,
              "warmup": cfg.warmup, "eval_frames": cfg.evaluated(), "seed": cfg.seed, "gt_spp": cfg.gt_spp}
    results = experiment.results_object(NAME, config, rows)
    main_rows = [r for r in rows if not r["sweep"]]
    md = (f"# {NAME}\n\n{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up), "
          f"quality on frames {cfg.evaluated()} against {cfg.gt_spp}-sample ground truth; "
          f"time = median DI ms per frame.\n\n" + experiment.markdown_table(main_rows) + "\n")
    sweep_rows = [r for r in rows if r["sweep"]]
    if sweep_rows:
        md += "\n## Speed-against-error sweep\n\n" + experiment.markdown_table(
            sweep_rows, [("scene", "scene"), ("setting", "setting"), ("time_ms", "t [ms]"), ("flip", "FLIP"),
                         ("psnr", "PSNR"), ("ssim", "SSIM")]) + "\n"
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
