"""crc: Table 1 and Figs. 5, 9 and 10 of "Real-time Radiance Caching using
Chrominance Compression" (Vardis, Papaioannou and Gkaravelis 2014).

With the paper's defaults (``slc.methods.crc.CRCCache``: RSM first bounce with
Halton sampling, 10 march samples for the first bounce and 5 for later
ones, depth-occupancy stride 10 at 1 MPixel), per scene and bounce count
(1 bounce: depth occupancy; 2 bounces: geometry occupancy):

- *Table 1* (each configuration is the registered method ``crc`` through
  the common pipeline, :func:`slc.run.experiment.run_case`): occupancy off
  (RGB3, the "unoptimized" Radiance Hints) and on with RGB3 (27
  coefficients), Y3Co2Cg2 (17) and Y3Co1Cg1 (11), Y3Co1Cg1 with the
  "ratio" chroma decoding, and our earlier choices as named variants (``first_bounce=paths``: light-traced VPLs
  chosen by PCG32; ``dense``: one march sample per voxel; ``stride10``: the
  paper's literal s = 10 at this small frame size). Per row: median cache
  time per frame, occupancy ratio, CIE Lab RMSE and pdiff (Yee's
  PerceptualDiff, :func:`slc.methods.crc.quality.pdiff`) against the RGB3 cache
  of the same sampling (the paper's comparison), and FLIP/PSNR/SSIM/Lab
  RMSE of ground-truth direct + cache indirect against direct + the
  path-traced indirect reference (``lab_rmse_ref``).
- *Fig. 9*: encodings of (almost) equal budget, Y3Co1Cg1 (11) and
  Y2Co2Cg2 (12; RGB2 gives identical images, a linear transform of the same
  bands), against RGB3 and the reference (rows and an image strip).
- *Stage profile*: RGB3 and Y3Co1Cg1 run frame by frame
  in alternating order on the same G-buffers; per stage the minimum and
  median ms over the frames after warm-up; the saving on the stages whose
  work scales with the coefficient count (projection/propagation, blend,
  reconstruction) next to the total (marching, light injection and
  occupancy do not depend on the encoding).
- *Fig. 5*: depth-occupancy ratio and first-bounce time at viewer
  positions spread over the camera path (1 bounce).
- *Fig. 10*: stage times against the CRC resolution (first scene, 2
  bounces, Y3Co1Cg1).

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
            eval_frames=[15, 23], bounces=[1, 2], ref_spp=512, direct_spp=512, resolution=24,
            profile_frames=16, path_positions=10, sweep=[8, 16, 24, 32])
QUICK = dict(scenes=["cornell", "atrium"], width=128, height=72, frames=8, warmup=3, eval_frames=[7], bounces=[1, 2],
             ref_spp=256, direct_spp=256, resolution=16, profile_frames=10, path_positions=4, sweep=[8, 16])
ENCODINGS = ["rgb3", "y3co2cg2", "y3co1cg1"]
#: Fig. 9: 11 and 12 coefficients (RGB2 gives the same images as Y2Co2Cg2: same bands, linear
#: transform; tests/test_crc.py::test_encodings)
BUDGET = ["y3co1cg1", "y2co2cg2"]
PROFILED = ["rgb3", "y3co1cg1"]
RECONSTRUCT_REPEATS = 5
#: our earlier choices, kept as named settings (run as Y3Co1Cg1 variants)
#: the error terms: sample multiplier of the low-noise runs, seed offset of the noise run
TERMS_SAMPLES = 4
#: the moving volume: window side as a fraction of the grid resolution, camera-path frames per
#: rendered frame (a faster walk, so that the window moves within the quick preset's frames),
#: window centre ahead of the viewer [cells] (0: centred at the viewer, the paper); scenes whose
#: cameras stay outside the scene box (the Cornell box) are not run
MOVING = dict(window_fraction=0.5, step=20, ahead=0.0, skip=("cornell",))
VARIANTS = {"paths": dict(first_bounce="paths"),
            "dense": dict(march_samples=0, secondary_march_samples=0),
            "stride10": dict(depth_stride=10)}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (about 3 minutes on 2 cores)")
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


def _spec(settings: dict) -> str:
    items = {k: v for k, v in settings.items() if k != "variant"}
    return "crc:" + ",".join(f"{k}={int(v) if isinstance(v, bool) else v}" for k, v in items.items())


def _extra_specs(specs, nb: int, common: dict) -> list[dict]:
    """``--methods`` specs as settings, with the experiment's bounces and
    resolution unless the spec sets them."""
    from slc import methods
    out = []
    for spec in specs or []:
        name, settings = methods.parse_spec(spec)
        if name != "crc":
            raise methods.MethodError(f"the crc experiment runs the crc method only (got '{spec}')")
        out.append({**common, "bounces": nb, "variant": "extra", **settings})
    return out


# ---------------------------------------------------------------------------
# Stage profile: encodings frame by frame in alternating order
# ---------------------------------------------------------------------------

def _profile(scene, viewers, specs: list[str], W: int, H: int, frames: int, warmup: int, seed: int) -> dict:
    """{spec: {stage: (min ms, median ms)}} over frames >= warmup; the
    methods render the same G-buffers, in order A B C, C B A, ... so that
    load changes hit all alike; a frame's reconstruction is the minimum of
    ``RECONSTRUCT_REPEATS`` runs."""
    import statistics
    import time

    import drjit as dr

    from slc import methods
    from slc.methods import FrameContext
    from slc.run.pipeline import gbuffers_for
    from slc.core.timing import StageTimer
    made = {sp: methods.create(sp, scene, seed=seed) for sp in specs}
    timers = {sp: StageTimer() for sp in specs}
    for f in range(frames):
        gbs = gbuffers_for(scene, viewers, f, W, H)
        for sp in (specs if f % 2 == 0 else specs[::-1]):
            t = timers[sp]
            t.begin_frame()
            made[sp].render(FrameContext(f), gbs, t)
            cur = t.end_frame()
            # reconstruction is short (a few ms) next to the scheduler's time slices on a loaded
            # machine: the frame's figure is the minimum of RECONSTRUCT_REPEATS runs of it
            # (it only reads the cache)
            for _ in range(RECONSTRUCT_REPEATS - 1):
                dr.sync_thread()
                t0 = time.perf_counter()
                dr.eval([made[sp].shade(gb) for gb in gbs])
                dr.sync_thread()
                ms = (time.perf_counter() - t0) * 1e3
                if ms < cur["reconstruct"]:
                    cur["total"] -= cur["reconstruct"] - ms
                    cur["reconstruct"] = ms
    out = {}
    for sp, t in timers.items():
        fr = t.frames[warmup:] or t.frames[-1:]
        keys = sorted({k for x in fr for k in x})
        out[sp] = {k: (min(x.get(k, 0.0) for x in fr), statistics.median(x.get(k, 0.0) for x in fr)) for k in keys}
    return out


def _profile_rows(scene_name: str, nb: int, prof: dict, specs: dict) -> list[dict]:
    """Rows (one per stage and the sums) with the ms of each encoding and the
    ratio to RGB3, for the minimum and the median over frames."""
    from slc.methods.crc.cache import CRCCache
    groups = {"coefficient stages": CRCCache.COEFFICIENT_STAGES, "fixed stages": CRCCache.FIXED_STAGES}
    stages = [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if k in prof[specs["rgb3"]]]
    rows = []
    for name in stages + list(groups) + ["total", "total without lights"]:
        r = {"scene": scene_name, "bounces": nb, "stage": name}
        for enc, sp in specs.items():
            p = prof[sp]
            if name in groups:
                mn = sum(p.get(k, (0.0, 0.0))[0] for k in groups[name])
                md = sum(p.get(k, (0.0, 0.0))[1] for k in groups[name])
            elif name == "total without lights":     # the paper's GI time excludes rendering the RSM
                mn = sum(v[0] for k, v in p.items() if k not in ("total", "lights"))
                md = sum(v[1] for k, v in p.items() if k not in ("total", "lights"))
            else:
                mn, md = p.get(name, (0.0, 0.0))
            r[f"{enc}_min"], r[f"{enc}_median"] = mn, md
        for enc in specs:
            if enc != "rgb3":
                r[f"{enc}_vs_rgb3_min"] = r[f"{enc}_min"] / max(r["rgb3_min"], 1e-9)
                r[f"{enc}_vs_rgb3_median"] = r[f"{enc}_median"] / max(r["rgb3_median"], 1e-9)
        rows.append(r)
    return rows


# ---------------------------------------------------------------------------
# Error terms and the moving volume
# ---------------------------------------------------------------------------

def _last_image(scene, viewers, spec: str, W: int, H: int, frames: int, seed: int):
    """(method, G-buffer, indirect image) of the last of ``frames`` frames."""
    from slc import methods
    from slc.methods import FrameContext
    from slc.run.pipeline import gbuffers_for
    from slc.reference.references import image_of
    from slc.core.timing import NullTimer
    m = methods.create(spec, scene, seed=seed)
    for f in range(frames):
        gbs = gbuffers_for(scene, viewers, f, W, H)
        out = m.render(FrameContext(f), gbs, NullTimer())
    return m, gbs[0], image_of("indirect", gbs[0], out[0])


def _error_terms(scene, viewers, nb: int, common: dict, W: int, H: int, frames: int, seed: int,
                 ref_spp: int, direct_spp: int) -> dict:
    """The terms of the errors, each measured alone at the last frame
    (composited: ground-truth direct + indirect; Lab RMSE, percent):

    - encoding: Y3Co1Cg1 (offset / ratio decoding) against RGB3 of the same
      sampling (the paper's comparison), at the default sample count and at
      ``TERMS_SAMPLES`` x samples (what stays is systematic);
    - noise: RGB3 against RGB3 with another seed (two independent
      estimates: sqrt(2) x one estimate's noise);
    - quantisation: the RGB3 cache stored as float16 (the GPU's RGBA16F
      render targets) against float32;
    - interpolation (1 bounce): the grid cache against the first-bounce
      estimator evaluated at each shaded point's own lookup point (no grid,
      jitter, trilinear interpolation or blend), both at the high sample count;
    - reference noise: the indirect reference at ``ref_spp`` against 4x as
      many paths;
    - RGB3 against the reference at both sample counts, and the
      unfiltered estimator against it (what the grid adds)."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from slc.reference.metrics import lab_rmse
    from slc.reference.references import image_of, reference_for
    f = frames - 1

    def spec(**kw):
        return _spec({**common, "bounces": nb, **kw})

    m0, gb, rgb = _last_image(scene, viewers, spec(encoding="rgb3"), W, H, frames, seed)
    hi = TERMS_SAMPLES * m0.samples
    direct = reference_for("direct", scene, gb, f, gb.viewer, spp=direct_spp)
    ind = reference_for("indirect", scene, gb, f, gb.viewer, spp=ref_spp, bounces=nb)
    ind4 = reference_for("indirect", scene, gb, f, gb.viewer, spp=4 * ref_spp, bounces=nb)
    x = scene.exposure

    def L(a, b):
        return lab_rmse(direct + a, direct + b, x)

    img = {"rgb3": rgb}
    for name, kw in (("offset", dict(encoding="y3co1cg1")), ("ratio", dict(encoding="y3co1cg1", chroma="ratio")),
                     ("seed", dict(encoding="rgb3"))):
        img[name] = _last_image(scene, viewers, spec(**kw), W, H, frames, seed + (1 if name == "seed" else 0))[2]
    mh, _, img["rgb3_hi"] = _last_image(scene, viewers, spec(encoding="rgb3", samples=hi), W, H, frames, seed)
    img["offset_hi"] = _last_image(scene, viewers, spec(encoding="y3co1cg1", samples=hi), W, H, frames, seed)[2]
    img["ratio_hi"] = _last_image(scene, viewers, spec(encoding="y3co1cg1", chroma="ratio", samples=hi),
                                  W, H, frames, seed)[2]
    out = {"scene": scene.name, "bounces": nb, "samples": m0.samples, "samples_hi": hi,
           "encoding_offset": L(img["rgb3"], img["offset"]), "encoding_ratio": L(img["rgb3"], img["ratio"]),
           "encoding_offset_hi": L(img["rgb3_hi"], img["offset_hi"]),
           "encoding_ratio_hi": L(img["rgb3_hi"], img["ratio_hi"]),
           "noise_two_seeds": L(img["rgb3"], img["seed"]),
           "noise_vs_hi": L(img["rgb3_hi"], img["rgb3"]),
           "rgb3_vs_ref": L(ind, img["rgb3"]), "rgb3_hi_vs_ref": L(ind, img["rgb3_hi"]),
           "reference_noise": L(ind4, ind), "rgb3_vs_ref4": L(ind4, img["rgb3"])}
    # ------------------------------ quantisation ------------------------------
    c32 = mh.cache
    mh.cache = mi.Float(np.array(c32, dtype=np.float32).astype(np.float16).astype(np.float32))
    out["quantisation_fp16"] = L(img["rgb3_hi"], image_of("indirect", gb, mh.shade(gb)))
    mh.cache = c32
    # ------------------------------ interpolation ------------------------------
    out["interpolation"] = out["unfiltered_hi_vs_ref"] = None
    if nb == 1:
        unf = image_of("indirect", gb, mh.shade_unfiltered(f, gb))
        dr.eval()
        out["interpolation"] = L(unf, img["rgb3_hi"])
        out["unfiltered_hi_vs_ref"] = L(ind, unf)
    # mean indirect light over the reference's, per channel
    out["rgb3_hi_mean_over_ref"] = (img["rgb3_hi"].reshape(-1, 3).mean(0)
                                    / np.maximum(ind.reshape(-1, 3).mean(0), 1e-12)).round(3).tolist()
    out["indirect_share"] = float(np.mean(ind) / max(float(np.mean(direct + ind)), 1e-12))
    return out


def _moving(scene, viewers, nb: int, common: dict, W: int, H: int, frames: int, seed: int, ref_spp: int,
            direct_spp: int) -> dict:
    """The moving volume (``volume=camera``) against the grid over the whole
    scene, Y3Co1Cg1, on the camera path at ``MOVING['step']`` path frames
    per rendered frame, both on the same G-buffers in alternating order.
    Times: median ms per frame after 2 warm-up frames; kernels built or
    loaded by the moving cache after warm-up and after its first move (the
    first move builds the scroll kernel; slc.core.timing.KernelCounter);
    errors at the last frame (composited, Lab RMSE): each against the
    reference over the image and over the pixels inside the window, and the
    two caches against each other inside the window."""
    import statistics

    import numpy as np

    from slc import methods
    from slc.methods.crc.cache import front_normal
    from slc.methods import FrameContext
    from slc.reference.metrics import lab_rmse
    from slc.run.pipeline import gbuffers_for
    from slc.reference.references import image_of, reference_for
    from slc.core.timing import KernelCounter, StageTimer
    window = max(4, int(round(common["resolution"] * MOVING["window_fraction"])))
    sp_scene = _spec({**common, "bounces": nb})
    sp_cam = _spec({**common, "bounces": nb, "volume": "camera", "window": window, "ahead": MOVING["ahead"]})
    ms, mc = methods.create(sp_scene, scene, seed=seed), methods.create(sp_cam, scene, seed=seed)
    ts, tc = StageTimer(), StageTimer()
    built, warm, first_move = 0, 2, None
    with KernelCounter() as kc:
        for k in range(frames):
            f = k * MOVING["step"]
            gbs = gbuffers_for(scene, viewers, f, W, H)
            order = [(ms, ts, "s"), (mc, tc, "c")]
            for m, t, tag in (order if k % 2 == 0 else order[::-1]):
                kc.take()
                t.begin_frame()
                out = m.render(FrameContext(f), gbs, t)
                t.end_frame()
                n = kc.take()
                if tag == "c":
                    # kernels built after warm-up and after the first move (which builds the scroll kernel)
                    if first_move is not None and k >= warm:
                        built += n
                    if first_move is None and m.moves:
                        first_move = k
                if tag == "s":
                    img_s = out[0]
                else:
                    img_c = out[0]
    gb = gbs[0]
    direct = reference_for("direct", scene, gb, f, gb.viewer, spp=direct_spp)
    ind = reference_for("indirect", scene, gb, f, gb.viewer, spp=ref_spp, bounces=nb)
    a, b = image_of("indirect", gb, img_s), image_of("indirect", gb, img_c)
    q = gb.si.p + front_normal(gb.si) * (0.5 * mc.grid.h)
    inside = np.array(gb.valid & mc.in_window(gb.si.p, q)).reshape(H, W)
    x = scene.exposure

    def err(r, t, mask=None):
        d = direct
        if mask is not None:
            if not mask.any():
                return None
            d, r, t = direct[mask][None], r[mask][None], t[mask][None]
        return lab_rmse(d + r, d + t, x)

    med = lambda t, key: statistics.median(fr.get(key, 0.0) for fr in t.frames[warm:])  # noqa: E731
    return {"scene": scene.name, "bounces": nb, "window": window, "window_cells": mc.grid.n_cells,
            "grid_cells": ms.grid.n_cells, "step": MOVING["step"], "frames": frames, "last_frame": f,
            "moves": mc.moves, "first_move_frame": first_move, "kernels_built_after_warmup": built,
            "time_scene_ms": med(ts, "total"), "time_camera_ms": med(tc, "total"),
            "scroll_ms": med(tc, "scroll"), "time_camera_vs_scene": med(tc, "total") / max(med(ts, "total"), 1e-9),
            "active_scene": ms.n_active, "active_camera": mc.n_active,
            "inside_fraction": float(inside.sum() / max(int(np.array(gb.valid).sum()), 1)),
            "lab_rmse_ref_scene": err(ind, a), "lab_rmse_ref_camera": err(ind, b),
            "lab_rmse_ref_scene_inside": err(ind, a, inside), "lab_rmse_ref_camera_inside": err(ind, b, inside),
            "camera_vs_scene_inside": err(a, b, inside)}


# ---------------------------------------------------------------------------
# Fig. 5 and Fig. 10
# ---------------------------------------------------------------------------

def _along_path(scene, viewer, spec: str, W: int, H: int, positions: int, seed: int) -> list[dict]:
    """Fig. 5: depth occupancy ratio and first-bounce ms at ``positions``
    viewer positions spread over the camera path (3 frames at each, the
    last one timed; the cache is reset between positions)."""
    from slc.scene import gbuffer as gbuf
    from slc import methods
    from slc.methods import FrameContext
    from slc.core.timing import StageTimer
    m = methods.create(spec, scene, seed=seed)
    path = getattr(viewer.pose, "__self__", None)
    n = int(getattr(path, "n_frames", 0) or 0) or 600
    out = []
    for k in range(positions):
        f0 = int(round(k * (n - 3) / max(positions - 1, 1)))
        m.reset()
        t = StageTimer()
        for f in range(f0, f0 + 3):
            cam = viewer.camera(f)
            scene.set_frame(f)
            gbs = [gbuf.render_gbuffer(scene, cam, W, H, viewer.camera(f - 1) if f > 0 else None, viewer.name)]
            t.begin_frame()
            m.render(FrameContext(f), gbs, t)
            t.end_frame()
        last = t.frames[-1]
        out.append({"position": k, "frame": f0 + 2, "occupancy_ratio": m.occupancy_ratio(),
                    "active_cells": m.n_active,
                    "bounce1_ms": last.get("bounce1_march", 0.0) + last.get("bounce1_project", 0.0),
                    "total_ms": last["total"]})
    return out


def _sweep(scene, viewers, resolutions, W: int, H: int, seed: int) -> list[dict]:
    """Fig. 10: stage ms (minimum of 3 frames after 2 warm-up) against the
    CRC resolution; Y3Co1Cg1, 2 bounces."""
    from slc import methods
    from slc.methods import FrameContext
    from slc.run.pipeline import gbuffers_for
    from slc.core.timing import StageTimer
    rows = []
    for r in resolutions:
        m = methods.create(f"crc:resolution={r},bounces=2", scene, seed=seed)
        t = StageTimer()
        for f in range(5):
            gbs = gbuffers_for(scene, viewers, f, W, H)
            t.begin_frame()
            m.render(FrameContext(f), gbs, t)
            t.end_frame()
        fr = t.frames[2:]
        stages = sorted({k for x in fr for k in x if k != "total"})
        rows.append({"resolution": r, "cells": m.grid.n_cells, "occupancy_ratio": m.occupancy_ratio(),
                     "voxelize_ms": m.voxelize_ms, **{k: min(x.get(k, 0.0) for x in fr) for k in stages},
                     "total_ms": min(x["total"] for x in fr)})
    return rows


# ---------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------

def _plot(path, rows, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc.core import io
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.6))
    std = [r for r in rows if r["variant"] == "" and r["visibility"] == "march" and r["chroma"] == "offset"]
    a1.bar(range(len(std)), [r["time_ms"] for r in std], color="tab:blue")
    a1.set_xticks(range(len(std)), [r["encoding"].upper() + ("" if r["occupancy"] else "\nocc. off") for r in std],
                  fontsize=7)
    a1.set_ylabel("cache time per frame [ms] (median)")
    rs = [r for r in std if r["occupancy"] and r.get("lab_rmse") is not None]
    a2.bar(range(len(rs)), [r["lab_rmse"] for r in rs], color="tab:red", label="vs RGB3 cache")
    a2.plot(range(len(rs)), [r["lab_rmse_ref"] for r in rs], "ko", label="vs reference")
    a2.set_xticks(range(len(rs)), [f"{r['encoding'].upper()}\n({r['coefficients']})" for r in rs], fontsize=7)
    a2.set_ylabel("Lab RMSE [%]")
    a2.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _strip(path, panels, exposure, title):
    """Fig. 9: tone-mapped images side by side, titles with their errors."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc.core import io
    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.0))
    for ax, (label, img) in zip(axes, panels):
        ax.imshow(io.tonemap(img, exposure))
        ax.set_title(label, fontsize=7)
        ax.axis("off")
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _plot_path(path, pts, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc.core import io
    fig, a1 = plt.subplots(figsize=(5, 3.2))
    x = [p["position"] + 1 for p in pts]
    a1.plot(x, [100 * p["occupancy_ratio"] for p in pts], "o-", color="tab:blue")
    a1.set_xlabel("viewer position along the camera path")
    a1.set_ylabel("depth occupancy [% of cells]", color="tab:blue")
    a2 = a1.twinx()
    a2.plot(x, [p["bounce1_ms"] for p in pts], "s--", color="tab:red")
    a2.set_ylabel("first bounce [ms]", color="tab:red")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _plot_sweep(path, rows, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc.core import io
    from slc.methods.crc.cache import CRCCache
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    stages = [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if any(k in r for r in rows)]
    x = range(len(rows))
    bottom = [0.0] * len(rows)
    for k in stages:
        v = [r.get(k, 0.0) for r in rows]
        ax.bar(x, v, bottom=bottom, label=k)
        bottom = [b + y for b, y in zip(bottom, v)]
    for i, r in enumerate(rows):
        ax.annotate(f"{100 * r['occupancy_ratio']:.0f}%", (i, bottom[i]), ha="center", fontsize=7,
                    textcoords="offset points", xytext=(0, 2))
    ax.set_xticks(list(x), [f"{r['resolution']}" for r in rows])
    ax.set_xlabel("CRC resolution (cells on the longest side); label: occupancy")
    ax.set_ylabel("ms per frame (min of 3)")
    ax.legend(fontsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------
# The experiment
# ---------------------------------------------------------------------------

def _preset(opts) -> dict:
    from slc.run import experiment
    preset = dict(QUICK if opts.quick else FULL)
    if opts.res:
        w, _, h = opts.res.lower().partition("x")
        try:
            preset["width"], preset["height"] = int(w), int(h)
        except ValueError:
            raise experiment.ExperimentError(f"bad resolution '{opts.res}' (expected WxH, e.g. 320x180)") from None
        if preset["width"] < 8 or preset["height"] < 8:
            raise experiment.ExperimentError(f"resolution '{opts.res}' is too small (at least 8x8)")
    if opts.frames:
        if opts.frames < 1:
            raise experiment.ExperimentError("--frames must be at least 1")
        preset["frames"] = opts.frames
        preset["eval_frames"] = [f for f in preset["eval_frames"] if f < opts.frames] or [opts.frames - 1]
        preset["warmup"] = min(preset["warmup"], max(opts.frames - 1, 0))
        preset["profile_frames"] = max(min(preset["profile_frames"], opts.frames), 2)
    if opts.grid:
        if opts.grid < 2:
            raise experiment.ExperimentError("--grid must be at least 2")
        preset["resolution"] = opts.grid
    if opts.bounces:
        if min(opts.bounces) < 1:
            raise experiment.ExperimentError("--bounces must be at least 1")
        preset["bounces"] = opts.bounces
    return preset


def _base_for(r: dict, group: list[dict]):
    """Index of the RGB3 row that differs from ``r`` only in the encoding
    and chroma decoding (None for the variants)."""
    if r["variant"]:
        return None
    return next((j for j, x in enumerate(group) if x["variant"] == "" and x["occupancy"] == r["occupancy"]
                 and x["visibility"] == r["visibility"] and x["encoding"] == "rgb3" and x["chroma"] == "offset"),
                None)


def run(opts) -> dict:
    import dataclasses

    import numpy as np
    from tqdm import tqdm

    from slc.run import experiment

    from slc.core import io

    from slc import methods

    from slc.scene import views
    from slc.methods.crc.grid import Grid
    from slc.methods.crc.quality import de76_fraction, pdiff
    from slc.reference.metrics import evaluate, lab_rmse
    from slc.run.pipeline import RunConfig
    from slc.reference.references import reference_for

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

    rows, prof_rows, path_rows, sweep_rows, term_rows, moving_rows = [], [], [], [], [], []
    total = len(names) * sum(len(p) for p in plans.values()) * preset["frames"]
    with tqdm(total=total, desc=NAME, unit="frame", disable=None) as bar:
        for si, s in enumerate(experiment.each_scene(names)):
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
                        q["pdiff_ref"] = pdiff(ref_full, final, s.exposure)
                        for k, v in q.items():
                            acc.setdefault(k, []).append(v)
                    row.update({k: float(np.mean(v)) for k, v in acc.items()})
                    row.update({"encoding": st["encoding"], "occupancy": st["occupancy"],
                                "visibility": st["visibility"], "bounces": st["bounces"], "chroma": st["chroma"],
                                "first_bounce": st["first_bounce"], "march_samples": st["march_samples"],
                                "secondary_march_samples": st["secondary_march_samples"],
                                "depth_stride": m.stride_for(W, H), "variant": c["variant"],
                                "coefficients": m.enc.n,
                                "grid": list(Grid.around(s.bbox_min, s.bbox_max, st["resolution"]).dims)})
                    group.append(row)
                    finals.append(composed)
                # ------------------- against the RGB3 cache (the paper's comparison) -------------------
                for r, fin in zip(group, finals):
                    base = _base_for(r, group)
                    r["lab_rmse"] = r["pdiff"] = r["de76_fraction"] = None
                    if base is None:
                        continue
                    fb = finals[base]
                    r["lab_rmse"] = float(np.mean([lab_rmse(fb[f][0], fin[f][0], s.exposure) for f in fin]))
                    r["pdiff"] = float(np.mean([pdiff(fb[f][0], fin[f][0], s.exposure) for f in fin]))
                    r["de76_fraction"] = float(np.mean([de76_fraction(fb[f][0], fin[f][0], s.exposure) for f in fin]))
                unopt = next(r for r in group if not r["occupancy"] and r["encoding"] == "rgb3")
                for r in group:
                    b = _base_for(r, group)
                    r["time_vs_rgb3"] = r["time_ms"] / max(group[b]["time_ms"], 1e-9) if b is not None else None
                    r["time_vs_unoptimized"] = r["time_ms"] / max(unopt["time_ms"], 1e-9)
                rows += group
                # ------------------------------ images, Fig. 9 ------------------------------
                stem = out / "images" / f"{s.name}_b{nb}"
                last = max(finals[0])
                io.write_hdr_and_png(stem.with_name(stem.name + "_reference"), finals[0][last][1], s.exposure)
                panels = [("reference (path traced)", finals[0][last][1])]
                for enc in ["rgb3"] + BUDGET:
                    j = next(i for i, r in enumerate(group) if r["variant"] == "" and r["occupancy"]
                             and r["visibility"] == "march" and r["chroma"] == "offset" and r["encoding"] == enc)
                    r, img = group[j], finals[j][last][0]
                    io.write_hdr_and_png(stem.with_name(f"{stem.name}_{enc}"), img, s.exposure)
                    err = "" if enc == "rgb3" else f"\nvs RGB3 {r['lab_rmse']:.2f}%,"
                    label = "Y2Co2Cg2 = RGB2" if enc == "y2co2cg2" else enc.upper()
                    panels.append((f"{label} ({r['coefficients']}){err} vs ref {r['lab_rmse_ref']:.2f}%", img))
                _strip(out / f"fig9_{s.name}_b{nb}.png", panels, s.exposure,
                       f"Fig. 9: {s.name}, {nb} bounce(s): encodings at equal budget (Lab RMSE)")
                _plot(out / f"crc_{s.name}_b{nb}.png", group, f"{s.name}, {nb} bounce(s), {W}x{H}")
                # ------------------- stage profile (alternating order, same G-buffers) -------------------
                specs = {enc: _spec({**common, "bounces": nb, "encoding": enc}) for enc in PROFILED}
                bar.set_postfix_str(f"{s.name}/profile/b{nb}")
                prof = _profile(s, viewers, list(specs.values()), W, H, preset["profile_frames"],
                                min(3, preset["profile_frames"] - 1), opts.seed)
                prof_rows += _profile_rows(s.name, nb, prof, specs)
                # ------------------------ error terms, moving volume ------------------------
                bar.set_postfix_str(f"{s.name}/terms/b{nb}")
                term_rows.append(_error_terms(s, viewers, nb, common, W, H, preset["frames"], opts.seed,
                                              preset["ref_spp"], preset["direct_spp"]))
                if s.name not in MOVING["skip"]:
                    bar.set_postfix_str(f"{s.name}/moving/b{nb}")
                    moving_rows.append(_moving(s, viewers, nb, common, W, H, preset["frames"], opts.seed,
                                               preset["ref_spp"], preset["direct_spp"]))
            # ------------------------------ Figs. 5 and 10 ------------------------------
            if 1 in preset["bounces"]:
                bar.set_postfix_str(f"{s.name}/path")
                pts = _along_path(s, viewers[0], _spec({**common, "bounces": 1}), W, H, preset["path_positions"],
                                  opts.seed)
                path_rows += [{"scene": s.name, **p} for p in pts]
                _plot_path(out / f"fig5_{s.name}.png", pts, f"Fig. 5: {s.name}, depth occupancy along the path")
            if si == 0:
                bar.set_postfix_str(f"{s.name}/sweep")
                sw = _sweep(s, viewers, preset["sweep"], W, H, opts.seed)
                sweep_rows += [{"scene": s.name, **r} for r in sw]
                _plot_sweep(out / f"fig10_{s.name}.png", sw, f"Fig. 10: {s.name}, 2 bounces, Y3Co1Cg1")

    config = {"quick": bool(opts.quick), "scenes": names, **preset, "seed": opts.seed,
              "pdiff": "Yee and Newman's PerceptualDiff (slc.methods.crc.quality.pdiff): percent of pixels visibly "
                       "different from the RGB3 cache (pdiff_ref: from the reference)",
              "de76_fraction": "percent of pixels with CIE76 dE > 2.3 against the RGB3 cache",
              "lab_rmse": "CIE Lab RMSE (percent) against the RGB3 cache of the same sampling; "
                          "lab_rmse_ref against the reference",
              "reference": "slc.reference.references: indirect reference (the method's bounces) + ground-truth direct light",
              "indirect_metrics": "indirect_*: the pipeline's comparison of the indirect light alone with the "
                                  "indirect reference (exposure 0.8 / p99 of the reference)",
              "profile": "stage ms, minimum and median over frames after 3 warm-up, encodings run frame by frame "
                         "in alternating order on the same G-buffers"}
    results = experiment.results_object(NAME, config, experiment.strip_private(rows))
    results["profile"] = prof_rows
    results["fig5_path"] = path_rows
    results["fig10_sweep"] = sweep_rows
    results["error_terms"] = term_rows
    results["moving"] = moving_rows
    experiment.write_results(out, results, _markdown(rows, prof_rows, path_rows, sweep_rows, preset, names,
                                                     term_rows, moving_rows))
    print(f"results: {out / 'results.json'}")
    return results


def _f(v, fmt="{:.2f}"):
    return "-" if v is None else fmt.format(v)


def _markdown(rows, prof_rows, path_rows, sweep_rows, preset, names, term_rows=(), moving_rows=()) -> str:
    from slc.run import experiment
    W, H = preset["width"], preset["height"]
    cols = [("scene", "scene"), ("bounces", "b"), ("variant", "variant"), ("visibility", "visibility"),
            ("occupancy", "occ."), ("encoding", "encoding"), ("chroma", "chroma"), ("coefficients", "coeffs"),
            ("occupancy_ratio", "occ. ratio"), ("time_ms", "t [ms]"), ("time_vs_rgb3", "t / RGB3"),
            ("time_vs_unoptimized", "t / unopt."), ("lab_rmse", "Lab RMSE vs RGB3 [%]"),
            ("pdiff", "pdiff vs RGB3 [%]"), ("lab_rmse_ref", "Lab RMSE vs ref [%]"), ("pdiff_ref", "pdiff vs ref [%]"),
            ("flip", "FLIP"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]
    md = (f"# {NAME}\n\n{W}x{H}, {preset['frames']} frames ({preset['warmup']} warm-up), grid resolution "
          f"{preset['resolution']}, the paper's defaults (RSM + Halton, march samples 10 / 5, depth stride 10 at "
          f"1 MPixel = {max(1, round(10 * (W * H / 1e6) ** 0.5))} here). t = median cache ms per frame through "
          f"the pipeline, configurations one after the other (load-sensitive; see the stage profile for "
          f"side-by-side ratios). Lab RMSE and pdiff (Yee's PerceptualDiff) against the RGB3 cache of the same "
          f"sampling (the paper's Table 1 comparison) and against the reference (ground-truth direct + "
          f"{preset['ref_spp']} spp path-traced indirect, slc.reference.references; FLIP and SSIM too). Variants: "
          f"`paths` = light-traced VPLs + PCG32, `dense` = one march sample per voxel, `stride10` = the literal "
          f"s = 10 at this frame size.\n\n" + experiment.markdown_table(rows, cols) + "\n")
    # ------------------------------- stage profile -------------------------------
    encs = [e for e in PROFILED if e != "rgb3"]
    from slc.methods.crc.cache import CRCCache
    stage_names = set(CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES)
    md += ("\n## Stage profile (encodings side by side)\n\nms per frame, minimum (median) over the profiled frames "
           "after warm-up, encodings run frame by frame in alternating order on the same G-buffers "
           f"(reconstruct: per frame the minimum of {RECONSTRUCT_REPEATS} runs). "
           "*Coefficient stages* (work proportional to the coefficient count): bounce1_project (projection and "
           "accumulation of the first bounce), bounce2_project (secondary-bounce lookups of the previous volume "
           "+ projection: the propagation), blend, reconstruct. *Fixed stages*: occupancy, lights (light "
           "injection: RSM), bounce1_march and bounce2_march (visibility marching). *Total without lights*: the "
           "sum of the stages' minima but the RSM (the paper's GI time does not include rendering the RSM).\n\n")
    md += ("| scene | b | stage | RGB3 [ms] | " + " | ".join(f"{e.upper()} [ms] | {e.upper()} / RGB3" for e in encs)
           + " |\n|" + "---|" * (4 + 2 * len(encs)) + "\n")
    for r in prof_rows:
        cells = [r["scene"], str(r["bounces"]), f"**{r['stage']}**" if r["stage"] not in stage_names
                 else r["stage"], f"{r['rgb3_min']:.2f} ({r['rgb3_median']:.2f})"]
        for e in encs:
            cells += [f"{r[e + '_min']:.2f} ({r[e + '_median']:.2f})",
                      f"{r[e + '_vs_rgb3_min']:.2f} ({r[e + '_vs_rgb3_median']:.2f})"]
        md += "| " + " | ".join(cells) + " |\n"
    # ------------------------------- Figs. 5 and 10 -------------------------------
    if path_rows:
        md += ("\n## Fig. 5: depth occupancy along the camera path (1 bounce, Y3Co1Cg1)\n\n"
               "| scene | position | frame | occupancy ratio | active cells | first bounce [ms] | total [ms] |\n"
               "|---|---|---|---|---|---|---|\n")
        for p in path_rows:
            md += (f"| {p['scene']} | {p['position'] + 1} | {p['frame']} | {p['occupancy_ratio']:.3f} | "
                   f"{p['active_cells']} | {p['bounce1_ms']:.2f} | {p['total_ms']:.2f} |\n")
    if sweep_rows:
        from slc.methods.crc.cache import CRCCache
        st = [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if any(k in r for r in sweep_rows)]
        md += ("\n## Fig. 10: stage ms against the CRC resolution (2 bounces, Y3Co1Cg1, min of 3 frames)\n\n"
               "| scene | resolution | cells | occupancy | " + " | ".join(st) + " | total | voxelize (once) |\n|"
               + "---|" * (6 + len(st)) + "\n")
        for r in sweep_rows:
            md += (f"| {r['scene']} | {r['resolution']} | {r['cells']} | {r['occupancy_ratio']:.3f} | "
                   + " | ".join(f"{r.get(k, 0.0):.2f}" for k in st) + f" | {r['total_ms']:.2f} | "
                   f"{r['voxelize_ms']:.0f} |\n")
    # ------------------------------- error terms -------------------------------
    if term_rows:
        md += ("\n## Error terms (Lab RMSE [%] of the composited image, last frame, each term alone)\n\n"
               "*encoding*: Y3Co1Cg1 against RGB3 of the same sampling (the paper's Table 1 comparison), "
               "offset (the paper's) / ratio decoding, at the default samples per cache point and at "
               f"{TERMS_SAMPLES}x (what stays is systematic). *noise*: RGB3 against RGB3 with another seed "
               "(two independent estimates). *fp16*: the RGB3 cache (high samples) stored as float16 against "
               "float32. *interpolation* (1 bounce): the grid cache against the estimator evaluated at each "
               "shaded point's own lookup point, both at the high sample count (includes that per-point "
               "estimate's own noise). *ref noise*: the indirect "
               "reference against one with 4x its paths. Against the reference: RGB3 at both sample counts; "
               "*unfiltered*: the estimator at the shaded points.\n\n"
               "| scene | b | encoding offset / ratio | same at high samples | noise (2 seeds) | fp16 | "
               "interpolation | ref noise | RGB3 vs ref / high samples / vs 4x ref | unfiltered vs ref | "
               "RGB3 (high) mean / ref (R, G, B) | indirect share |\n|" + "---|" * 12 + "\n")
        for t in term_rows:
            md += (f"| {t['scene']} | {t['bounces']} | {t['encoding_offset']:.2f} / {t['encoding_ratio']:.2f} | "
                   f"{t['encoding_offset_hi']:.2f} / {t['encoding_ratio_hi']:.2f} | {t['noise_two_seeds']:.2f} | "
                   f"{t['quantisation_fp16']:.4f} | {_f(t['interpolation'])} | {t['reference_noise']:.2f} | "
                   f"{t['rgb3_vs_ref']:.2f} / {t['rgb3_hi_vs_ref']:.2f} / {t['rgb3_vs_ref4']:.2f} | "
                   f"{_f(t['unfiltered_hi_vs_ref'])} | {', '.join(f'{v:.2f}' for v in t['rgb3_hi_mean_over_ref'])} | "
                   f"{t['indirect_share']:.2f} |\n")
    # ------------------------------- moving volume -------------------------------
    if moving_rows:
        md += ("\n## Moving volume (volume=camera) against the grid over the scene (Y3Co1Cg1)\n\n"
               f"A window of `window` cells per side of the same lattice, re-centred on the viewer in whole "
               f"cells (coefficients scrolled); the camera walks {MOVING['step']} path frames per rendered frame; "
               "both caches render the same G-buffers in alternating order. Times: median ms per frame after 2 "
               "warm-up frames (load-sensitive; the ratio is side by side). Kernels: built or loaded by the "
               "moving cache after warm-up and after its first move (which builds the scroll kernel once). "
               "Lab RMSE at the last frame against the reference, over the image and "
               "over the pixels inside the window (outside it the moving cache gives no indirect light; the "
               "paper blends in an ambient colour there).\n\n"
               "| scene | b | window | cells (window / scene) | moves | kernels built | t scene [ms] | "
               "t camera [ms] | camera / scene | scroll [ms] | pixels inside | Lab RMSE vs ref: scene / camera | "
               "inside: scene / camera | camera vs scene inside |\n|" + "---|" * 14 + "\n")
        for r in moving_rows:
            md += (f"| {r['scene']} | {r['bounces']} | {r['window']} | {r['window_cells']} / {r['grid_cells']} | "
                   f"{r['moves']} | {r['kernels_built_after_warmup']} | {r['time_scene_ms']:.1f} | "
                   f"{r['time_camera_ms']:.1f} | {r['time_camera_vs_scene']:.2f} | {r['scroll_ms']:.2f} | "
                   f"{r['inside_fraction']:.2f} | {_f(r['lab_rmse_ref_scene'])} / {_f(r['lab_rmse_ref_camera'])} | "
                   f"{_f(r['lab_rmse_ref_scene_inside'])} / {_f(r['lab_rmse_ref_camera_inside'])} | "
                   f"{_f(r['camera_vs_scene_inside'])} |\n")
    # ----------------------------------- targets -----------------------------------
    md += "\n## Targets\n\n"
    for name in names:
        for nb in preset["bounces"]:
            g = [r for r in rows if r["scene"] == name and r["bounces"] == nb]
            std = [r for r in g if r["variant"] == "" and r["visibility"] == "march"]
            y1 = next(r for r in std if r["occupancy"] and r["encoding"] == "y3co1cg1" and r["chroma"] == "offset")
            y1r = next(r for r in std if r["chroma"] == "ratio")
            rgb = next(r for r in std if r["occupancy"] and r["encoding"] == "rgb3")
            off = next(r for r in std if not r["occupancy"])
            p = {r["stage"]: r for r in prof_rows if r["scene"] == name and r["bounces"] == nb}
            c, t, g = p["coefficient stages"], p["total"], p["total without lights"]
            md += (f"- {name}, {nb} bounce(s): Y3Co1Cg1 / RGB3 time on the coefficient stages "
                   f"{c['y3co1cg1_vs_rgb3_min']:.2f} (median {c['y3co1cg1_vs_rgb3_median']:.2f}; target <= 0.75), "
                   f"total {t['y3co1cg1_vs_rgb3_min']:.2f} (median {t['y3co1cg1_vs_rgb3_median']:.2f}), without "
                   f"the RSM {g['y3co1cg1_vs_rgb3_min']:.2f} ({g['y3co1cg1_vs_rgb3_median']:.2f}); "
                   f"Lab RMSE vs RGB3 {y1['lab_rmse']:.2f}% (ratio decoding {y1r['lab_rmse']:.2f}%), pdiff "
                   f"{y1['pdiff']:.2f}% ({y1r['pdiff']:.2f}%); Lab RMSE vs reference: Y3Co1Cg1 "
                   f"{y1['lab_rmse_ref']:.2f}%, RGB3 {rgb['lab_rmse_ref']:.2f}% (target < 1% on non-Cornell "
                   f"scenes); occupancy ratio {rgb['occupancy_ratio']:.2f}, occupancy on/off time "
                   f"{rgb['time_ms'] / max(off['time_ms'], 1e-9):.2f}\n")
            t = next((x for x in term_rows if x["scene"] == name and x["bounces"] == nb), None)
            if t is not None:
                md += (f"  - error terms: encoding (offset) {t['encoding_offset']:.2f}% ({t['encoding_offset_hi']:.2f}% "
                       f"at {t['samples_hi']} samples: systematic), ratio {t['encoding_ratio']:.2f}% "
                       f"({t['encoding_ratio_hi']:.2f}%); noise {t['noise_two_seeds']:.2f}% between seeds; fp16 "
                       f"{t['quantisation_fp16']:.4f}%; interpolation {_f(t['interpolation'])}%; reference noise "
                       f"{t['reference_noise']:.2f}%; RGB3 vs reference {t['rgb3_vs_ref']:.2f}% "
                       f"({t['rgb3_hi_vs_ref']:.2f}% at {t['samples_hi']} samples)\n")
            mv = next((x for x in moving_rows if x["scene"] == name and x["bounces"] == nb), None)
            if mv is not None:
                md += (f"  - moving volume ({mv['window']}^3 of {mv['grid_cells']} cells): {mv['moves']} moves, "
                       f"{mv['kernels_built_after_warmup']} kernels built after warm-up, time {mv['time_camera_vs_scene']:.2f}x "
                       f"the scene grid's (scroll {mv['scroll_ms']:.2f} ms); Lab RMSE vs reference inside the window "
                       f"{_f(mv['lab_rmse_ref_camera_inside'])}% (scene grid {_f(mv['lab_rmse_ref_scene_inside'])}%), "
                       f"whole image {_f(mv['lab_rmse_ref_camera'])}% ({_f(mv['lab_rmse_ref_scene'])}%)\n")
    return md


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
