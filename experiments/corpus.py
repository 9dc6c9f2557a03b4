"""corpus: every built-in scene, and the user's own, for the method a user should pick.

One viewer per scene (its first camera path), the per-viewer baselines (``rt48``,
``restir``), the shared world-space grid (``regir``) and the shared surface caches
(``slc``, ``adaptive``) side by side in one process per scene, against the 2048-sample
ground truth. The built-in scenes include four written as exporters write Mitsuba XML
(``box_export``, ``lamp_export``, ``preview_export``, ``sun_export``: shapes and lights
placed by matrices, two-sided walls facing out, mirrored meshes, a light in a lamp shade,
plastic under an environment map, a lone directional light). ``--scene FILE.xml`` adds a
user's scenes to the table.

One table: FLIP, PSNR, relMSE and time (and time against ``rt48``) per scene and method,
the column "adaptive vs best rival" (adaptive's FLIP over the lowest FLIP of the other
methods), and the share of ``adaptive``'s entries in each representation.

    slc run corpus --quick [--scene my/scene.xml] [--methods rt48 slc adaptive]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.core.timing import stage_table  # noqa: E402 (after the path of a standalone run)
from slc.run import experiment as ex  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.images import strip_saver  # noqa: E402
from slc.run.pipeline import RunConfig  # noqa: E402
from slc.scene import scenes, views  # noqa: E402

NAME = "corpus"
FULL = dict(width=320, height=180, frames=120, warmup=10, eval_frames=[59, 119])
QUICK = dict(width=320, height=180, frames=24, warmup=10, eval_frames=[15, 23])
METHODS = ["rt48", "restir", "regir", "slc", "adaptive"]
RIVALS = ("rt48", "restir", "regir", "slc")      # the column "adaptive vs best rival"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)


def run(opts) -> dict:
    preset = ex.apply_common(opts, QUICK if opts.quick else FULL)
    specs = opts.methods or ex.available_methods(METHODS)
    out = Path(opts.out) / NAME
    # every built-in scene, then the user's own (--scene adds to the corpus)
    own = [s for s in (opts.scene or []) if s not in scenes.builtin_names()]
    checked = ex.load_and_validate(own + scenes.builtin_names(), specs, False)     # the user's files first
    names = checked[len(own):] + checked[:len(own)]
    cfg = RunConfig(width=preset["width"], height=preset["height"], frames=preset["frames"],
                    warmup=preset["warmup"], eval_frames=preset["eval_frames"], seed=opts.seed)

    rows = ex.run_per_scene(names, lambda s: [(spec, views.single(s), {"rig": "single"}) for spec in specs],
                            cfg, NAME, opts.seed, keep_images=True, on_result=strip_saver(out))
    summary = versus_rivals(rows)
    config = {"quick": bool(opts.quick), "scenes": names, "methods": specs, "width": cfg.width,
              "height": cfg.height, "frames": cfg.frames, "warmup": cfg.warmup, "eval_frames": cfg.evaluated(),
              "seed": cfg.seed, "gt_spp": cfg.gt_spp}
    results = ex.results_object(NAME, config, rows)
    results["summary"] = summary
    md = (f"# {NAME}\n\n{len(names)} scenes, {cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up), "
          f"quality on frames {cfg.evaluated()} against {cfg.gt_spp}-sample ground truth, time = median DI ms "
          f"per frame after the warm-up; t/rt48 = time over rt48's in the same run.\n\n"
          + ex.markdown_table(rows, [("scene", "scene"), ("label", "method"), ("time_ms", "t [ms]"),
                                     ("time_vs_rt48", "t/rt48"), ("flip", "FLIP"), ("psnr", "PSNR"),
                                     ("rel_mse", "relMSE"), ("memory_mb", "memory [MB]")]) + "\n")
    md += "\n## adaptive against the best rival\n\n" + summary_table(summary)
    md += "\n## Representation chosen by `adaptive` (share of the entries active in the last frame)\n\n" + \
        shares_table(rows)
    md += ("\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host time)\n\n"
           + stage_table(rows, ("scene", "setting")))
    ex.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


def versus_rivals(rows: list[dict]) -> list[dict]:
    """Per scene with an ``adaptive`` row: its FLIP over the lowest FLIP of the rivals
    (:data:`RIVALS` present in the run), its time over ``rt48``'s, its PSNR minus ``slc``'s.
    Also sets ``time_vs_rt48`` on every row of a scene with an ``rt48`` row."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = {r["label"]: r for r in rows if r["scene"] == scene}
        rt48 = rs.get("rt48")
        for r in rs.values():
            if rt48 and rt48.get("time_ms"):
                r["time_vs_rt48"] = r["time_ms"] / rt48["time_ms"]
        ad = rs.get("adaptive")
        rivals = {k: rs[k] for k in RIVALS if k in rs}
        if ad is None or not rivals:
            continue
        best = min(rivals, key=lambda k: rivals[k]["flip"])
        row = {"scene": scene, "best_rival": best, "best_rival_flip": rivals[best]["flip"],
               "adaptive_flip": ad["flip"],
               "flip_vs_best_rival": ad["flip"] / rivals[best]["flip"] if rivals[best]["flip"] > 0 else float("inf")}
        if rt48 and rt48.get("time_ms"):
            row["time_vs_rt48"] = ad["time_ms"] / rt48["time_ms"]
        if "slc" in rs:
            row["psnr_minus_slc"] = ad["psnr"] - rs["slc"]["psnr"]
        out.append(row)
    return out


def summary_table(summary: list[dict]) -> str:
    lines = ["| scene | best rival | its FLIP | adaptive FLIP | adaptive vs best rival | adaptive t/rt48 | "
             "adaptive PSNR - slc's [dB] |", "|---|---|---|---|---|---|---|"]
    for s in summary:
        t = f"{s['time_vs_rt48']:.2f}x" if "time_vs_rt48" in s else "-"
        p = f"{s['psnr_minus_slc']:+.2f}" if "psnr_minus_slc" in s else "-"
        lines.append(f"| {s['scene']} | {s['best_rival']} | {s['best_rival_flip']:.4f} | {s['adaptive_flip']:.4f} | "
                     f"{s['flip_vs_best_rival']:.2f}x | {t} | {p} |")
    return "\n".join(lines) + "\n"


def shares_table(rows: list[dict]) -> str:
    lines = ["| scene | method | visibility % | cones % | sh % |", "|---|---|---|---|---|"]
    for r in rows:
        if "share_visibility" in r:
            lines.append(f"| {r['scene']} | {r['label']} | {100 * r['share_visibility']:.1f} | "
                         f"{100 * r['share_cones']:.1f} | {100 * r['share_sh']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
