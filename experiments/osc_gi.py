"""osc-gi: global illumination with on-surface radiance caches (the slides' tables and figures).

Per scene (one viewer on the scene's first camera path, moving):

- ``osc-gi`` (full light: direct + indirect) through the common pipeline against the reference of
  its kind (:func:`slc.references.reference_for` with ``ref_spp``: ``ref_spp``-sample direct light +
  the ``ref_spp``-path indirect reference with the method's bounces; the pipeline passes ``ref_spp``
  for every part of a full reference), with the slides' timing split: *cache* (the on-surface cache's requests,
  allocation, queue), *effect* (primary and secondary cache updates: all rays), *display* (shading
  the pixels from the primary caches); memory of the primary caches (on-surface cache + payloads)
  and of the secondary cells in use, min and max over the path; the secondary-cache reuse
  histogram (primary-cache rays per touched cell, last frame);
- beside ``osc-gi`` (whose direct light is per pixel, ``direct=rt``), the same with the defaults
  before session gi8 (independent light samples, 8 glossy samples, 30 cm cells, 32 rays per cell
  update, cells' EMA over 4 updates; also for the indirect light), before session gi6 (direct light cached in the entries,
  32 texel rays, EMA over 8, 30 cm cells in any scene) and with the other direct-light options (``DIRECT_VARIANTS``: cached, cones, ReSTIR, RT-4), also
  under ``--no-ablations``; each row gets its own FLIP / PT at equal time;
- path tracing (``pt``, full light, its estimator frozen) at several sample counts, for the speed-against-error plot and
  the FLIP of PT at osc-gi's time (log-log interpolation between the two PT points around it);
- the indirect light alone: ``osc-gi:output=indirect``, ``pt`` (indirect) and ``crc`` against the
  indirect reference;
- multi-viewer (unless ``--no-multi``): 1, 4, 16 viewers at about 75% overlap
  (:func:`slc.views.overlap_rig` about the look-at point where the camera is outside the scene),
  time against viewer count, per stage, the first viewer's FLIP at the last frame; the 16-viewer
  row also without the update budget and front-only requests (``MULTI_ABLATIONS``, session gi9),
  and the 16-viewer fan's first view alone (the fan's views are narrowed when it would span more
  than 360 degrees); 3 repetitions in alternating order, the ratio to one viewer per repetition;
- ablations (unless ``--no-ablations``): secondary cells of 30/60 cm (15 cm the default since session gi8), 1 and 3 bounces (each against
  its own reference), cells not keyed by shape (``--quick``: 60 cm and 1 bounce only).

- with ``--laps``: one more osc-gi run per scene with the update's sub-stage clock
  (:class:`slc.oscgi.laps.Laps`; host syncs between stages), written as ``update_laps_ms``.

The full preset runs cornell and atrium at 160x90 (24 frames, 8 warm-up); ``--quick`` cornell at 64x36
(8 frames, 3 warm-up, PT at 1-64 spp); ``--frames F`` keeps at most max(3, F // 3) warm-up frames
(``--warmup`` sets it): ``--res 256x144 --frames 10`` times 7 frames (2 before session gi8).
PT at equal time: PT's time per frame fitted as a + b spp over its rows, the sample count it
affords at the method's time, FLIP interpolated log-log between the spp rows around it
(``flip_vs_pt_equal_time``; the former interpolation in the PT rows' own times is kept as
``flip_vs_pt_equal_time_direct``). ``--retime N`` (3): afterwards osc-gi (now and before session
gi8) and the PT rows are timed again in turn, N passes, each with its own ratio (the median is
reported): the shared cores' load changes within a run. Both also run this session's switches one at a time (``SESSION_ABLATIONS``:
osc-gi and pt not frozen, osc-gi without the glossy-hit rays, osc-gi at mip bias 1).

    python experiments/osc_gi.py --quick
    slc run osc-gi --quick [--scene cornell]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = "osc-gi"

FILTER_ABLATIONS = ["osc-gi:filter_radius=3", "osc-gi:filter_radius=3,parallax=0",
                    "osc-gi:output=indirect,filter_radius=3", "osc-gi:output=indirect,filter_radius=3,parallax=0"]
# this session's changes, switched off one at a time (before/after in one run): the frozen kernels of
# osc-gi and pt, the NEE + BSDF ray at glossy hits; and the finer mip bias
# session gi6: the defaults before it (cached direct light, 32 texel rays, EMA over 8, 30 cm cells in any
# scene) and the other direct-light options, run with the main rows (also under --no-ablations)
# session gi8: the defaults before it (independent light samples per pixel, 8 glossy samples, 30 cm cells,
# 32 rays per cell update, the cells' EMA over n_max = 4 updates): the row "before" of its table, in the same run
BEFORE_GI8_CELLS = "glossy_samples=8,secondary_cm=30,secondary_rays=32,secondary_n_max=0"
BEFORE_GI8 = f"direct_lds=0,{BEFORE_GI8_CELLS}"
BEFORE_GI6 = f"texel_rays=32,n_max=8,secondary_scene=0,{BEFORE_GI8_CELLS}"
DIRECT_VARIANTS = [f"osc-gi:{BEFORE_GI8}", f"osc-gi:direct=cache,{BEFORE_GI6}", "osc-gi:direct=cache",
                   "osc-gi:direct=cones", "osc-gi:direct=restir", "osc-gi:direct=rt,direct_n=4"]
INDIRECT_VARIANTS = [f"osc-gi:output=indirect,{BEFORE_GI8_CELLS}", f"osc-gi:output=indirect,{BEFORE_GI6}"]
SESSION_ABLATIONS = ["osc-gi:freeze=0", "osc-gi:glossy_hits=0", "osc-gi:bias=1", "pt:spp=2,freeze=0",
                     "pt:spp=16,freeze=0"]
# overlap: the rig's target (calibrated on another cache): 0.75 measured 76% with osc-gi's cache at
# 16 viewers on cornell (0.7: 55%, 0.8: 80%), inside the target's 60-80%
FULL = dict(scenes=["cornell", "atrium"], width=160, height=90, frames=24, warmup=8, eval_frames=[23],
            ref_spp=256, pt_spp=[1, 2, 4, 8, 16, 32, 64], ind_pt=5, viewers=[1, 4, 16], overlap=0.75,
            multi_res=(64, 36), multi_frames=20, multi_warmup=5, multi_repeats=3,
            ablations=SESSION_ABLATIONS + FILTER_ABLATIONS + ["osc-gi:secondary_cm=30", "osc-gi:secondary_cm=60",
                                                           "osc-gi:bounces=1", "osc-gi:bounces=3", "osc-gi:shape_key=0"],
            memory_res=[(64, 36), (128, 72), (256, 144), (480, 270)])
QUICK = dict(scenes=["cornell"], width=64, height=36, frames=8, warmup=3, eval_frames=[7],
             ref_spp=64, pt_spp=[1, 2, 4, 8, 16, 32, 64], ind_pt=5, viewers=[1, 4, 16], overlap=0.75,
             multi_res=(32, 18), multi_frames=16, multi_warmup=4, multi_repeats=3,
             ablations=SESSION_ABLATIONS + FILTER_ABLATIONS + ["osc-gi:secondary_cm=60", "osc-gi:bounces=1"],
             memory_res=[(64, 36), (128, 72), (256, 144)])
# multi-viewer: the 16-viewer row also without this session's (gi9) update budget and front-only requests
MULTI_ABLATIONS = ["osc-gi:update_budget=0", "osc-gi:update_budget=0,front_only=0"]
SLIDES_1080P_MB = (300, 700)        # the slides' single-viewer memory at 1080p (GPU)
CACHE_STAGES = ("requests", "allocate", "queue")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset: cornell only, 64x36, 8 frames")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/osc-gi)")
    p.add_argument("--res", help="WxH (default 160x90, quick 64x36)")
    p.add_argument("--frames", type=int, help="frames per sequence")
    p.add_argument("--warmup", type=int, help="frames not timed (default: the preset's; with --frames at most "
                   "max(3, frames // 3), so that --frames 10 times 7 frames rather than 2)")
    p.add_argument("--no-multi", action="store_true", help="skip the multi-viewer runs")
    p.add_argument("--no-ablations", action="store_true", help="skip the ablations")
    p.add_argument("--only-multi", action="store_true", help="run the multi-viewer part only")
    p.add_argument("--no-memory", action="store_true", help="skip the memory-against-resolution runs")
    p.add_argument("--retime", type=int, default=3,
                   help="after the rows: time osc-gi (now and before session gi8) and the PT rows again, in turn, "
                        "this many times; the equal-time ratio of each pass from its own times (0: off)")
    p.add_argument("--laps", action="store_true",
                   help="one more osc-gi run with the update's sub-stage clock (host syncs between stages)")
    p.add_argument("--seed", type=int, default=0)


def _split(stages: dict) -> dict:
    return {"cache_ms": sum(stages.get(k, 0.0) for k in CACHE_STAGES), "effect_ms": stages.get("update", 0.0),
            "display_ms": stages.get("shade", 0.0) + stages.get("direct", 0.0)}


def _equal_time_direct(pt_rows, t):
    """FLIP of PT at time t, log-log interpolation between the PT points around t in measured time
    (None outside); a PT row timed slow or fast by the load moves it (see :func:`_equal_time`)."""
    import math
    pts = sorted((r["time_ms"], r["flip"]) for r in pt_rows if r["time_ms"] > 0 and r["flip"] > 0)
    for (t0, f0), (t1, f1) in zip(pts, pts[1:]):
        if t0 <= t <= t1 and t1 > t0:
            a = (math.log(t) - math.log(t0)) / (math.log(t1) - math.log(t0))
            return math.exp(math.log(f0) + a * (math.log(f1) - math.log(f0)))
    return None


def _pt_cost(pt_rows):
    """PT's time per frame as a + b spp, least squares over all PT rows on relative errors (weights
    1/t^2): PT's work is a fixed part plus one path per pixel and sample, so one row timed slow or
    fast by the machine's load no longer decides the equal-time point alone. Returns (a, b) or None."""
    import numpy as np
    pts = [(float(r["spp"]), r["time_ms"]) for r in pt_rows if r.get("spp") and r["time_ms"] > 0]
    if len(pts) < 2:
        return None
    n, t = np.array(pts).T
    w = 1.0 / t
    a, b = np.linalg.lstsq(np.stack([w, n * w], 1), t * w, rcond=None)[0]
    return (float(a), float(b)) if b > 0 else None


