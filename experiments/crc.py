"""crc: Table 1 and Figs. 5, 9 and 10 of "Real-time Radiance Caching using
Chrominance Compression" (Vardis, Papaioannou and Gkaravelis 2014).

With the paper's defaults (``slc.methods.crc.CRCCache``: RSM first bounce with
Halton sampling, 10 march samples for the first bounce and 5 for later
ones, depth-occupancy stride 10 at 1 MPixel), per scene and bounce count
(1 bounce: depth occupancy; 2 bounces: geometry occupancy):

- *Table 1* (each configuration is the registered method ``crc`` through
  the common pipeline, :func:`slc.run.pipeline.run_case`): occupancy off
  (RGB3, the "unoptimized" Radiance Hints) and on with RGB3 and Y3Co3Cg3
  (27 coefficients), Y3Co2Cg2 (17) and Y3Co1Cg1 (11), Y3Co1Cg1 with the
  "ratio" chroma decoding, and our earlier choices as named variants (``first_bounce=paths``: light-traced VPLs
  chosen by PCG32; ``dense``: one march sample per voxel; ``stride10``: the
  paper's literal s = 10 at this small frame size). Per row: median cache
  time per frame, occupancy ratio, and the paper's two measures, CIE Lab
  RMSE and pdiff (Yee's PerceptualDiff, :func:`slc.methods.crc.quality.pdiff`),
  of two images against two references of the same sampling (``experiments/_crc_protocol.py``):
  the *final* frame (ground-truth direct light + the cache's indirect light,
  textures included, at the scene's exposure; ``lab_rmse_final``,
  ``pdiff_final``: against Y3Co3Cg3, the paper's Table 1;
  ``..._final_vs_rgb3``) and the *indirect* light alone (at the exposure that
  puts the 99th percentile of the reference's luminance at 0.8;
  ``lab_rmse_indirect``, ``pdiff_indirect``, ``..._indirect_vs_rgb3``); and the
  final frame against direct + the path-traced indirect reference
  (``lab_rmse_final_vs_ref``, ``pdiff_final_vs_ref``, ``flip``, ``psnr``,
  ``ssim``; the indirect light alone: ``*_indirect_vs_ref``).
- *Fig. 9*: encodings of (almost) equal budget, Y3Co1Cg1 (11) and
  Y2Co2Cg2 (12; RGB2 gives identical images, a linear transform of the same
  bands), against RGB3 and the reference (rows and an image strip).
- *Stage profile*: RGB3 and Y3Co1Cg1 run in turn (whole sequences, A B then
  B A, :func:`slc.run.experiment.runs_in_turn`); per stage the minimum and
  median ms over the frames after warm-up; the saving on the stages whose
  work scales with the coefficient count (projection/propagation, blend,
  reconstruction) next to the total (marching, light injection and
  occupancy do not depend on the encoding).
- *Fig. 5*: depth-occupancy ratio and first-bounce time at viewer
  positions spread over the camera path (1 bounce).
- *Fig. 10*: stage times against the CRC resolution (first scene, 2
  bounces, Y3Co1Cg1).
- *Where Y3Co1Cg1 differs* (``attribution``): the final frame's squared
  CIE76 differences from Y3Co3Cg3 split between the pixels lit mostly by
  indirect light and the others, and per light the final-frame Lab RMSE
  when only that light's indirect light is compressed.

Scenes of the quick preset: the Cornell box and the atrium, and two like
the paper's Table 1 scenes: an outdoor one lit by one sun (``village:sun=1``,
a directional light whose RSM holds the VPLs) and an interior lit by two
lights (``lamps:lights=2``, a point light and a spot light).

    python experiments/crc.py --quick
    slc run crc --quick [--scene cornell]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dataclasses  # noqa: E402 (after the path of a standalone run)
import functools  # noqa: E402
import statistics  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from slc import methods  # noqa: E402
from slc.core.errors import MethodError  # noqa: E402
from slc.core.spec import parse_spec  # noqa: E402
from slc.methods.crc.cache import CRCCache  # noqa: E402
from slc.methods.crc.grid import Grid  # noqa: E402
from slc.methods.crc.quality import pdiff  # noqa: E402
from slc.reference.metrics import evaluate  # noqa: E402
from slc.reference.references import reference_for  # noqa: E402
from slc.run import experiment, pipeline  # noqa: E402
from slc.run.pipeline import RunConfig, run_sequence  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "crc"

#: the quick preset's scenes: today's two, an outdoor scene lit by one sun, an interior lit by two lights
QUICK_SCENES = ["cornell", "atrium", "village:sun=1", "lamps:lights=2"]
FULL = dict(scenes=QUICK_SCENES + ["sponza"], width=320, height=180, frames=24, warmup=4,
            eval_frames=[15, 23], bounces=[1, 2], ref_spp=512, direct_spp=512, resolution=24,
            profile_frames=16, path_positions=10, sweep=[8, 16, 24, 32])
QUICK = dict(scenes=QUICK_SCENES, width=128, height=72, frames=8, warmup=3, eval_frames=[7], bounces=[1, 2],
             ref_spp=256, direct_spp=256, resolution=16, profile_frames=10, path_positions=4, sweep=[8, 16])
ENCODINGS = ["rgb3", "y3co3cg3", "y3co2cg2", "y3co1cg1"]
#: Fig. 9: 11 and 12 coefficients (RGB2 gives the same images as Y2Co2Cg2: same bands, linear
#: transform; tests/test_crc.py::test_encodings)
BUDGET = ["y3co1cg1", "y2co2cg2"]
PROFILED = ["rgb3", "y3co1cg1"]
PROFILE_REPEATS = 3     # the profiled encodings' runs in turn: A B, B A, A B
#: variants of Y3Co1Cg1: light-traced VPLs (paths), one march sample per voxel (dense), the literal s = 10
VARIANTS = {"paths": dict(first_bounce="paths"),
            "dense": dict(march_samples=0, secondary_march_samples=0),
            "stride10": dict(depth_stride=10)}
TIMING_KEYS = ("kernel", "compiled")     # per-frame fields of a run that are not stages


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (about 4 minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/crc)")
    p.add_argument("--res", help="WxH (default 320x180, quick 128x72)")
    p.add_argument("--frames", type=int, help="frames per sequence")
    p.add_argument("--grid", type=int, help="CRC resolution (cells on the longest side)")
    p.add_argument("--bounces", type=int, nargs="+", help="indirect bounce counts (default 1 2)")
    p.add_argument("--methods", nargs="+", metavar="SPEC",
                   help="extra configurations, e.g. crc:encoding=y3co2cg2,chroma=ratio (checked before any work)")
    p.add_argument("--seed", type=int, default=0)


def _configs(bounces: int) -> list[dict]:
    out = [dict(occupancy=False, encoding="rgb3")]
    out += [dict(encoding=e) for e in ENCODINGS + BUDGET[1:]]
    out += [dict(encoding="y3co1cg1", chroma="ratio")]
    for name, v in VARIANTS.items():
        if name != "stride10" or bounces == 1:
            out.append(dict(encoding="y3co1cg1", variant=name, **v))
    return out


def settings_of(config: dict) -> dict:
    """The crc method's settings of a configuration (its ``variant`` names the configuration)."""
    return {k: v for k, v in config.items() if k != "variant"}


