"""camera-speed: error and time against camera speed (where a cache wins and loses).

One viewer per scene on the scene's first camera path, moving at 0.25x to
4x walking speed (1x = 1.4 m/s with view turns up to 30 deg/s, at 60 Hz;
``slc.scene.camera.WALK_SPEED`` / ``TURN_RATE``). A cache entry stays in view for
fewer frames the faster the camera moves, so it spends a larger share of
its life in the 8-ray start-up and averages fewer samples; per-pixel
methods (rt48) do not care, ReSTIR's temporal reuse does. Every speed runs
the same number of frames, so a faster camera covers more of the path.
Time = median DI ms per frame after the warm-up (steady state);
``startup_ms`` = median of frames 1-7 (the first frame's entries still in
start-up).

    slc run camera-speed --quick
    slc run camera-speed --speeds 0.5 1 8 --scene village
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402 (after the path of a standalone run)

from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.images import save_strip  # noqa: E402
from slc.run.pipeline import run_case  # noqa: E402
from slc.scene import views  # noqa: E402
from slc.scene.camera import FPS, TURN_RATE, WALK_SPEED  # noqa: E402

NAME = "camera-speed"
SPEEDS = [0.25, 0.5, 1.0, 2.0, 4.0]
FALLBACK_SCENE = "village"      # second scene when ../shared (Sponza) is absent
FULL = dict(scenes=["atrium", "sponza"], speeds=SPEEDS, width=320, height=180, frames=240, warmup=10,
            eval_frames=[79, 159, 239], eval_viewers=1)
QUICK = dict(scenes=["atrium", "sponza"], speeds=SPEEDS, width=96, height=54, frames=24, warmup=10,
             eval_frames=[15, 23], eval_viewers=1)
METHODS = ["slc", "rt48", "restir"]


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--speeds", type=float, nargs="+", help="camera speeds as multiples of walking speed")


def run(opts):
    pr, specs, names, cfg = ex.setup(opts, QUICK, FULL, METHODS)
    if not opts.scene and len(names) < 2 and FALLBACK_SCENE not in names:
        names += ex.load_and_validate([FALLBACK_SCENE], specs, True)
    speeds = opts.speeds or pr["speeds"]
    if any(not k > 0 for k in speeds):
        raise ex.ExperimentError("--speeds must be positive multiples of walking speed")
    out = Path(opts.out) / NAME
    rows = []
    with tqdm(total=len(names) * len(specs) * len(speeds) * cfg.frames, desc=NAME, unit="frame",
              disable=None) as bar:
        for s in ex.each_scene(names):
            for spec in specs:
                for k in speeds:
                    vs = views.at_speed(views.single(s), k)
                    row = run_case(s, spec, vs, cfg, bar, seed=opts.seed, rig="single", camera_speed=k,
                                   speed_mps=round(WALK_SPEED * k, 3), turn_rate_dps=TURN_RATE * k,
                                   path=vs[0].name)
                    save_strip(out, s, f"{row['label']}_x{k:g}", row.pop("_result"))
                    rows.append(row)
    ex.add_startup(rows)
    for name in names:
        rs = [r for r in rows if r["scene"] == name]
        plots.time_vs_viewers_plot(out / f"flip_vs_speed_{name}.png", rs,
                                f"{name}: FLIP against camera speed ({cfg.width}x{cfg.height}, 60 Hz)",
                                x="camera_speed", y="flip", ylabel="FLIP (lower is better)")
        plots.time_vs_viewers_plot(out / f"time_vs_speed_{name}.png", rs,
                                f"{name}: time against camera speed ({cfg.width}x{cfg.height}, 60 Hz)",
                                x="camera_speed")
    cols = [("scene", "scene"), ("method", "method"), ("camera_speed", "speed [x walk]"),
            ("speed_mps", "m/s"), ("time_ms", "t [ms]"), ("startup_ms", "start-up t [ms]"),
            ("compiled_after_warmup", "kernels after warm-up"),
            ("recordings_after_warmup", "recordings after warm-up"), ("flip", "FLIP"), ("psnr", "PSNR"),
            ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]
    md = (f"1x = walking speed {WALK_SPEED} m/s, view turns up to {TURN_RATE:g} deg/s, 60 Hz; every speed "
          f"renders {cfg.frames} frames of the scene's first path.\n\n" + ex.markdown_table(rows, cols)
          + "\n\n## Ratios measured in this run\n\n" + _ratios(rows, names, speeds))
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"speeds": speeds,
                                                                    "walk_speed_mps": WALK_SPEED,
                                                                    "turn_rate_dps": TURN_RATE,
                                                                    "fps": FPS})


def _ratios(rows, names, speeds) -> str:
    """slc against rt48 and restir per speed: FLIP and time ratios."""
    lines = []
    for name in names:
        by = {(r["setting"], r["camera_speed"]): r for r in rows if r["scene"] == name}
        for other in ("rt48", "restir"):
            parts = []
            for k in speeds:
                a, b = by.get(("slc", k)), by.get((other, k))
                if a and b:
                    parts.append(f"{k:g}x: FLIP {ex.ratio(a['flip'], b['flip']):.2f}, "
                                 f"time {ex.ratio(a['time_ms'], b['time_ms']):.2f}")
            if parts:
                lines.append(f"- {name}, slc / {other}: " + "; ".join(parts))
    return "\n".join(lines) + "\n" if lines else ""


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
