"""Scene-variant sweeps (many-lights, envmap, point-lights): every method on every variant of
a scene (:func:`variant_experiment`), e.g. the variants of one scene option given on the
command line (:func:`scene_option_sweep`), with their tables, plots and image strips.
"""
from __future__ import annotations

from pathlib import Path

from slc.core.timing import stage_table
from slc.run.experiment import (DEFAULT_COLUMNS, add_startup, apply_common, available_methods, each_scene,
                                load_and_validate, markdown_table, results_object, run_cases, strip_private,
                                write_results)
from slc.run.images import save_strip
from slc.run.pipeline import RunConfig
from slc.run.plots import metric_vs_value_plot, speed_error_plot
from slc.scene import views


def variant_experiment(opts, name: str, preset: dict, specs: list[str], variants: list[tuple], field: str,
                       title: str) -> dict:
    """Every method on every scene variant, one viewer on the scene's first
    path. ``variants``: (value, scene spec) pairs, e.g. ``(24, "hangar:lights=24")``;
    rows carry the value in ``field``. Writes results.json/results.md, a
    FLIP-and-time-against-``field`` plot, a speed-against-error plot per
    variant and an image strip per (variant, method)."""
    out = Path(opts.out) / name
    scene_specs = load_and_validate([v for _, v in variants], specs, True)
    value_of = {s: v for v, s in variants}
    cfg = RunConfig(width=preset["width"], height=preset["height"], frames=preset["frames"],
                    warmup=preset["warmup"], eval_frames=preset["eval_frames"], seed=opts.seed)
    rows = []
    for s in each_scene(scene_specs):
        case_rows = run_cases([(s, spec, views.single(s), {field: value_of[s.name], "rig": "single"})
                               for spec in specs], cfg, f"{name} {s.name}", opts.seed, keep=True)
        for r in case_rows:
            r["family"] = r["method"].rstrip("0123456789") or r["method"]
            save_strip(out, s, r["label"], r.pop("_result"))
        speed_error_plot(out / f"speed_error_{s.name.replace(':', '_').replace('=', '')}.png", case_rows,
                         f"{s.name}: time vs FLIP ({cfg.width}x{cfg.height})")
        rows += case_rows
    add_startup(rows)
    metric_vs_value_plot(out / f"flip_time_vs_{field}.png", rows, field, title)
    columns = DEFAULT_COLUMNS[:1] + [(field, field)] + [("setting", "method")] + DEFAULT_COLUMNS[3:4] + \
        [("startup_ms", "start-up [ms]"), ("compiled_after_warmup", "kernels after warm-up"),
         ("recordings_after_warmup", "recordings after warm-up")] + DEFAULT_COLUMNS[4:]
    md = (f"# {name}\n\n{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up), one viewer; "
          f"quality on frames {cfg.evaluated()} against {cfg.gt_spp}-sample ground truth; time = median DI ms "
          f"per frame.\n\n" + markdown_table(rows, columns) + "\n"
          + "\n## Where the time goes (median ms per stage; kernel execution in brackets, the rest is host time)\n\n"
          + stage_table(rows, ("scene", "setting")))
    config = {"quick": bool(opts.quick), "methods": specs, "variants": [list(v) for v in variants],
              "width": cfg.width, "height": cfg.height, "frames": cfg.frames, "warmup": cfg.warmup,
              "eval_frames": cfg.evaluated(), "seed": cfg.seed, "gt_spp": cfg.gt_spp}
    results = results_object(name, config, strip_private(rows))
    write_results(out, results, md)
    print(md)
    return results


def scene_option_sweep(opts, name: str, quick: dict, full: dict, methods: list[str], option: str,
                       title: str) -> dict:
    """:func:`variant_experiment` over ``SCENE:option=value`` for the values
    given on the command line (``opts.<option>``) or in the preset."""
    pr = apply_common(opts, quick if opts.quick else full)
    scene = (opts.scene or [pr["scene"]])[0]
    variants = [(v, f"{scene}:{option}={v}") for v in (getattr(opts, option, None) or pr[option])]
    specs = opts.methods or available_methods(methods)
    return variant_experiment(opts, name, pr, specs, variants, option, title)