def spec_of(config: dict) -> str:
    """The configuration's name in rows, profiles and plots: its settings as a method spec."""
    return "crc:" + ",".join(f"{k}={int(v) if isinstance(v, bool) else v}" for k, v in settings_of(config).items())


def make(scene, config: dict, seed: int):
    """The crc method of ``config``, its settings passed as data, labelled :func:`spec_of`."""
    m = methods.create("crc", scene, seed=seed, **settings_of(config))
    m.label = spec_of(config)
    return m


def _extra_specs(specs, nb: int, common: dict) -> list[dict]:
    """``--methods`` specs as settings, with the experiment's bounces and
    resolution unless the spec sets them."""
    out = []
    for spec in specs or []:
        name, settings = parse_spec(spec, "method setting", MethodError)
        if name != "crc":
            raise methods.MethodError(f"the crc experiment runs the crc method only (got '{spec}')")
        out.append({**common, "bounces": nb, "variant": "extra", **settings})
    return out


def run_config(W: int, H: int, frames: int, warmup: int, **kw):
    """A run of ``frames`` frames, nothing evaluated (the experiment compares images itself)."""
    return RunConfig(width=W, height=H, frames=frames, warmup=warmup, eval_frames=[], measure_overlap=False, **kw)


def _stage_frames(res, warmup: int) -> list[dict]:
    """The stage ms of a run's frames from ``warmup`` on (the last frame if none)."""
    fr = res.frames_ms[warmup:] or res.frames_ms[-1:]
    return [{k: v for k, v in f.items() if k not in TIMING_KEYS} for f in fr]


