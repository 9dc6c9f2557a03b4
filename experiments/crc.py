"""crc: Table 1 of "Real-time Radiance Caching using Chrominance Compression".

Per scene and bounce count (1 bounce: depth occupancy; 2 bounces: geometry
occupancy), the CRC grid cache runs with occupancy off and on and with the
encodings RGB3 (27 coefficients, uncompressed), Y3Co3Cg3 (27), Y3Co2Cg2 (17)
and Y3Co1Cg1 (11), plus the "ratio" chroma decoding and Mitsuba-ray
visibility for RGB3 and Y3Co1Cg1 (and any ``--methods crc:...`` specs).
Each configuration is the registered method ``crc`` run on the same frames
through the common pipeline (:func:`slc.experiment.run_case`, one
configuration after the other). Reported per row: median cache time per
frame after warm-up (occupancy, light paths, bounces, blending,
reconstruction; voxelization is static and given separately), occupancy
ratio, CIE Lab RMSE and pdiff (percent of pixels with CIE76 dE > 2.3)
against the uncompressed cache (RGB3, same occupancy and visibility),
FLIP/PSNR/SSIM/Lab RMSE of the composited image (ground-truth direct +
cache indirect) against direct + the indirect reference at the same
G-buffer points (:func:`slc.references.reference_for`, ``"full"``), and
``indirect_*``: the pipeline's own comparison of the indirect light alone
with the indirect reference.

    python experiments/crc.py --quick
    slc run crc --quick [--scene cornell]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "crc"

FULL = dict(scenes=["cornell", "atrium", "sponza"], width=320, height=180, frames=24, warmup=4,
            eval_frames=[15, 23], bounces=[1, 2], ref_spp=512, direct_spp=512, resolution=24)
QUICK = dict(scenes=["cornell", "atrium"], width=128, height=72, frames=14, warmup=4, eval_frames=[13], bounces=[1, 2],
             ref_spp=256, direct_spp=256, resolution=16)
ENCODINGS = ["rgb3", "y3co3cg3", "y3co2cg2", "y3co1cg1"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/crc)")
    p.add_argument("--res", help="WxH (default 320x180, quick 128x72)")
    p.add_argument("--frames", type=int, help="frames per sequence")
    p.add_argument("--grid", type=int, help="CRC resolution (cells on the longest side)")
    p.add_argument("--bounces", type=int, nargs="+", help="indirect bounce counts (default 1 2)")
    p.add_argument("--march-samples", type=int, default=0,
                   help="fixed ray-march sample count (the paper's 8-12); 0 = one sample per geometry voxel")
    p.add_argument("--methods", nargs="+", metavar="SPEC",
                   help="extra configurations, e.g. crc:encoding=y3co2cg2,chroma=ratio (checked before any work)")
    p.add_argument("--seed", type=int, default=0)


def _configs(bounces: int):
    out = [dict(occupancy=occ, encoding=e, visibility="march") for occ in (False, True) for e in ENCODINGS]
    out += [dict(occupancy=True, encoding="y3co1cg1", visibility="march", chroma="ratio")]
    out += [dict(occupancy=True, encoding=e, visibility="rays") for e in ("rgb3", "y3co1cg1")]
    return out


def _plot(path, rows, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc import io
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.6))
    march = [r for r in rows if r["visibility"] == "march" and r["chroma"] == "offset"]
    for occ, off in ((False, -0.2), (True, 0.2)):
        rs = [r for r in march if r["occupancy"] == occ]
        xs = [ENCODINGS.index(r["encoding"]) + off for r in rs]
        a1.bar(xs, [r["time_ms"] for r in rs], width=0.38, label=f"occupancy {'on' if occ else 'off'}")
    a1.set_xticks(range(len(ENCODINGS)), [e.upper() for e in ENCODINGS], fontsize=7)
    a1.set_ylabel("cache time per frame [ms]")
    a1.legend(fontsize=7)
    rs = [r for r in rows if r["occupancy"] and r["visibility"] == "march"]
    a2.bar(range(len(rs)), [r["lab_rmse"] for r in rs], color="tab:red")
    a2.set_xticks(range(len(rs)), [r["encoding"].upper() + ("\nratio" if r["chroma"] == "ratio" else "")
                                   for r in rs], fontsize=7)
    a2.set_ylabel("Lab RMSE vs RGB3 [%]")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _spec(settings: dict) -> str:
    return "crc:" + ",".join(f"{k}={int(v) if isinstance(v, bool) else v}" for k, v in settings.items())


def _extra_specs(specs, nb: int, common: dict) -> list[dict]:
    """``--methods`` specs as settings, with the experiment's bounces,
    resolution and march samples unless the spec sets them."""
    from slc import methods
    out = []
    for spec in specs or []:
        name, settings = methods.parse_spec(spec)
        if name != "crc":
            raise methods.MethodError(f"the crc experiment runs the crc method only (got '{spec}')")
        out.append({**common, "bounces": nb, **settings})
    return out


def run(opts) -> dict:
    import dataclasses

    import numpy as np
    from tqdm import tqdm

    from slc import experiment, io, methods, views
    from slc.crc.grid import Grid
    from slc.crc.quality import JND_CIE76, pdiff
    from slc.metrics import evaluate, lab_rmse
    from slc.pipeline import RunConfig
    from slc.references import reference_for

    preset = dict(QUICK if opts.quick else FULL)
    if opts.res:
        w, _, h = opts.res.lower().partition("x")
        try:
            preset["width"], preset["height"] = int(w), int(h)
        except ValueError:
            raise experiment.ExperimentError(f"bad resolution '{opts.res}' (expected WxH, e.g. 320x180)") from None
    if opts.frames:
        if opts.frames < 1:
            raise experiment.ExperimentError("--frames must be at least 1")
        preset["frames"] = opts.frames
        preset["eval_frames"] = [f for f in preset["eval_frames"] if f < opts.frames] or [opts.frames - 1]
        preset["warmup"] = min(preset["warmup"], max(opts.frames - 1, 0))
    if opts.grid:
        preset["resolution"] = opts.grid
    if opts.bounces:
        preset["bounces"] = opts.bounces
    W, H = preset["width"], preset["height"]
    out = Path(opts.out) / NAME
    common = dict(resolution=preset["resolution"], march_samples=getattr(opts, "march_samples", 0) or 0)

    # ----------------- validate everything before any work -----------------
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    cfg = RunConfig(width=W, height=H, frames=preset["frames"], warmup=preset["warmup"],
                    eval_frames=preset["eval_frames"], seed=opts.seed, ref_spp=preset["ref_spp"],
                    keep_images=False, measure_overlap=False)
    plans = {nb: [{**common, "bounces": nb, **c} for c in _configs(nb)] + _extra_specs(opts.methods, nb, common)
             for nb in preset["bounces"]}

    rows = []
    total = len(names) * sum(len(p) for p in plans.values()) * preset["frames"]
    with tqdm(total=total, desc=NAME, unit="frame", disable=None) as bar:
        for s in experiment.each_scene(names):
            viewers = views.single(s)
            made = {nb: [methods.create(_spec(c), s, seed=opts.seed) for c in plan] for nb, plan in plans.items()}
            for nb, plan in plans.items():
                group, finals = [], []
                for c, m in zip(plan, made[nb]):
                    # --- one configuration through the common pipeline; the hook keeps the
                    # composited images (direct ground truth + indirect) of the evaluated frames ---
                    composed = {}

                    def on_eval(f, v, gb, img, ref, composed=composed):
                        direct = reference_for("direct", s, gb, f, gb.viewer, spp=preset["direct_spp"])
                        composed[f] = (direct + img, direct + ref)

                    row = experiment.run_case(s, _spec(c), viewers, dataclasses.replace(cfg, on_eval=on_eval),
                                              bar, seed=opts.seed)
                    res = row.pop("_result")
                    st = m.settings()
                    for k in res.metrics:   # the pipeline's comparison: indirect light alone
                        row["indirect_" + k] = row.pop(k)
                    acc = {}
                    for f, (final, ref_full) in sorted(composed.items()):
                        q = evaluate(ref_full, final, s.exposure)
                        q["lab_rmse_ref"] = q.pop("lab_rmse")
                        for k, v in q.items():
                            acc.setdefault(k, []).append(v)
                    row.update({k: float(np.mean(v)) for k, v in acc.items()})
                    row.update({"encoding": st["encoding"], "occupancy": st["occupancy"],
                                "visibility": st["visibility"], "bounces": st["bounces"], "chroma": st["chroma"],
                                "coefficients": m.enc.n,
                                "grid": list(Grid.around(s.bbox_min, s.bbox_max, st["resolution"]).dims)})
                    group.append(row)
                    finals.append(composed)
                # ------------------- against the RGB3 cache (the paper's comparison) -------------------
                for r, fin in zip(group, finals):
                    base = next((j for j, x in enumerate(group) if x["occupancy"] == r["occupancy"]
                                 and x["visibility"] == r["visibility"] and x["encoding"] == "rgb3"
                                 and x["chroma"] == "offset"), None)
                    if base is None:
                        continue
                    fb = finals[base]
                    r["lab_rmse"] = float(np.mean([lab_rmse(fb[f][0], fin[f][0], s.exposure) for f in fin]))
                    r["pdiff"] = float(np.mean([pdiff(fb[f][0], fin[f][0], s.exposure) for f in fin]))
                unopt = next(r for r in group if not r["occupancy"] and r["encoding"] == "rgb3")
                for r in group:
                    same = next((x for x in group if x["occupancy"] == r["occupancy"] and x["chroma"] == "offset"
                                 and x["visibility"] == r["visibility"] and x["encoding"] == "rgb3"), None)
                    r["time_vs_rgb3"] = r["time_ms"] / max(same["time_ms"], 1e-9) if same else None
                    r["time_vs_unoptimized"] = r["time_ms"] / max(unopt["time_ms"], 1e-9)
                rows += group
                # ------------------------------ images ------------------------------
                stem = out / "images" / f"{s.name}_b{nb}"
                last = max(finals[0])
                io.write_hdr_and_png(stem.with_name(stem.name + "_reference"), finals[0][last][1], s.exposure)
                for r, fin in zip(group, finals):
                    if r["occupancy"] and r["visibility"] == "march" and r["encoding"] in ("rgb3", "y3co1cg1"):
                        tag = r["encoding"] + ("_ratio" if r["chroma"] == "ratio" else "")
                        io.write_hdr_and_png(stem.with_name(f"{stem.name}_{tag}"), fin[last][0], s.exposure)
                _plot(out / f"crc_{s.name}_b{nb}.png", group, f"{s.name}, {nb} bounce(s), {W}x{H}")

    config = {"quick": bool(opts.quick), "scenes": names, **preset, "seed": opts.seed,
              "march_samples": getattr(opts, "march_samples", 0) or 0,
              "pdiff": f"percent of pixels with CIE76 dE > {JND_CIE76} against the RGB3 cache",
              "lab_rmse": "CIE Lab RMSE (percent) against the RGB3 cache; lab_rmse_ref against the reference",
              "reference": "slc.references: indirect reference (the method's bounces) + ground-truth direct light",
              "indirect_metrics": "indirect_*: the pipeline's comparison of the indirect light alone with the "
                                  "indirect reference (exposure 0.8 / p99 of the reference)"}
    results = experiment.results_object(NAME, config, experiment.strip_private(rows))
    cols = [("scene", "scene"), ("bounces", "bounces"), ("visibility", "visibility"), ("occupancy", "occupancy"),
            ("encoding", "encoding"), ("chroma", "chroma"), ("coefficients", "coeffs"),
            ("occupancy_ratio", "occ. ratio"),
            ("time_ms", "t [ms]"), ("time_vs_rgb3", "t / RGB3"), ("time_vs_unoptimized", "t / unopt."),
            ("lab_rmse", "Lab RMSE vs RGB3 [%]"), ("pdiff", "pdiff [%]"), ("lab_rmse_ref", "Lab RMSE vs ref [%]"),
            ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]
    md = (f"# {NAME}\n\n{W}x{H}, {preset['frames']} frames ({preset['warmup']} warm-up), grid resolution "
          f"{preset['resolution']}; t = median cache ms per frame (voxelization excluded); Lab RMSE and pdiff "
          f"(CIE76 dE > {JND_CIE76}) against the uncompressed RGB3 cache; FLIP/PSNR/SSIM of ground-truth direct + "
          f"cache indirect against the reference ({preset['ref_spp']} spp indirect (slc.references) + "
          f"{preset['direct_spp']} spp direct); indirect_* in results.json: indirect light alone against the "
          f"indirect reference (the pipeline's comparison).\n\n"
          + experiment.markdown_table(rows, cols) + "\n")
    md += "\n## Targets\n\n"
    for name in names:
        for nb in preset["bounces"]:
            g = [r for r in rows if r["scene"] == name and r["bounces"] == nb and r["visibility"] == "march"]
            y1r = next(r for r in g if r["occupancy"] and r["chroma"] == "ratio")
            g = [r for r in g if r["chroma"] == "offset"]
            y1 = next(r for r in g if r["occupancy"] and r["encoding"] == "y3co1cg1")
            on = next(r for r in g if r["occupancy"] and r["encoding"] == "rgb3")
            off = next(r for r in g if not r["occupancy"] and r["encoding"] == "rgb3")
            md += (f"- {name}, {nb} bounce(s): Y3Co1Cg1 / RGB3 time = {y1['time_vs_rgb3']:.2f} (target <= 0.75), "
                   f"Lab RMSE {y1['lab_rmse']:.3f}% (target < 1%); occupancy on/off time = "
                   f"{on['time_ms'] / max(off['time_ms'], 1e-9):.2f} at occupancy ratio "
                   f"{on['occupancy_ratio']:.2f}; all optimizations / unoptimized = {y1['time_vs_unoptimized']:.2f}; "
                   f"with ratio chroma decoding: time {y1r['time_vs_rgb3']:.2f}, Lab RMSE {y1r['lab_rmse']:.3f}%, "
                   f"pdiff {y1r['pdiff']:.2f}%\n")
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
