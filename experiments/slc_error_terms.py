"""slc-error-terms: where Surface Light Cones' error comes from.

Controlled runs of ``slc`` on one viewer, each removing one error term, all
against the 2048-sample ground truth at the same G-buffer points:

- **cache resolution** (a): the converged cones (``rays_new = rays_settled =
  CONVERGED_RAYS``) on the on-surface cache against the same on a cache with one
  entry per pixel (:class:`slc.methods.cones.pixelcache.PixelSlotCache`, the pixel's own
  surface point; still camera only, the stand-in keeps frame 0's pixels);
- **cone representation** (b): the converged one-entry-per-pixel cache alone
  (what is left when every other term is gone: cones of uniform radiance and
  the shading's quadrature);
- **variance of young and settled entries** (c): the default ray policy against
  the converged one on the same camera (still and walking), and the per-pixel
  FLIP of the default run binned by the age (updates so far) of the pixel's entry;
- **fetch** (d): every run with the nearest and the bilinear fetch.

``rt48`` is run beside them as the yardstick. The still camera holds the
path's first pose; the walking camera follows the path at 1.4 m/s (60 Hz).

    slc run slc-error-terms --quick [--scene atrium] [--settings slc:rays_new=32,rays_settled=8]
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
from slc.core.keys import INVALID  # noqa: E402
from slc.methods.cones.pixelcache import PixelSlotCache  # noqa: E402
from slc.reference import references  # noqa: E402
from slc.reference.metrics import evaluate  # noqa: E402
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.pipeline import RunConfig, run_sequence  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "slc-error-terms"
CONVERGED_RAYS = 64          # rays per entry and frame of the "converged" runs
AGE_BINS = [(1, 1), (2, 3), (4, 7), (8, 15), (16, 31), (32, 10 ** 9)]
FULL = dict(scenes=["atrium", "sponza"], width=320, height=180, frames=48, warmup=10, eval_frames=[31, 47])
QUICK = dict(scenes=["atrium"], width=160, height=90, frames=24, warmup=10, eval_frames=[15, 23])


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--settings", nargs="*", default=[],
                   help="extra slc settings to run on both cameras with the age histogram (e.g. "
                        "slc:rays_new=32,rays_settled=8)")


def _cases(extra):
    """(camera, label, spec, pixel cache?) of every controlled run."""
    conv = f"rays_new={CONVERGED_RAYS},rays_settled={CONVERGED_RAYS},rays_moving={CONVERGED_RAYS}"
    cases = []
    for cam in ("still", "walking"):
        cases.append((cam, "rt48", "rt48", False))
        for fetch in ("nearest", "bilinear"):
            cases.append((cam, f"default/{fetch}", f"slc:fetch={fetch}", False))
            cases.append((cam, f"converged/{fetch}", f"slc:fetch={fetch},{conv}", False))
        if cam == "still":
            cases.append((cam, "per-pixel default", "slc", True))
            cases.append((cam, "per-pixel converged", f"slc:{conv}", True))
        for spec in extra:
            cases.append((cam, spec, spec, False))
    return cases


def _age_histogram(method, gb, img, gt, exposure, acc):
    """Per-pixel FLIP of ``img`` binned by the age (completed updates) of the
    pixel's entry; accumulates (pixels, FLIP sum) per bin into ``acc``."""
    fmap = evaluate(gt, img, exposure, with_map=True)["flip_map"].reshape(-1)
    slot = mi.UInt32(method.requests.pixel_slot[0])
    ok = slot != INVALID
    age = np.asarray(dr.select(ok, dr.gather(mi.UInt32, method.policy_state, slot, ok) & 0xFFFF, 0))
    for i, (lo, hi) in enumerate(AGE_BINS):
        m = (age >= lo) & (age <= hi)
        a = acc.setdefault(i, [0, 0.0])
        a[0] += int(m.sum())
        a[1] += float(fmap[m].sum())