# ---------------------------------------------------------------------------
# Stage profile, error terms, the moving volume, Figs. 5 and 10
# ---------------------------------------------------------------------------

def _profile(scene, viewers, configs: list[dict], W: int, H: int, frames: int, warmup: int, seed: int) -> dict:
    """{spec: {stage: (min ms, median ms)}} over the frames >= warmup of
    ``PROFILE_REPEATS`` runs of each configuration, in turn (A B, B A, ...: load changes hit all alike)."""
    runs = experiment.runs_in_turn(scene, [(functools.partial(make, scene, c, seed), viewers) for c in configs],
                                   run_config(W, H, frames, warmup), PROFILE_REPEATS, seed)
    out = {}
    for sp, rs in zip(map(spec_of, configs), runs):
        fr = [f for r in rs for f in _stage_frames(r, warmup)]
        keys = sorted({k for x in fr for k in x})
        out[sp] = {k: (min(x.get(k, 0.0) for x in fr), statistics.median(x.get(k, 0.0) for x in fr)) for k in keys}
    return out


def _profile_rows(scene_name: str, nb: int, prof: dict, specs: dict) -> list[dict]:
    """Rows (one per stage and the sums) with the ms of each encoding and the
    ratio to RGB3, for the minimum and the median over frames."""
    groups = {"coefficient stages": CRCCache.COEFFICIENT_STAGES, "fixed stages": CRCCache.FIXED_STAGES}
    stages = [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if k in prof[specs["rgb3"]]]
    rows = []
    for name in stages + list(groups) + ["total", "total without lights"]:
        r = {"scene": scene_name, "bounces": nb, "stage": name}
        for enc, sp in specs.items():
            p = prof[sp]
            # the paper's GI time ("total without lights") excludes rendering the RSM
            keys = [k for k in p if k not in ("total", "lights")] if name == "total without lights" else \
                groups.get(name, [name])
            r[f"{enc}_min"], r[f"{enc}_median"] = (sum(p.get(k, (0.0, 0.0))[i] for k in keys) for i in (0, 1))
        for enc in specs:
            if enc != "rgb3":
                for q in ("min", "median"):
                    r[f"{enc}_vs_rgb3_{q}"] = r[f"{enc}_{q}"] / max(r[f"rgb3_{q}"], 1e-9)
        rows.append(r)
    return rows


def _along_path(scene, viewer, config: dict, W: int, H: int, positions: int, seed: int) -> list[dict]:
    """Fig. 5: depth occupancy ratio and first-bounce ms at ``positions`` viewer positions
    spread over the camera path (3 frames at each, the last one timed; the run resets the
    cache)."""
    m = make(scene, config, seed)
    path = getattr(viewer.pose, "__self__", None)
    n = int(getattr(path, "n_frames", 0) or 0) or 600
    out = []
    for k in range(positions):
        f0 = int(round(k * (n - 3) / max(positions - 1, 1)))
        res = run_sequence(scene, m, [viewer], run_config(W, H, 3, 2, start_frame=f0, keep_images=False))
        last = res.frames_ms[-1]
        out.append({"position": k, "frame": f0 + 2, "occupancy_ratio": m.occupancy_ratio(),
                    "active_cells": m.n_active,
                    "bounce1_ms": last.get("bounce1_march", 0.0) + last.get("bounce1_project", 0.0),
                    "total_ms": last["total"]})
    return out


