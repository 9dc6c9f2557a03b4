"""single-viewer: Table 1 of the Surface Light Cones paper.

One viewer per scene on a camera path; every method shades the same
G-buffer points; caches are carried across frames; quality is measured
against 2048-sample ground truth on the evaluated frames and time is the
median DI time per frame after warm-up. A sweep of settings per scene
feeds the speed-against-error plot.

    python experiments/single_viewer.py --quick
    slc run single-viewer --quick [--scene atrium] [--methods rt16 rt48]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.core.timing import stage_table  # noqa: E402 (after the path of a standalone run)
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.images import strip_saver  # noqa: E402
from slc.run.pipeline import RunConfig  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "single-viewer"

# 60 Hz paths at walking speed: the full preset renders 4 s (240 frames); the warm-up (10 frames) covers
# kernel builds and the start-up of the first frame's entries (the rays of a new entry, under the per-frame
# ray budget), so time_ms is the steady state and
# startup_ms (frames 1-7) the start-up
FULL = dict(scenes=["atrium", "street", "village", "garden", "sponza"], width=320, height=180,
            frames=240, warmup=10, eval_frames=[79, 159, 239],
            sweep=["rt4", "rt8", "rt32", "slc:rays_settled=2", "slc:max_cones=2", "slc:bias=0.5", "slc:bias=2"])
QUICK = dict(scenes=["atrium"], width=160, height=90, frames=24, warmup=10, eval_frames=[15, 23],
             sweep=["rt4"])
BASE_METHODS = ["rt16", "rt48", "restir", "regir", "slc", "slc:fetch=bilinear"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)
    p.add_argument("--sweep", nargs="*", help="extra settings for the speed-against-error plot")


def run(opts) -> dict:
    preset = ex.apply_common(opts, QUICK if opts.quick else FULL)
    method_specs = opts.methods or ex.available_methods(BASE_METHODS)
    sweep = ex.available_methods(preset["sweep"]) if opts.sweep is None else opts.sweep
    sweep = [s for s in sweep if s not in method_specs]
    out = Path(opts.out) / NAME
    names = ex.load_and_validate(opts.scene or preset["scenes"], method_specs + sweep, bool(opts.scene))

    cfg = RunConfig(width=preset["width"], height=preset["height"], frames=preset["frames"],
                    warmup=preset["warmup"], eval_frames=preset["eval_frames"], seed=opts.seed)

    # one job per scene: every method of the comparison in the same process (docs/experiments.md)
    rows = ex.run_per_scene(names, lambda s: [(spec, views.single(s), {"rig": "single", "sweep": spec in sweep})
                                              for spec in method_specs + sweep],
                            cfg, NAME, opts.seed, keep_images=True, on_result=strip_saver(out))
    for row in rows:
        row["family"] = row["method"].rstrip("0123456789") or row["method"]
    ex.add_startup(rows)
    for scene in dict.fromkeys(r["scene"] for r in rows):
        plots.speed_error_plot(out / f"speed_error_{scene}.png", [r for r in rows if r["scene"] == scene],
                            f"{scene}: time vs FLIP ({cfg.width}x{cfg.height})")

    config = {"quick": bool(opts.quick), "scenes": names, "methods": method_specs,
              "sweep": sweep, "width": cfg.width, "height": cfg.height, "frames": cfg.frames,
              "warmup": cfg.warmup, "eval_frames": cfg.evaluated(), "seed": cfg.seed, "gt_spp": cfg.gt_spp}
    results = ex.results_object(NAME, config, rows)
    md = (f"# {NAME}\n\n{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up), "
          f"quality on frames {cfg.evaluated()} against {cfg.gt_spp}-sample ground truth; "
          f"time = median DI ms per frame after the warm-up (steady state); start-up = median of frames 1-7 "
          f"(the first frame's cache entries still new: more rays per entry, capped by the ray budget). Camera at walking speed "
          f"(1.4 m/s, 60 Hz).\n\n" + ex.markdown_table(
              [r for r in rows if not r["sweep"]], [("setting", "method") if k == "method" else (k, h)
                                                    for k, h in ex.DEFAULT_COLUMNS[:4]]
              + [("startup_ms", "start-up t [ms]"), ("compiled_after_warmup", "kernels after warm-up"),
                 ("recordings_after_warmup", "recordings after warm-up")]
              + ex.DEFAULT_COLUMNS[4:]) + "\n")
    md += _targets(rows)
    md += ("\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host time)\n\n"
           + stage_table([r for r in rows if not r["sweep"]], ("scene", "setting")))
    sweep_rows = [r for r in rows if r["sweep"]]
    if sweep_rows:
        md += "\n## Speed-against-error sweep\n\n" + ex.markdown_table(
            sweep_rows, [("scene", "scene"), ("setting", "setting"), ("time_ms", "t [ms]"), ("flip", "FLIP"),
                         ("psnr", "PSNR"), ("ssim", "SSIM")]) + "\n"
    ex.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


def _targets(rows) -> str:
    """The issue's targets as ratios measured in this run."""
    lines = []
    by = {(r["scene"], r["setting"]): r for r in rows}
    for scene in sorted({r["scene"] for r in rows}):
        rt48, restir = by.get((scene, "rt48")), by.get((scene, "restir"))
        for setting in ("slc", "slc:fetch=bilinear"):
            slc_r = by.get((scene, setting))
            if not (slc_r and rt48):
                continue
            t = slc_r["time_ms"] / rt48["time_ms"] if rt48["time_ms"] else float("nan")
            f = slc_r["flip"] / rt48["flip"] if rt48["flip"] else float("nan")
            best = max((r for r in rows if r["scene"] == scene and not r["sweep"]), key=lambda r: r["ssim"])
            lines.append(f"- {scene}: {setting}/rt48 time {t:.2f}x (target <= {0.67 if scene == 'street' else 0.33:.2f}x), "
                         f"FLIP {f:.2f}x (target <= 1.05x), best SSIM: {best['setting']} ({best['ssim']:.3f})")
        ad = by.get((scene, "adaptive"))
        if ad and rt48:
            t = ad["time_ms"] / rt48["time_ms"] if rt48["time_ms"] else float("nan")
            f = ad["flip"] / rt48["flip"] if rt48["flip"] else float("nan")
            tgt = " (target on the street: <= 0.4x at FLIP <= 0.7x)" if scene == "street" else ""
            lines.append(f"- {scene}: adaptive/rt48 time {t:.2f}x, FLIP {f:.2f}x{tgt}")
        slc_r = by.get((scene, "slc"))
        if slc_r and restir:
            lines.append(f"- {scene}: restir/slc time {restir['time_ms'] / max(slc_r['time_ms'], 1e-9):.2f}x "
                         f"(paper: 1.5-2x), FLIP slc {slc_r['flip']:.4f} vs restir {restir['flip']:.4f}")
        if restir and rt48:
            lines.append(f"- {scene}: restir/rt48 time {restir['time_ms'] / max(rt48['time_ms'], 1e-9):.2f}x, "
                         f"FLIP restir {restir['flip']:.4f} vs rt48 {rt48['flip']:.4f}")
    return ("\n## Targets (ratios measured in this run)\n\n" + "\n".join(lines) + "\n") if lines else ""


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
