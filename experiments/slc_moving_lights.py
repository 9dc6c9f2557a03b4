"""slc-moving-lights: where Surface Light Cones' error sits under moving lights.

One viewer on ``street`` (two emissive spheres drifting along the street at up
to 7.7 m/s, a tumbling emissive cube, cars): every frame is compared with the
ground truth (``--gt-spp``, 512 by default: the per-frame curve compares
settings, the Table-1 figures come from single-viewer), and the cache's state
is recorded per frame: the share of entries in the moving state (C capped,
``rays_moving`` rays), the share that reported motion this frame, and the
mean accumulation count C of the viewer's entries. Controlled variants switch
one mechanism at a time:

- ``converged``: 64 rays per entry and frame (variance gone: what is left is
  lag, detection and representation);
- ``shrink_period=1``: settled entries run the shrink test every frame
  (stale cones of a light that left are found 4x sooner);
- ``multi_cycles``-like forgetting via ``rays_moving``: moving entries' memory is 8 cycles of
  ``rays_moving`` samples;
- ``beta_min``: the smallest cone turn (degrees) that counts as motion;
- ``adaptive``: the lights listed per entry (spheres and the cube as polygon lights), their
  unoccluded light exact at the pixel in every frame, only visibility learnt: its per-frame
  curve is the lag of the visible fractions alone.

    slc run slc-moving-lights --quick [--methods slc slc:shrink_period=1 ...]
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import drjit as dr  # noqa: E402 (after the path of a standalone run)
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from slc import methods  # noqa: E402
from slc.lib.cones.packing import gather_words, unpack  # noqa: E402
from slc.reference import references  # noqa: E402
from slc.reference.metrics import evaluate  # noqa: E402
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.pipeline import RunConfig, run_sequence  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "slc-moving-lights"
FULL = dict(scenes=["street"], width=320, height=180, frames=64, warmup=10)
QUICK = dict(scenes=["street"], width=160, height=90, frames=32, warmup=10)
METHODS = ["rt48", "restir", "slc", "slc:rays_new=64,rays_settled=64,rays_moving=64", "slc:shrink_period=1",
           "slc:beta_min=0.25", "adaptive"]


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--gt-spp", type=int, default=512, help="ground-truth samples per pixel of the per-frame curve")


def _cache_state(m) -> dict:
    """Moving share, motion share and mean C of the entries of viewer 0's pixels."""
    fr = m.requests
    if fr is None or fr.n_active == 0:
        return {}
    st = np.asarray(dr.gather(mi.UInt32, m.policy_state, fr.active))
    _, A, _, C, n = unpack(gather_words(m.storage, fr.active, m.max_cones), m.max_cones)
    n = np.asarray(n)
    live = np.stack([n > i for i in range(m.max_cones)])
    alpha = np.stack([np.asarray(a) for a in A])
    s = m.stats()
    return {"moving_share": float(np.mean((st >> 16) > 0)), "motion_share": s.get("motion_entries", 0.0) / fr.n_active,
            "mean_C": float(np.mean(np.asarray(C))), "mean_cones": float(np.mean(n)),
            "mean_alpha_deg": float(np.degrees(alpha[live].mean())) if live.any() else 0.0,
            "shrunk_share": s.get("shrunk_entries", 0.0) / fr.n_active,
            "dropped_share": s.get("dropped_entries", 0.0) / fr.n_active}


def run(opts):
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    specs = opts.methods or METHODS
    names = ex.load_and_validate(opts.scene or pr["scenes"], specs, bool(opts.scene))
    cfg = RunConfig(width=pr["width"], height=pr["height"], frames=pr["frames"], warmup=pr["warmup"],
                    eval_frames=list(range(pr["frames"])), seed=opts.seed, gt_spp=opts.gt_spp, keep_images=False)
    out = Path(opts.out) / NAME
    rows = []
    with tqdm(total=len(names) * len(specs) * cfg.frames, desc=NAME, unit="frame", disable=None) as bar:
        for s in ex.each_scene(names):
            for spec in specs:
                m = methods.create(spec, s, seed=opts.seed)
                per_frame = []

                def on_eval(f, v, gb, img, gt, m=m, per_frame=per_frame):
                    e = evaluate(gt, img, references.exposure_for("direct", s, gt))
                    rec = {"frame": f, "flip": e["flip"], "rel_mse": e["rel_mse"]}
                    if spec.startswith("slc"):
                        rec.update(_cache_state(m))
                    per_frame.append(rec)
                res = run_sequence(s, m, views.single(s), replace(cfg, on_eval=on_eval), progress=bar)
                late = [r for r in per_frame if r["frame"] >= cfg.warmup]
                rows.append({"scene": s.name, "setting": spec, "time_ms": res.time_ms,
                             "flip": sum(r["flip"] for r in late) / max(len(late), 1),
                             "compiled_after_warmup": res.compiled_after_warmup, "per_frame": per_frame,
                             **{k: sum(r.get(k, 0.0) for r in late) / max(len(late), 1)
                                for k in ("moving_share", "motion_share", "mean_C", "mean_alpha_deg")}})
                del m
    _plot(out, rows)
    md = ex.markdown_table(rows, [("scene", "scene"), ("setting", "setting"), ("time_ms", "t [ms]"),
                                  ("flip", "FLIP (mean of frames after warm-up)"),
                                  ("moving_share", "entries moving"), ("motion_share", "motion reported / frame"),
                                  ("mean_C", "mean C"), ("mean_alpha_deg", "mean cone angle [deg]")]) + "\n"
    md += (f"\nPer-frame FLIP against a {opts.gt_spp}-sample ground truth, frames {cfg.warmup}-{cfg.frames - 1}; "
           f"per-frame curves in per_frame_*.png and results.json.\n")
    return ex.finish(NAME, out, opts, cfg, names, specs, rows, md, {"gt_spp": opts.gt_spp})


def _plot(out: Path, rows):
    plt = plots.pyplot()
    out.mkdir(parents=True, exist_ok=True)
    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, axs = plt.subplots(3, 1, figsize=(6.4, 8.0), dpi=120, sharex=True)
        for r in rows:
            if r["scene"] != scene:
                continue
            fs = [p["frame"] for p in r["per_frame"]]
            line, = axs[0].plot(fs, [p["flip"] for p in r["per_frame"]], label=r["setting"])
            if r["setting"].startswith("slc"):
                axs[1].plot(fs, [p.get("moving_share", 0.0) for p in r["per_frame"]], color=line.get_color())
                axs[2].plot(fs, [p.get("mean_alpha_deg", 0.0) for p in r["per_frame"]], color=line.get_color())
        axs[0].set_ylabel("FLIP")
        axs[1].set_ylabel("share of entries moving")
        axs[2].set_ylabel("mean cone half-angle [deg]")
        axs[2].set_xlabel("frame")
        axs[0].legend(fontsize=6)
        axs[0].set_title(f"{scene}: per-frame error and motion state")
        fig.tight_layout()
        fig.savefig(out / f"per_frame_{scene}.png")
        plt.close(fig)


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