def _sweep(scene, viewers, resolutions, W: int, H: int, seed: int) -> list[dict]:
    """Fig. 10: stage ms (minimum of 3 frames after 2 warm-up) against the
    CRC resolution; Y3Co1Cg1, 2 bounces."""
    rows = []
    for r in resolutions:
        m = make(scene, dict(resolution=r, bounces=2), seed)
        fr = _stage_frames(run_sequence(scene, m, viewers, run_config(W, H, 5, 2, keep_images=False)), 2)
        stages = sorted({k for x in fr for k in x if k != "total"})
        rows.append({"resolution": r, "cells": m.grid.n_cells, "occupancy_ratio": m.occupancy_ratio(),
                     "voxelize_ms": m.voxelize_ms, **{k: min(x.get(k, 0.0) for x in fr) for k in stages},
                     "total_ms": min(x["total"] for x in fr)})
    return rows


# ---------------------------------------------------------------------------
# The experiment
# ---------------------------------------------------------------------------

def _preset(opts) -> dict:
    preset = experiment.apply_common(opts, QUICK if opts.quick else FULL)     # --res, --frames
    if preset["width"] < 8 or preset["height"] < 8:
        raise experiment.ExperimentError(f"resolution '{opts.res}' is too small (at least 8x8)")
    if opts.frames is not None:
        preset["profile_frames"] = max(min(preset["profile_frames"], opts.frames), 2)
    if opts.grid is not None:
        if opts.grid < 2:
            raise experiment.ExperimentError("--grid must be at least 2")
        preset["resolution"] = opts.grid
    if opts.bounces:
        if min(opts.bounces) < 1:
            raise experiment.ExperimentError("--bounces must be at least 1")
        preset["bounces"] = opts.bounces
    return preset


def _table1_row(s, c: dict, m, viewers, cfg, preset, bar, seed: int):
    """One configuration through the common pipeline (:func:`slc.run.pipeline.run_case`): its row
    and its images per evaluated frame ({frame: {"direct", "indirect", "final", "indirect_ref",
    "final_ref"}}: the ground-truth direct light, the cache's indirect light, their sum, the
    path-traced indirect reference and direct + that reference)."""
    images = {}

    def on_eval(f, v, gb, img, ref):
        direct = reference_for("direct", s, gb, f, gb.viewer, spp=preset["direct_spp"])
        images[f] = {"direct": direct, "indirect": img, "final": direct + img, "indirect_ref": ref,
                     "final_ref": direct + ref}

    row = pipeline.run_case(s, spec_of(c), viewers, dataclasses.replace(cfg, on_eval=on_eval), bar, seed=seed,
                            method=make(s, c, seed))
    res, st = row.pop("_result"), m.settings()
    for k in res.metrics:   # the pipeline's comparison: indirect light alone against the indirect reference
        row[k + "_indirect_vs_ref"] = row.pop(k)
    acc = {}
    for f, im in sorted(images.items()):
        q = evaluate(im["final_ref"], im["final"], s.exposure)
        q["lab_rmse_final_vs_ref"] = q.pop("lab_rmse")
        q["pdiff_final_vs_ref"] = pdiff(im["final_ref"], im["final"], s.exposure)
        for k, v in q.items():
            acc.setdefault(k, []).append(v)
    row.update({k: float(np.mean(v)) for k, v in acc.items()})
    row.update({k: st[k] for k in ("encoding", "occupancy", "visibility", "bounces", "chroma", "first_bounce",
                                   "march_samples", "secondary_march_samples")})
    row.update({"depth_stride": m.stride_for(cfg.width, cfg.height), "variant": c["variant"],
                "coefficients": m.enc.n, "grid": list(Grid.around(s.bbox_min, s.bbox_max, st["resolution"]).dims)})
    return row, images