def run(opts):
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    extra = list(opts.settings or [])
    cases = _cases(extra)
    names = ex.load_and_validate(opts.scene or pr["scenes"], sorted({c[2] for c in cases}), bool(opts.scene))
    cfg = RunConfig(width=pr["width"], height=pr["height"], frames=pr["frames"], warmup=pr["warmup"],
                    eval_frames=pr["eval_frames"], seed=opts.seed)
    out = Path(opts.out) / NAME
    rows = []
    with tqdm(total=len(names) * len(cases) * cfg.frames, desc=NAME, unit="frame", disable=None) as bar:
        for s in ex.each_scene(names):
            walk = views.single(s)
            cams = {"walking": walk, "still": [replace(walk[0], speed=0.0)]}
            for cam, label, spec, per_pixel in cases:
                kw = {"cache": PixelSlotCache()} if per_pixel else {}
                m = methods.create(spec, s, seed=opts.seed, **kw)
                acc = {}
                if spec.startswith("slc") and not per_pixel:
                    def on_eval(f, v, gb, img, gt, m=m, acc=acc):
                        _age_histogram(m, gb, img, gt, references.exposure_for("direct", s, gt), acc)
                    run_cfg = replace(cfg, on_eval=on_eval, keep_images=False)
                else:
                    run_cfg = replace(cfg, keep_images=False)
                res = run_sequence(s, m, cams[cam], run_cfg, progress=bar)
                row = {"scene": s.name, "camera": cam, "case": label, "setting": spec, "per_pixel": per_pixel,
                       **{k: res.metrics.get(k) for k in ("flip", "psnr", "ssim", "rel_mse")},
                       "time_ms": res.time_ms, "compiled_after_warmup": res.compiled_after_warmup}
                if acc:
                    tot = sum(a[0] for a in acc.values()) or 1
                    row["age_bins"] = [{"ages": f"{lo}-{hi}" if hi < 10 ** 9 else f">={lo}",
                                        "share": acc[i][0] / tot,
                                        "flip": acc[i][1] / acc[i][0] if acc[i][0] else None}
                                       for i, (lo, hi) in enumerate(AGE_BINS)]
                rows.append(row)
                del m
    md = _report(rows, cfg)
    _plot(out, rows)
    return ex.finish(NAME, out, opts, cfg, names, sorted({c[2] for c in cases}), rows, md,
                     {"converged_rays": CONVERGED_RAYS, "age_bins": AGE_BINS})


def _report(rows, cfg) -> str:
    md = ex.markdown_table(rows, [("scene", "scene"), ("camera", "camera"), ("case", "run"), ("time_ms", "t [ms]"),
                                  ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("rel_mse", "relMSE")]) + "\n"
    md += "\n## Error terms (FLIP differences between the controlled runs)\n\n"
    for scene in dict.fromkeys(r["scene"] for r in rows):
        by = {(r["camera"], r["case"]): r["flip"] for r in rows if r["scene"] == scene}
        g = by.get
        lines = []
        if g(("still", "per-pixel converged")) is not None:
            lines.append(f"- {scene}, still: representation (per-pixel converged) {g(('still', 'per-pixel converged')):.4f}; "
                         f"+ cache resolution (OSC converged, nearest) {g(('still', 'converged/nearest')):.4f}; "
                         f"+ variance (default, nearest) {g(('still', 'default/nearest')):.4f}; rt48 {g(('still', 'rt48')):.4f}")
        for cam in ("still", "walking"):
            if g((cam, "default/nearest")) is None:
                continue
            lines.append(f"- {scene}, {cam}: variance term (default - converged) nearest "
                         f"{g((cam, 'default/nearest')) - g((cam, 'converged/nearest')):+.4f}, bilinear "
                         f"{g((cam, 'default/bilinear')) - g((cam, 'converged/bilinear')):+.4f}; fetch term "
                         f"(bilinear - nearest) default {g((cam, 'default/bilinear')) - g((cam, 'default/nearest')):+.4f}, "
                         f"converged {g((cam, 'converged/bilinear')) - g((cam, 'converged/nearest')):+.4f}")
        md += "\n".join(lines) + "\n"
    md += "\n## Per-pixel FLIP against the age of the pixel's entry (updates so far)\n\n"
    md += "| scene | camera | run | " + " | ".join(f"age {lo}-{hi}" if hi < 10 ** 9 else f"age >= {lo}"
                                              for lo, hi in AGE_BINS) + " |\n"
    md += "|---|---|---|" + "---|" * len(AGE_BINS) + "\n"
    for r in rows:
        if "age_bins" in r:
            cells = [f"{b['flip']:.3f} ({100 * b['share']:.0f} %)" if b["flip"] is not None else "-"
                     for b in r["age_bins"]]
            md += f"| {r['scene']} | {r['camera']} | {r['case']} | " + " | ".join(cells) + " |\n"
    md += ("\nCells: mean per-pixel FLIP of the pixels whose entry has that age (share of the pixels). "
           f"Converged = {CONVERGED_RAYS} rays per entry and frame.\n")
    return md


def _plot(out: Path, rows):
    plt = plots.pyplot()
    out.mkdir(parents=True, exist_ok=True)
    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
        for r in rows:
            if r["scene"] != scene or "age_bins" not in r:
                continue
            xs = [i for i, b in enumerate(r["age_bins"]) if b["flip"] is not None]
            ax.plot(xs, [r["age_bins"][i]["flip"] for i in xs], marker="o", label=f"{r['camera']}: {r['case']}")
        for r in rows:
            if r["scene"] == scene and r["case"] == "rt48":
                ax.axhline(r["flip"], ls="--", lw=0.8, color="k" if r["camera"] == "walking" else "gray",
                           label=f"rt48 ({r['camera']}, image mean)")
        ax.set_xticks(range(len(AGE_BINS)))
        ax.set_xticklabels([f"{lo}-{hi}" if hi < 10 ** 9 else f">={lo}" for lo, hi in AGE_BINS])
        ax.set_xlabel("age of the pixel's entry (updates)")
        ax.set_ylabel("mean per-pixel FLIP")
        ax.set_title(f"{scene}: slc error against entry age")
        ax.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(out / f"flip_vs_age_{scene}.png")
        plt.close(fig)


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
