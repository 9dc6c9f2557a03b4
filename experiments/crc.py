"""crc: Table 1 of "Real-time Radiance Caching using Chrominance Compression".

Per scene and bounce count (1 bounce: depth occupancy; 2 bounces: geometry
occupancy), the CRC grid cache runs with occupancy off and on and with the
encodings RGB3 (27 coefficients, uncompressed), Y3Co3Cg3 (27), Y3Co2Cg2 (17)
and Y3Co1Cg1 (11), side by side on the same frames (every configuration
renders each frame in turn, so machine load affects all alike), plus
Mitsuba-ray visibility for RGB3 and Y3Co1Cg1. Reported per row: median
cache time per frame after warm-up (occupancy, light paths, bounces,
blending, reconstruction; voxelization is static and given separately),
occupancy ratio, CIE Lab RMSE and pdiff (percent of pixels with CIE76
dE > 2.3) against the uncompressed cache (RGB3, same occupancy and
visibility), and FLIP/PSNR/SSIM/Lab RMSE of the composited image (direct +
indirect) against a path-traced reference of the diffuse indirect light at
the same G-buffer points (plus the same direct light).

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
    io._atomic(path, lambda p: fig.savefig(p, dpi=120, format="png"))
    plt.close(fig)


def run(opts) -> dict:
    import numpy as np
    from tqdm import tqdm

    from slc import experiment, io, views
    from slc.crc import CRCCache
    from slc.crc.quality import JND_CIE76, pdiff
    from slc.crc.reference import reference_indirect
    from slc.gbuffer import to_image
    from slc.groundtruth import ground_truth
    from slc.metrics import evaluate, lab_rmse
    from slc.pipeline import gbuffers_for
    from slc.timing import StageTimer

    preset = dict(QUICK if opts.quick else FULL)
    if opts.res:
        w, _, h = opts.res.lower().partition("x")
        preset["width"], preset["height"] = int(w), int(h)
    if opts.frames:
        preset["frames"] = opts.frames
        preset["eval_frames"] = [f for f in preset["eval_frames"] if f < opts.frames] or [opts.frames - 1]
        preset["warmup"] = min(preset["warmup"], max(opts.frames - 1, 0))
    if opts.grid:
        preset["resolution"] = opts.grid
    if opts.bounces:
        preset["bounces"] = opts.bounces
    W, H = preset["width"], preset["height"]
    out = Path(opts.out) / NAME

    # ----------------- validate everything before any work -----------------
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))

    rows = []
    evals = set(preset["eval_frames"])
    total = len(names) * len(preset["bounces"]) * preset["frames"]
    with tqdm(total=total, desc=NAME, unit="frame", disable=None) as bar:
        for s in experiment.each_scene(names):
            viewers = views.single(s)
            for nb in preset["bounces"]:
                cfgs = _configs(nb)
                caches = [CRCCache(s, bounces=nb, resolution=preset["resolution"], seed=opts.seed,
                                   march_samples=getattr(opts, "march_samples", 0) or 0, **c)
                          for c in cfgs]
                timers = [StageTimer() for _ in cfgs]
                acc = [dict() for _ in cfgs]
                stats = [dict() for _ in cfgs]
                last = {}
                for f in range(preset["frames"]):
                    bar.set_postfix_str(f"{s.name}/{nb} bounce(s)")
                    gbs = gbuffers_for(s, viewers, f, W, H)
                    imgs = []
                    for cache, tm in zip(caches, timers):
                        tm.begin_frame()
                        ind = cache.render(f, gbs, tm)
                        tm.end_frame()
                        imgs.append(to_image(gbs[0], ind[0]))
                    for st, cache in zip(stats, caches):
                        for k, v in cache.stats().items():
                            st.setdefault(k, []).append(float(v))
                    if f in evals:
                        gb = gbs[0]
                        direct = ground_truth(s, gb, f, gb.viewer, spp=preset["direct_spp"])
                        ref = direct + reference_indirect(s, gb, f, gb.viewer, spp=preset["ref_spp"], bounces=nb)
                        finals = [direct + im for im in imgs]
                        for i, c in enumerate(cfgs):
                            base = next(j for j, d in enumerate(cfgs) if d["occupancy"] == c["occupancy"]
                                        and "chroma" not in d
                                        and d["visibility"] == c["visibility"] and d["encoding"] == "rgb3")
                            m = evaluate(ref, finals[i], s.exposure)
                            m["lab_rmse_ref"] = m.pop("lab_rmse")
                            m["lab_rmse"] = lab_rmse(finals[base], finals[i], s.exposure)
                            m["pdiff"] = pdiff(finals[base], finals[i], s.exposure)
                            for k, v in m.items():
                                acc[i].setdefault(k, []).append(v)
                        last = {"ref": ref, "finals": finals, "direct": direct}
                    bar.update(1)
                # ------------------------------ rows ------------------------------
                group = []
                for i, (c, cache, tm) in enumerate(zip(cfgs, caches, timers)):
                    summ = tm.summary(preset["warmup"])
                    w0 = preset["warmup"]
                    row = {"scene": s.name, "method": "crc", "viewers": len(viewers), "encoding": c["encoding"],
                           "occupancy": c["occupancy"], "visibility": c["visibility"], "bounces": nb,
                           "chroma": c.get("chroma", "offset"),
                           "coefficients": cache.enc.n, "time_ms": summ.get("total", 0.0),
                           "stages_ms": {k: v for k, v in summ.items() if k != "total"},
                           "memory_mb": cache.memory_bytes() / 2 ** 20,
                           "occupancy_ratio": float(np.mean(stats[i]["occupancy_ratio"][w0:] or
                                                            stats[i]["occupancy_ratio"])),
                           "voxelize_ms": cache.voxelize_ms, "grid": list(cache.grid.dims),
                           "resolution": f"{W}x{H}"}
                    row.update({k: float(np.mean(v)) for k, v in acc[i].items()})
                    group.append(row)
                unopt = next(r for r in group if not r["occupancy"] and r["encoding"] == "rgb3")
                for r in group:
                    same = next(x for x in group if x["occupancy"] == r["occupancy"] and x["chroma"] == "offset" and
                                x["visibility"] == r["visibility"] and x["encoding"] == "rgb3")
                    r["time_vs_rgb3"] = r["time_ms"] / max(same["time_ms"], 1e-9)
                    r["time_vs_unoptimized"] = r["time_ms"] / max(unopt["time_ms"], 1e-9)
                rows += group
                # ------------------------------ images ------------------------------
                stem = out / "images" / f"{s.name}_b{nb}"
                io.write_hdr_and_png(stem.with_name(stem.name + "_reference"), last["ref"], s.exposure)
                for i, c in enumerate(cfgs):
                    if c["occupancy"] and c["visibility"] == "march" and c["encoding"] in ("rgb3", "y3co1cg1"):
                        tag = c["encoding"] + ("_ratio" if c.get("chroma") == "ratio" else "")
                        io.write_hdr_and_png(stem.with_name(f"{stem.name}_{tag}"), last["finals"][i],
                                             s.exposure)
                _plot(out / f"crc_{s.name}_b{nb}.png", group, f"{s.name}, {nb} bounce(s), {W}x{H}")

    config = {"quick": bool(opts.quick), "scenes": names, **preset, "seed": opts.seed,
              "march_samples": getattr(opts, "march_samples", 0) or 0,
              "pdiff": f"percent of pixels with CIE76 dE > {JND_CIE76} against the RGB3 cache",
              "lab_rmse": "CIE Lab RMSE (percent) against the RGB3 cache; lab_rmse_ref against the reference",
              "reference": "path-traced diffuse indirect light (slc.crc.reference) + ground-truth direct light"}
    results = experiment.results_object(NAME, config, rows)
    cols = [("scene", "scene"), ("bounces", "bounces"), ("visibility", "visibility"), ("occupancy", "occupancy"),
            ("encoding", "encoding"), ("chroma", "chroma"), ("coefficients", "coeffs"),
            ("occupancy_ratio", "occ. ratio"),
            ("time_ms", "t [ms]"), ("time_vs_rgb3", "t / RGB3"), ("time_vs_unoptimized", "t / unopt."),
            ("lab_rmse", "Lab RMSE vs RGB3 [%]"), ("pdiff", "pdiff [%]"), ("lab_rmse_ref", "Lab RMSE vs ref [%]"),
            ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]
    md = (f"# {NAME}\n\n{W}x{H}, {preset['frames']} frames ({preset['warmup']} warm-up), grid resolution "
          f"{preset['resolution']}; t = median cache ms per frame (voxelization excluded); Lab RMSE and pdiff "
          f"(CIE76 dE > {JND_CIE76}) against the uncompressed RGB3 cache; FLIP/PSNR/SSIM against the "
          f"path-traced reference ({preset['ref_spp']} spp indirect + {preset['direct_spp']} spp direct).\n\n"
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