def _scene_parts(s, viewers, nb: int, common: dict, preset: dict, out: Path, seed: int, bar, acc: dict,
                 group: list[dict], images: list[dict]) -> None:
    """Per scene and bounce count: the stage profile, the error terms, the moving volume and
    where Y3Co1Cg1 differs from Y3Co3Cg3 (rows appended to ``acc``; ``group`` and ``images``:
    the Table 1 rows and their images)."""
    W, H = preset["width"], preset["height"]
    configs = {enc: {**common, "bounces": nb, "encoding": enc} for enc in PROFILED}
    specs = {enc: spec_of(c) for enc, c in configs.items()}
    bar.set_postfix_str(f"{s.name}/profile/b{nb}")
    prof = _profile(s, viewers, list(configs.values()), W, H, preset["profile_frames"],
                    min(3, preset["profile_frames"] - 1), seed)
    acc["profile"] += _profile_rows(s.name, nb, prof, specs)
    bar.set_postfix_str(f"{s.name}/terms/b{nb}")
    terms, me = experiment.load_part("crc_terms"), sys.modules[__name__]
    acc["error_terms"].append(terms.error_terms(me, s, viewers, nb, common, W, H, preset["frames"], seed,
                                                preset["ref_spp"], preset["direct_spp"]))
    if s.name not in terms.MOVING["skip"]:
        bar.set_postfix_str(f"{s.name}/moving/b{nb}")
        acc["moving"].append(terms.moving(me, s, viewers, nb, common, W, H, preset["frames"], seed,
                                          preset["ref_spp"], preset["direct_spp"]))
    bar.set_postfix_str(f"{s.name}/attribution/b{nb}")
    std = {r["encoding"]: im for r, im in zip(group, images) if r["variant"] == "" and r["occupancy"]
           and r["visibility"] == "march" and r["chroma"] == "offset"}
    f = max(std["y3co3cg3"])
    acc["attribution"].append(terms.attribution(me, s, viewers, nb, common, W, H, f, seed, std["y3co3cg3"][f],
                                                std["y3co1cg1"][f]))


def _figures(s, viewers, first: bool, common: dict, preset: dict, out: Path, seed: int, bar, acc: dict) -> None:
    """Fig. 5 (1 bounce) and, on the first scene, Fig. 10."""
    report = experiment.load_part("crc_report")
    W, H = preset["width"], preset["height"]
    if 1 in preset["bounces"]:
        bar.set_postfix_str(f"{s.name}/path")
        pts = _along_path(s, viewers[0], {**common, "bounces": 1}, W, H, preset["path_positions"], seed)
        acc["fig5_path"] += [{"scene": s.name, **p} for p in pts]
        report.plot_path(out / f"fig5_{report.file_stem(s.name)}.png", pts,
                         f"Fig. 5: {s.name}, depth occupancy along the path")
    if first:
        bar.set_postfix_str(f"{s.name}/sweep")
        sw = _sweep(s, viewers, preset["sweep"], W, H, seed)
        acc["fig10_sweep"] += [{"scene": s.name, **r} for r in sw]
        report.plot_sweep(out / f"fig10_{report.file_stem(s.name)}.png", sw, f"Fig. 10: {s.name}, 2 bounces, Y3Co1Cg1")