def _equal_time(pt_rows, t):
    """FLIP of PT at time t: the sample count PT affords in t by its fitted cost (:func:`_pt_cost`),
    then log-log interpolation of FLIP between the PT rows around that count (FLIP against spp is
    exact: the same random numbers in every run). None outside the measured spp range."""
    import math
    cost = _pt_cost(pt_rows)
    if cost is None:
        return None
    spp = (t - cost[0]) / cost[1]
    pts = sorted((float(r["spp"]), r["flip"]) for r in pt_rows if r.get("spp") and r["flip"] > 0)
    for (n0, f0), (n1, f1) in zip(pts, pts[1:]):
        if n0 <= spp <= n1 and n1 > n0:
            a = (math.log(spp) - math.log(n0)) / (math.log(n1) - math.log(n0))
            return math.exp(math.log(f0) + a * (math.log(f1) - math.log(f0)))
    return None


RETIMED = ("osc-gi", f"osc-gi:{BEFORE_GI8}")     # rows timed again beside PT (--retime)


def _retime(s, v, cfg, srows, opts, bar=None) -> None:
    """Time the rows ``RETIMED`` and the full-light PT rows again, one after the other, ``opts.retime``
    passes (no evaluation; the same frames and warm-up): each pass gives osc-gi / PT at equal time from
    its own times (:func:`_equal_time`, FLIP from the rows), so a load that changes during the run
    (2 shared cores) no longer compares a quiet osc-gi row with loaded PT rows or the reverse.
    Written into the rows: ``retimed_ms``, ``flip_vs_pt_retimed`` (per pass) and its median."""
    import dataclasses
    import statistics

    from slc import experiment
    pts = [r for r in srows if r["group"] == "full" and r["family"] == "pt"]
    rows = [r for r in srows if r["group"] == "full" and r["setting"] in RETIMED]
    if not pts or not rows:
        return
    tcfg = dataclasses.replace(cfg, eval_frames=[], keep_images=False)      # no frame evaluated
    every = rows + pts

    def before(i):
        if bar is not None:
            bar.set_postfix_str(f"{s.name}/{every[i]['setting']} (retime)")

    runs = experiment.runs_in_turn(s, [(r["setting"], v) for r in every], tcfg, opts.retime, opts.seed,
                                   alternate=False, before=before)
    times = {r["setting"]: [x.time_ms for x in rs] for r, rs in zip(every, runs)}
    for r, rs in zip(every, runs):
        r["retime_compiled_after_warmup"] = r.get("retime_compiled_after_warmup", 0) + sum(
            x.compiled_after_warmup for x in rs)
    for r in rows:
        ratios = []
        for i in range(opts.retime):
            f = _equal_time([dict(p, time_ms=times[p["setting"]][i]) for p in pts], times[r["setting"]][i])
            ratios.append(r["flip"] / f if f else None)
        r["retimed_ms"] = times[r["setting"]]
        r["flip_vs_pt_retimed"] = ratios
        ok = [x for x in ratios if x is not None]
        r["flip_vs_pt_retimed_median"] = statistics.median(ok) if ok else None
    for p in pts:
        p["retimed_ms"] = times[p["setting"]]