def run(opts) -> dict:
    report = experiment.load_part("crc_report")
    preset = _preset(opts)
    W, H = preset["width"], preset["height"]
    out = Path(opts.out) / NAME
    common = dict(resolution=preset["resolution"])
    # ----------------- validate everything before any work -----------------
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    cfg = RunConfig(width=W, height=H, frames=preset["frames"], warmup=preset["warmup"],
                    eval_frames=preset["eval_frames"], seed=opts.seed, ref_spp=preset["ref_spp"],
                    keep_images=False, measure_overlap=False)
    plans = {nb: [{**common, "bounces": nb, "variant": "", **c} for c in _configs(nb)]
             + _extra_specs(opts.methods, nb, common) for nb in preset["bounces"]}
    rows = []
    acc = {k: [] for k in ("profile", "fig5_path", "fig10_sweep", "error_terms", "moving", "attribution")}
    total = len(names) * sum(len(p) for p in plans.values()) * preset["frames"]
    with tqdm(total=total, desc=NAME, unit="frame", disable=None) as bar:
        for si, s in enumerate(experiment.each_scene(names)):
            viewers = views.single(s)
            made = {nb: [make(s, c, opts.seed) for c in plan] for nb, plan in plans.items()}
            for nb, plan in plans.items():
                done = [_table1_row(s, c, m, viewers, cfg, preset, bar, opts.seed) for c, m in zip(plan, made[nb])]
                group, images = [r for r, _ in done], [im for _, im in done]
                experiment.load_part("crc_protocol").compare(group, images, s)
                rows += group
                report.fig9(sys.modules[__name__], out, s, nb, group, images)
                report.plot(out / f"crc_{report.file_stem(s.name)}_b{nb}.png", group,
                            f"{s.name}, {nb} bounce(s), {W}x{H}")
                _scene_parts(s, viewers, nb, common, preset, out, opts.seed, bar, acc, group, images)
                report.protocol_strip(out, s, nb, acc["attribution"][-1])
            _figures(s, viewers, si == 0, common, preset, out, opts.seed, bar, acc)
    config = {"quick": bool(opts.quick), "scenes": names, **preset, "seed": opts.seed,
              "protocol": "the CRC paper's Table 1 measures (Sec. 7): CIE Lab RMSE (lab_rmse_*: RMS over the "
                          "frame's pixels of the CIE76 dE of the images at their exposure, clipped to [0, 1]; "
                          "dE 1 = 1%, the L* range being 100) and pdiff (pdiff_*: Yee and Newman's "
                          "PerceptualDiff, slc.methods.crc.quality.pdiff, percent of pixels visibly different) of "
                          "the final frame (ground-truth direct + the cache's indirect light, the scene's "
                          "exposure) and of the indirect light alone (exposure 0.8 / p99 of the reference's "
                          "luminance), against the Y3Co3Cg3 cache of the same sampling (the paper's 'Y3Co3Cg3 "
                          "vs Y3Co1Cg1'; fields without suffix) and against RGB3 (suffix _vs_rgb3)",
              "de76_fraction_final": "percent of pixels with CIE76 dE > 2.3, final frame against Y3Co3Cg3",
              "reference": "slc.reference.references: indirect reference (the method's bounces) + ground-truth "
                           "direct light; *_final_vs_ref, flip, psnr, ssim, rel_mse: the final frame against "
                           "it; *_indirect_vs_ref: the pipeline's comparison of the indirect light alone with "
                           "the indirect reference (exposure 0.8 / p99 of the reference)",
              "attribution": "final frame, Y3Co1Cg1 against Y3Co3Cg3: the squared dE of the pixels lit mostly by "
                             "indirect light (indirect >= half the luminance) and of the others; per light the "
                             "Lab RMSE when only that light's indirect light is compressed (the other lights "
                             "set to 0 in both caches)",
              "profile": f"stage ms, minimum and median over frames after 3 warm-up of {PROFILE_REPEATS} runs of "
                         "each encoding, run in turn (A B, B A, ...)"}
    results = experiment.results_object(NAME, config, experiment.strip_private(rows))
    results.update({k: experiment.strip_private(v) for k, v in acc.items()})
    experiment.write_results(out, results, report.markdown(
        sys.modules[__name__], rows, acc["profile"], acc["fig5_path"], acc["fig10_sweep"], preset, names,
        acc["error_terms"], acc["moving"], acc["attribution"]))
    print(f"results: {out / 'results.json'}")
    return results


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