def _reuse_plot(path, hist, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from slc import io
    fig, ax = plt.subplots(figsize=(5, 3.2))
    b = hist["bins"]
    labels = [f"{lo}" if hi == lo + 1 else (f"{lo}-{hi - 1}" if hi < 1 << 20 else f">={lo}")
              for lo, hi in zip(b, b[1:])]
    ax.bar(range(len(labels)), hist["counts"])
    ax.set_xticks(range(len(labels)), labels, fontsize=7)
    ax.set_xlabel("primary-cache rays per secondary cell (one frame)")
    ax.set_ylabel("secondary cells")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _memory_scaling(s, v, resolutions, seed) -> list:
    """osc-gi's memory at several resolutions (one viewer, 3 frames): the primary caches (the
    on-surface cache + payloads of the allocated entries), the secondary cells in use and the
    secondary table; a least-squares line in the pixel count through the primary + secondary
    figures, evaluated at 1920 x 1080 (the slides' single-viewer 300-700 MB)."""
    import numpy as np

    from slc import methods
    from slc.pipeline import RunConfig, run_sequence
    out = []
    for w, h in resolutions:
        m = methods.create("osc-gi", s, seed=seed)
        run_sequence(s, m, v, RunConfig(width=w, height=h, frames=3, warmup=1, eval_frames=[], seed=seed,
                                        measure_overlap=False))
        prim, sec = m.memory_log[-1]
        out.append({"scene": s.name, "resolution": f"{w}x{h}", "pixels": w * h,
                    "entries": int(m.cache.entries_allocated()), "primary_mb": prim / 2 ** 20,
                    "secondary_mb": sec / 2 ** 20, "secondary_table_mb": m.secondary.memory_bytes() / 2 ** 20,
                    "transient_filter_mb": 0.0 if m.filter.r <= 0 else 4 * dr_width(m.storage) / 2 ** 20})
    px = np.array([r["pixels"] for r in out], dtype=np.float64)
    y = np.array([r["primary_mb"] + r["secondary_mb"] for r in out])
    if len(out) >= 2:
        slope, icpt = np.polyfit(px, y, 1)
        est = float(slope * 1920 * 1080 + icpt)
        for r in out:
            r["estimate_1080p_mb"] = est
            r["estimate_1080p_with_table_mb"] = est + r["secondary_table_mb"]
    return out


def dr_width(x) -> int:
    import drjit as dr
    return dr.width(x)


def run(opts) -> dict:
    import dataclasses

    from tqdm import tqdm

    from slc import experiment, methods, views
    from slc.pipeline import RunConfig, run_sequence

    preset = experiment.apply_common(opts, QUICK if opts.quick else FULL)
    if getattr(opts, "warmup", None) is not None:
        if not 0 <= opts.warmup < preset["frames"]:
            raise experiment.ExperimentError("--warmup must be at least 0 and below the frame count")
        preset["warmup"] = opts.warmup
    elif getattr(opts, "frames", None):
        # a short sequence keeps 3 warm-up frames (the kernels are built in frames 0-2) and times the rest
        preset["warmup"] = min(preset["warmup"], max(3, preset["frames"] // 3))
    W, H = preset["width"], preset["height"]
    out = Path(opts.out) / NAME
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    cfg = RunConfig(width=W, height=H, frames=preset["frames"], warmup=preset["warmup"],
                    eval_frames=preset["eval_frames"], seed=opts.seed, ref_spp=preset["ref_spp"],
                    measure_overlap=False)
    main_specs = [] if opts.only_multi else ["osc-gi"] + DIRECT_VARIANTS + [f"pt:spp={n}" for n in preset["pt_spp"]]
    ind_specs = [] if opts.only_multi else (["osc-gi:output=indirect"] + INDIRECT_VARIANTS
                                            + [f"pt:spp={n},output=indirect" for n in preset["pt_spp"][:preset["ind_pt"]]]
                                            + ["crc"])
    abl_specs = [] if opts.no_ablations or opts.only_multi else list(preset["ablations"])
    for spec in main_specs + ind_specs + abl_specs:      # bad specs stop the run before any work
        methods.parse_spec(spec)

    rows, multi, hists, laps, memory = [], [], {}, {}, []
    n_runs = len(names) * (len(main_specs) + len(ind_specs) + len(abl_specs))
    with tqdm(total=n_runs * preset["frames"], desc=NAME, unit="frame", disable=None) as bar:
        for s in experiment.each_scene(names):
            v = views.single(s)

            def one(spec, group, cfg=cfg, viewers=v):
                m = methods.create(spec, s, seed=opts.seed)
                bar.set_postfix_str(f"{s.name}/{spec}")
                res = run_sequence(s, m, viewers, cfg, progress=bar)
                row = {"scene": s.name, **res.row(), "setting": spec, "label": m.label or m.name,
                       "group": group, "output": m.output, "bounces": getattr(m, "bounces", None),
                       "family": spec.split(":")[0], "resolution": f"{cfg.width}x{cfg.height}",
                       "spp": getattr(m, "spp", None) if spec.startswith("pt") else None}
                row.pop("frames_ms", None)
                row.update(_split(res.stages))
                if spec.startswith("osc-gi"):
                    log = m.memory_log[cfg.warmup:] or m.memory_log
                    row.update({"primary_mb_min": min(p for p, _ in log) / 2 ** 20,
                                "primary_mb_max": max(p for p, _ in log) / 2 ** 20,
                                "secondary_mb_min": min(q for _, q in log) / 2 ** 20,
                                "secondary_mb_max": max(q for _, q in log) / 2 ** 20,
                                "secondary_table_mb": m.secondary.memory_bytes() / 2 ** 20,
                                "bytes_per_entry": m.payload_bytes()})
                return row, res, m

            for spec in main_specs + ind_specs + abl_specs:
                group = "full" if spec in main_specs else ("indirect" if spec in ind_specs else "ablation")
                row, res, m = one(spec, group)
                rows.append(row)
                if spec in ("osc-gi", "osc-gi:output=indirect") or spec == "pt:spp=1":
                    experiment.save_strip(out, s, row["label"], res)
                if spec == "osc-gi":
                    hists[s.name] = m.secondary.reuse_histogram()
                    row["reuse_histogram"] = hists[s.name]
                    _reuse_plot(out / f"reuse_{s.name}.png", hists[s.name],
                                f"{s.name}: secondary-cache reuse ({W}x{H}, 1 viewer)")
            if getattr(opts, "laps", False) and not opts.only_multi:
                # ------ the update's sub-stages (a separate run: the clock's syncs split kernels) ------
                m = methods.create("osc-gi", s, seed=opts.seed)
                m._profile, m._profile_skip = True, cfg.warmup
                m.reset()
                run_sequence(s, m, v, cfg)
                laps[s.name] = {k: round(x, 2) for k, x in m.laps.per_frame().items()}
            # ----------------------------- equal-time comparison with PT -----------------------------
            srows = [r for r in rows if r["scene"] == s.name]
            for grp in ("full", "indirect"):
                pts = [r for r in srows if r["group"] == grp and r["family"] == "pt"]
                cost = _pt_cost(pts)
                for r in srows:
                    if r["group"] == grp and r["family"] != "pt":
                        f_pt = _equal_time(pts, r["time_ms"])
                        r["pt_flip_equal_time"] = f_pt
                        r["flip_vs_pt_equal_time"] = (r["flip"] / f_pt) if f_pt else None
                        # the former estimate (interpolation in the PT rows' own measured times)
                        f_d = _equal_time_direct(pts, r["time_ms"])
                        r["flip_vs_pt_equal_time_direct"] = (r["flip"] / f_d) if f_d else None
                        r["pt_cost_ms"] = cost          # PT time = a + b spp (fit over the PT rows)
                        # slower than PT's most expensive point: PT at equal time is at least that good,
                        # so its FLIP bounds the ratio from below
                        slow = max(pts, key=lambda x: x["time_ms"]) if pts else None
                        if f_pt is None and slow is not None and r["time_ms"] > slow["time_ms"]:
                            r["flip_vs_pt_at_least"] = r["flip"] / slow["flip"]
            # ---- the same rows timed again in turn (a load that changes during the run moves all alike) ----
            if opts.retime > 0 and srows:
                _retime(s, v, cfg, srows, opts, bar)
            if srows:
                experiment.speed_error_plot(out / f"speed_error_{s.name}.png",
                                            [r for r in srows if r["group"] == "full"],
                                            f"{s.name}: full light, time vs FLIP ({W}x{H})")
                experiment.speed_error_plot(out / f"speed_error_indirect_{s.name}.png",
                                            [r for r in srows if r["group"] == "indirect"],
                                            f"{s.name}: indirect light, time vs FLIP ({W}x{H})")
            # ----------------------------------- multi-viewer -----------------------------------
            if not opts.no_multi:
                mw, mh = preset["multi_res"]
                # session gi9: more timed frames (quick: 12 of 16, was 3 of 6: at ~8 ms a frame three
                # medians moved the 16-viewer ratio by +-0.4); the first viewer's FLIP at the last frame
                mf, mw_up = preset["multi_frames"], preset.get("multi_warmup", preset["multi_frames"] // 2)
                mcfg = dataclasses.replace(cfg, width=mw, height=mh, frames=mf, warmup=mw_up, eval_frames=[mf - 1],
                                           eval_viewers=1, measure_overlap=True)
                # a throwaway run first: its kernels (at this resolution) are then in the kernel cache
                run_sequence(s, methods.create("osc-gi", s, seed=opts.seed), v,
                             dataclasses.replace(mcfg, eval_frames=[]))
                # (setting, viewers, rig): the largest rig's first view alone too ("view0"): a fan wider than
                # 360 degrees is narrowed (cornell, 16 views: 18.6 instead of 45 degrees), so its views
                # request finer entries than the one-viewer row
                nmax = max(preset["viewers"])
                m_runs = [("osc-gi", n, "fan") for n in preset["viewers"]] + [("osc-gi", 1, "view0")]
                m_runs += [(a, nmax, "fan") for a in MULTI_ABLATIONS]
                # repetitions in alternating order (1, 4, 16, ... then back): the ratio to one viewer is
                # taken within each repetition (rows minutes apart saw other loads on the shared cores) and
                # its median reported with its range; quality from the first repetition
                def rig_of(n, rig):
                    # pivot "auto": tiles of the camera's own view where it is outside the scene
                    # (cornell: a fan about the eye left 11 of 16 views empty)
                    if rig == "view0":
                        return views.overlap_rig(s, nmax, preset["overlap"], pivot="auto")[:1]
                    return views.overlap_rig(s, n, preset["overlap"], pivot="auto") if n > 1 else v

                reps = preset.get("multi_repeats", 1)
                runs = dict(zip(m_runs, experiment.runs_in_turn(
                    s, [(spec, rig_of(n, rig)) for spec, n, rig in m_runs], dataclasses.replace(mcfg, eval_frames=[]),
                    reps, opts.seed, first_cfg=mcfg)))
                one = runs[("osc-gi", 1, "fan")]
                for spec, n, rig in m_runs:
                    rs = runs[(spec, n, rig)]
                    res, st = rs[0], rs[0].stats
                    med = lambda xs: statistics.median(xs) if xs else 0.0     # noqa: E731
                    stages = {k: med([x.stages.get(k, 0.0) for x in rs]) for k in rs[0].stages}
                    kstages = {k: med([x.stages_kernel.get(k, 0.0) for x in rs]) for k in rs[0].stages_kernel}
                    ratios = [x.time_ms / max(o.time_ms, 1e-9) for x, o in zip(rs, one)]
                    r = {"scene": s.name, "viewers": n, "setting": spec if rig == "fan" else f"{spec} ({nmax}-fan's view 0)",
                         "rig": rig, "target_overlap": preset["overlap"],
                         "time_ms": med([x.time_ms for x in rs]), "time_ms_reps": [x.time_ms for x in rs],
                         "time_vs_one": med(ratios), "time_vs_one_reps": ratios,
                         "time_vs_one_range": f"{min(ratios):.2f}-{max(ratios):.2f}",
                         "frames_timed": mf - mw_up, "repeats": reps,
                         "measured_overlap": st.get("measured_overlap"), "memory_mb": res.memory_mb,
                         "memory_per_viewer_mb": res.memory_mb / n, "entries": st.get("active_entries"),
                         "entries_updated": st.get("entries_updated"), "secondary_cells": st.get("secondary_cells"),
                         "flip_viewer0": res.metrics.get("flip"), "method": "osc-gi", "resolution": f"{mw}x{mh}",
                         "compiled_after_warmup": max(x.compiled_after_warmup for x in rs), **_split(stages),
                         "stages_ms": stages, "stages_kernel_ms": kstages}
                    multi.append(r)
                experiment.time_vs_viewers_plot(out / f"time_vs_viewers_{s.name}.png",
                                                [r for r in multi if r["scene"] == s.name and r["setting"] == "osc-gi"
                                                 and r["rig"] == "fan"],
                                                f"{s.name}: osc-gi, {mw}x{mh} per viewer, overlap "
                                                f"{preset['overlap']:.0%}")

            # ------------------- memory against resolution, extrapolated to 1080p -------------------
            if not getattr(opts, "no_memory", False) and not opts.only_multi:
                memory.extend(_memory_scaling(s, v, preset["memory_res"], opts.seed))

    # ------------------------------------------- report -------------------------------------------
    config = {"quick": bool(opts.quick), "scenes": names, **{k: v for k, v in preset.items() if k != "scenes"},
              "seed": opts.seed,
              "reference": "full: direct ground truth with ref_spp samples + indirect reference (ref_spp paths, "
                           "the method's bounces); indirect rows: the indirect reference alone",
              "timing": "cache = on-surface cache requests/allocate/queue, effect = primary + secondary cache "
                        "updates, display = shading; medians after warm-up on a shared 2-core CPU: ratios only"}
    all_rows = rows + [dict(r, group="multi") for r in multi]
    results = experiment.results_object(NAME, config, experiment.strip_private(all_rows))
    if laps:
        results["update_laps_ms"] = laps
    if memory:
        results["memory_scaling"] = memory
    cols = [("scene", "scene"), ("group", "group"), ("setting", "method"), ("time_ms", "t [ms]"),
            ("cache_ms", "cache"), ("effect_ms", "effect"), ("display_ms", "display"), ("flip", "FLIP"),
            ("psnr", "PSNR"), ("ssim", "SSIM"), ("pt_flip_equal_time", "PT FLIP @ equal t"),
            ("flip_vs_pt_equal_time", "FLIP / PT"), ("primary_mb_min", "primary MB min"),
            ("primary_mb_max", "primary MB max"), ("secondary_mb_min", "secondary MB min"),
            ("secondary_mb_max", "secondary MB max"), ("memory_mb", "memory [MB]")]
    md = (f"# {NAME}\n\n{W}x{H}, {cfg.frames} frames ({cfg.warmup} warm-up), one moving viewer; quality on frames "
          f"{cfg.evaluated()} against the reference of each method's output (full: {cfg.ref_spp}-sample direct + "
          f"{cfg.ref_spp}-path indirect; indirect: the indirect reference); times are medians on a shared CPU "
          f"(compare within this table only). Memory: primary = on-surface cache + payloads, secondary = cells "
          f"in use (the table is allocated up front: secondary_table_mb in results.json).\n\n"
          + (experiment.markdown_table(rows, cols) if rows else "(single-viewer runs skipped)") + "\n")
    if multi:
        md += ("\n## Multi-viewer\n\n" + experiment.markdown_table(
            multi, [("scene", "scene"), ("setting", "method"), ("viewers", "viewers"),
                    ("measured_overlap", "measured overlap %"), ("time_ms", "t [ms]"), ("time_vs_one", "t / 1 viewer"),
                    ("time_vs_one_range", "range"), ("compiled_after_warmup", "kernels after warm-up"),
                    ("entries", "entries"),
                    ("entries_updated", "entries updated"), ("flip_viewer0", "FLIP viewer 0"),
                    ("secondary_cells", "secondary cells"), ("memory_mb", "memory [MB]"),
                    ("memory_per_viewer_mb", "memory / viewer [MB]")]) + "\n")
        md += "\nPer stage (wall ms / of which kernel execution):\n\n"
        for r in multi:
            st, kk = r.get("stages_ms", {}), r.get("stages_kernel_ms", {})
            md += (f"- {r['scene']} {r['setting']}, {r['viewers']} viewers: " + ", ".join(
                f"{k} {st.get(k, 0.0):.1f} / {kk.get(k, 0.0):.1f}" for k in ("requests", "allocate", "queue", "update",
                                                                            "shade", "direct")) + "\n")
    st_rows = [r for r in rows if r["family"] == "osc-gi" and r["group"] in ("full", "indirect")]
    if st_rows:
        md += ("\n## Where the frame time goes (osc-gi; wall ms per stage / of which kernel execution; the rest "
               "is host time: Python tracing of the kernels, launches, syncs)\n\n")
        for r in st_rows:
            st, kk = r.get("stages_ms", {}), r.get("stages_kernel_ms", {})
            md += (f"- {r['scene']} {r['setting']}: " + ", ".join(
                f"{k} {st.get(k, 0.0):.1f} / {kk.get(k, 0.0):.1f}" for k in ("requests", "allocate", "queue", "update",
                                                                            "shade", "direct")) + "\n")
        for r in rows:
            if r["family"] == "pt" and r["group"] == "full":
                md += (f"- {r['scene']} {r['setting']}: shade {r['stages_ms'].get('shade', 0.0):.1f} / "
                       f"{r.get('stages_kernel_ms', {}).get('shade', 0.0):.1f}\n")
    if memory:
        md += ("\n## Memory against resolution (one viewer, 3 frames)\n\n" + experiment.markdown_table(
            memory, [("scene", "scene"), ("resolution", "resolution"), ("entries", "entries"),
                     ("primary_mb", "primary MB"), ("secondary_mb", "secondary MB in use"),
                     ("secondary_table_mb", "secondary table MB"),
                     ("estimate_1080p_mb", "1080p estimate MB (primary + secondary in use)")]) + "\n")
    for name, lp in laps.items():
        md += (f"\n## Update sub-stages, {name} (ms per frame after warm-up, separate run with host syncs)\n\n"
               + ", ".join(f"{k} {x:.1f}" for k, x in lp.items()) + "\n")
    md += "\n## Targets\n\n"
    for name in names:
        r = next((x for x in rows if x["scene"] == name and x["setting"] == "osc-gi"), None)
        ri = next((x for x in rows if x["scene"] == name and x["setting"] == "osc-gi:output=indirect"), None)
        crc = next((x for x in rows if x["scene"] == name and x["setting"] == "crc"), None)
        m16 = next((x for x in multi if x["scene"] == name and x["viewers"] == 16 and x["setting"] == "osc-gi"), None)
        if m16:
            ov = m16['measured_overlap'] or 0
            md += (f"- {name}: 16 viewers at {ov:.0f}% measured overlap cost "
                   f"{m16['time_vs_one']:.2f}x one viewer (median of {m16['repeats']} repetitions, "
                   f"{m16['time_vs_one_range']}; {m16['frames_timed']} timed frames each; target <= 4 at 60-80% overlap"
                   + ("" if 60 <= ov <= 80 else ": overlap outside that range") + ")\n")
        if r is None:
            continue
        for x in rows:
            if x["scene"] == name and x["group"] == "full" and x["family"] == "osc-gi" and x is not r:
                q = x.get("flip_vs_pt_equal_time")
                lb = x.get("flip_vs_pt_at_least")
                md += (f"- {name}, {x['setting']}: FLIP {x['flip']:.4f} at {x['time_ms']:.0f} ms; osc-gi / PT = "
                       + (f"{q:.2f}" if q else (f">= {lb:.2f} (slower than PT's slowest point)" if lb else
                                                "outside the PT range")) + "\n")
        for x in rows:
            if x["scene"] == name and x.get("retimed_ms"):
                q = x.get("flip_vs_pt_retimed") or []
                md += (f"- {name}, {x['setting']}, timed again in turn"
                       + (f" with PT ({len(q)} passes): " if x["family"] != "pt" else ": ")
                       + (f"{x['time_ms']:.0f} -> " if x["family"] != "pt" else "")
                       + ", ".join(f"{t:.0f}" for t in x["retimed_ms"]) + " ms"
                       + (f"; osc-gi / PT = " + ", ".join("-" if y is None else f"{y:.2f}" for y in q)
                          + (f", median {x['flip_vs_pt_retimed_median']:.2f}" if x.get("flip_vs_pt_retimed_median")
                             else "") if x["family"] != "pt" else "") + "\n")
        ratio, lb = r.get("flip_vs_pt_equal_time"), r.get("flip_vs_pt_at_least")
        md += (f"- {name}: FLIP {r['flip']:.4f} at {r['time_ms']:.0f} ms; PT at equal time "
               + (f"{r['pt_flip_equal_time']:.4f} -> osc-gi / PT = {ratio:.2f} (target <= 0.70)" if ratio else
                  (f"better than PT's slowest point -> osc-gi / PT >= {lb:.2f} (target <= 0.70)" if lb else
                   "outside the measured PT range (see the plot)")) + "\n")
        if ri is not None and crc is not None:
            md += (f"- {name}, indirect light: osc-gi FLIP {ri['flip']:.4f} vs crc {crc['flip']:.4f} "
                   f"(target: lower)\n")
        mem = next((x for x in memory if x["scene"] == name and "estimate_1080p_mb" in x), None)
        if mem:
            md += (f"- {name}: memory per viewer at 1080p (linear in pixels from {memory[0]['resolution']}-"
                   f"{[x for x in memory if x['scene'] == name][-1]['resolution']}): {mem['estimate_1080p_mb']:.0f} MB "
                   f"+ the secondary table {mem['secondary_table_mb']:.0f} MB (slides: {SLIDES_1080P_MB[0]}-"
                   f"{SLIDES_1080P_MB[1]} MB on GPU)\n")
        if hists.get(name):
            h = hists[name]
            md += f"- {name}: secondary reuse, mean {h['mean']:.1f} primary rays per cell (max {h['max']})\n"
    experiment.write_results(out, results, md)
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


if __name__ == "__main__":
    from slc.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
