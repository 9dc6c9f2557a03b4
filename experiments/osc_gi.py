"""osc-gi: global illumination with on-surface radiance caches (the slides' tables and figures).

Per scene, one moving viewer, against the reference of each row's output: ``osc-gi`` with the
slides' timing split (*cache*: the on-surface cache's stages; *effect*: the cache updates;
*display*: shading and per-pixel direct light), memory and the secondary cells' reuse; the other
direct-light options (``DIRECT_VARIANTS``); ``pt`` at several sample counts (PT's FLIP at
osc-gi's time: its time fitted as a + b spp, FLIP interpolated log-log in spp); the indirect light
alone (osc-gi, pt, crc); ``ABLATIONS``; ``--retime N``: osc-gi and PT timed again in turn, one
equal-time ratio per pass. Multi-viewer: 1, 4, 16 viewers at about 75% overlap, repetitions in
turn, the ratio to one viewer per repetition. Memory against resolution, extrapolated to 1080p.
``--laps``: the update's sub-stage clock (:class:`slc.methods.oscgi.laps.Laps`). Presets: cornell and
atrium at 160x90, 24 frames (``--quick``: cornell, 64x36, 8 frames).

    python experiments/osc_gi.py --quick
    slc run osc-gi --quick [--scene cornell]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402 (after the path of a standalone run)
from tqdm import tqdm  # noqa: E402

from slc import methods  # noqa: E402
from slc.core import io  # noqa: E402
from slc.core.errors import MethodError  # noqa: E402
from slc.core.spec import parse_spec  # noqa: E402
from slc.run import experiment, plots  # noqa: E402
from slc.run.images import save_strip  # noqa: E402
from slc.run.pipeline import RunConfig, run_sequence  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "osc-gi"

DIRECT_VARIANTS = ["osc-gi:direct=cache", "osc-gi:direct=cones", "osc-gi:direct=restir", "osc-gi:direct=rt,direct_n=4"]
FILTER_ABLATIONS = ["osc-gi:filter_radius=3", "osc-gi:output=indirect,filter_radius=3"]
ABLATIONS = ["osc-gi:freeze=0", "osc-gi:bias=1", "pt:spp=2,freeze=0", "pt:spp=16,freeze=0"] + FILTER_ABLATIONS
# overlap: the rig's target (calibrated on another cache): 0.75 measured 76% with osc-gi's cache at
# 16 viewers on cornell (0.7: 55%, 0.8: 80%), inside the target's 60-80%
FULL = dict(scenes=["cornell", "atrium"], width=160, height=90, frames=24, warmup=8, eval_frames=[23],
            ref_spp=256, pt_spp=[1, 2, 4, 8, 16, 32, 64], ind_pt=5, viewers=[1, 4, 16], overlap=0.75,
            multi_res=(64, 36), multi_frames=20, multi_warmup=5, multi_repeats=3,
            ablations=ABLATIONS + [f"osc-gi:{x}" for x in ("secondary_cm=30", "secondary_cm=60", "bounces=1",
                                                           "bounces=3")],
            memory_res=[(64, 36), (128, 72), (256, 144), (480, 270)])
QUICK = dict(FULL, scenes=["cornell"], width=64, height=36, frames=8, warmup=3, eval_frames=[7], ref_spp=64,
             multi_res=(32, 18), multi_frames=16, multi_warmup=4, memory_res=[(64, 36), (128, 72), (256, 144)],
             ablations=ABLATIONS + ["osc-gi:secondary_cm=60", "osc-gi:bounces=1"])
MULTI_ABLATIONS = ["osc-gi:update_budget=0"]      # the 16-viewer row without the update budget
CACHE_STAGES = ("requests", "allocate", "queue")
RETIMED = ("osc-gi",)               # rows timed again beside PT (--retime)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset: cornell only, 64x36, 8 frames")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/osc-gi)")
    p.add_argument("--res", help="WxH (default 160x90, quick 64x36)")
    p.add_argument("--frames", type=int, help="frames per sequence")
    p.add_argument("--warmup", type=int, help="frames not timed (default: the preset's; with --frames at most "
                   "max(3, frames // 3), so that --frames 10 times 7 frames rather than 2)")
    for flag, text in (("--no-multi", "skip the multi-viewer runs"), ("--no-ablations", "skip the ablations"),
                       ("--only-multi", "run the multi-viewer part only"),
                       ("--no-memory", "skip the memory-against-resolution runs"),
                       ("--laps", "one more osc-gi run with the update's sub-stage clock (host syncs between stages)")):
        p.add_argument(flag, action="store_true", help=text)
    p.add_argument("--retime", type=int, default=3, help="after the rows: time osc-gi and the PT rows again, in "
                   "turn, this many times; the equal-time ratio of each pass from its own times (0: off)")
    p.add_argument("--seed", type=int, default=0)


def _split(stages: dict) -> dict:
    return {"cache_ms": sum(stages.get(k, 0.0) for k in CACHE_STAGES), "effect_ms": stages.get("update", 0.0),
            "display_ms": stages.get("shade", 0.0) + stages.get("direct", 0.0)}


def _loglog(pts, x):
    """Log-log interpolation of (x, y) points (sorted) at x; None outside."""
    for (x0, f0), (x1, f1) in zip(pts, pts[1:]):
        if x0 <= x <= x1 and x1 > x0:
            a = (math.log(x) - math.log(x0)) / (math.log(x1) - math.log(x0))
            return math.exp(math.log(f0) + a * (math.log(f1) - math.log(f0)))
    return None


def _pt_cost(pt_rows):
    """PT's time per frame as a + b spp (a fixed part, one path per pixel and sample), least squares
    on relative errors over all PT rows: one row timed under another load does not decide alone."""
    pts = [(float(r["spp"]), r["time_ms"]) for r in pt_rows if r.get("spp") and r["time_ms"] > 0]
    if len(pts) < 2:
        return None
    n, t = np.array(pts).T
    w = 1.0 / t
    a, b = np.linalg.lstsq(np.stack([w, n * w], 1), t * w, rcond=None)[0]
    return (float(a), float(b)) if b > 0 else None


def _equal_time(pt_rows, t):
    """FLIP of PT at time t: the spp PT affords in t by its fitted cost (:func:`_pt_cost`), FLIP
    interpolated log-log between the PT rows around it (None outside their spp range)."""
    cost = _pt_cost(pt_rows)
    if cost is None:
        return None
    return _loglog(sorted((float(r["spp"]), r["flip"]) for r in pt_rows if r.get("spp") and r["flip"] > 0),
                   (t - cost[0]) / cost[1])


def _against_pt(srows) -> None:
    """Every non-PT row of a scene gets PT's FLIP at its time (full and indirect groups apart)."""
    for grp in ("full", "indirect"):
        pts = [r for r in srows if r["group"] == grp and r["family"] == "pt"]
        cost = _pt_cost(pts)
        slow = max(pts, key=lambda x: x["time_ms"]) if pts else None
        for r in (r for r in srows if r["group"] == grp and r["family"] != "pt"):
            f_pt = _equal_time(pts, r["time_ms"])
            r.update(pt_flip_equal_time=f_pt, flip_vs_pt_equal_time=(r["flip"] / f_pt) if f_pt else None,
                     pt_cost_ms=cost)
            # slower than PT's most expensive point: PT at equal time is at least that good
            if f_pt is None and slow is not None and r["time_ms"] > slow["time_ms"]:
                r["flip_vs_pt_at_least"] = r["flip"] / slow["flip"]


def _retime(s, v, cfg, srows, opts, bar=None) -> None:
    """The rows ``RETIMED`` and the full-light PT rows timed again in turn, ``opts.retime`` passes
    (:func:`slc.run.experiment.runs_in_turn`): osc-gi / PT at equal time from each pass's own times (a
    load that changes during the run weighs on both). Writes ``retimed_ms``, ``flip_vs_pt_retimed``."""
    pts = [r for r in srows if r["group"] == "full" and r["family"] == "pt"]
    rows = [r for r in srows if r["group"] == "full" and r["setting"] in RETIMED]
    if not pts or not rows:
        return
    every = rows + pts

    def before(i):
        if bar is not None:
            bar.set_postfix_str(f"{s.name}/{every[i]['setting']} (retime)")

    runs = experiment.runs_in_turn(s, [(r["setting"], v) for r in every],
                                   dataclasses.replace(cfg, eval_frames=[], keep_images=False), opts.retime,
                                   opts.seed, alternate=False, before=before)
    times = {r["setting"]: [x.time_ms for x in rs] for r, rs in zip(every, runs)}
    for r, rs in zip(every, runs):
        r["retime_compiled_after_warmup"] = sum(x.compiled_after_warmup for x in rs)
        r["retimed_ms"] = times[r["setting"]]
    for r in rows:
        fs = [_equal_time([dict(p, time_ms=times[p["setting"]][i]) for p in pts], times[r["setting"]][i])
              for i in range(opts.retime)]
        ratios = [r["flip"] / f if f else None for f in fs]
        ok = [x for x in ratios if x is not None]
        r["flip_vs_pt_retimed"] = ratios
        r["flip_vs_pt_retimed_median"] = statistics.median(ok) if ok else None


def _row(s, spec, group, cfg, bar, seed):
    """One single-viewer sequence (:func:`slc.run.pipeline.run_sequence`) -> (row, result, method)."""
    m = methods.create(spec, s, seed=seed)
    bar.set_postfix_str(f"{s.name}/{spec}")
    res = run_sequence(s, m, views.single(s), cfg, progress=bar)
    row = {"scene": s.name, **res.row(), "setting": spec, "label": m.label or m.name, "group": group,
           "output": m.output, "bounces": getattr(m, "bounces", None), "family": spec.split(":")[0],
           "resolution": f"{cfg.width}x{cfg.height}", "spp": getattr(m, "spp", None), **_split(res.stages)}
    row.pop("frames_ms", None)
    if spec.startswith("osc-gi"):
        log = m.memory_log[cfg.warmup:] or m.memory_log
        for i, part in enumerate(("primary", "secondary")):
            row.update({f"{part}_mb_{f.__name__}": f(x[i] for x in log) / 2 ** 20 for f in (min, max)})
        row.update(secondary_table_mb=m.secondary.memory_bytes() / 2 ** 20, bytes_per_entry=m.payload_bytes())
    return row, res, m


def _reuse_plot(path, hist, title):
    plt = plots.pyplot()

    fig, ax = plt.subplots(figsize=(5, 3.2))
    b = hist["bins"]
    labels = [str(a) if z == a + 1 else (f"{a}-{z - 1}" if z < 1 << 20 else f">={a}") for a, z in zip(b, b[1:])]
    ax.bar(range(len(labels)), hist["counts"])
    ax.set_xticks(range(len(labels)), labels, fontsize=7)
    ax.set(xlabel="primary-cache rays per secondary cell (one frame)", ylabel="secondary cells", title=title)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _multi_viewer(s, preset, cfg, seed) -> list:
    """1, 4, 16 viewers (and the ablations) in turn, ``multi_repeats`` times in alternating order;
    the ratio to one viewer within each repetition, its median reported with its range."""
    v = views.single(s)
    mw, mh = preset["multi_res"]
    mf, mw_up = preset["multi_frames"], preset["multi_warmup"]
    mcfg = dataclasses.replace(cfg, width=mw, height=mh, frames=mf, warmup=mw_up, eval_frames=[mf - 1],
                               eval_viewers=1, measure_overlap=True)
    # a throwaway run first: its kernels (at this resolution) are then in the kernel cache
    run_sequence(s, methods.create("osc-gi", s, seed=seed), v, dataclasses.replace(mcfg, eval_frames=[]))
    nmax = max(preset["viewers"])
    # (setting, viewers, rig): the largest rig's first view alone too ("view0"): a fan wider than 360
    # degrees is narrowed, so its views request finer entries than the one-viewer row
    m_runs = ([("osc-gi", n, "fan") for n in preset["viewers"]] + [("osc-gi", 1, "view0")]
              + [(a, nmax, "fan") for a in MULTI_ABLATIONS])

    def rig_of(n, rig):
        # pivot "auto": tiles of the camera's own view where it is outside the scene
        if rig == "view0":
            return views.overlap_rig(s, nmax, preset["overlap"], pivot="auto")[:1]
        return views.overlap_rig(s, n, preset["overlap"], pivot="auto") if n > 1 else v

    reps = preset["multi_repeats"]
    runs = dict(zip(m_runs, experiment.runs_in_turn(
        s, [(spec, rig_of(n, rig)) for spec, n, rig in m_runs], dataclasses.replace(mcfg, eval_frames=[]),
        reps, seed, first_cfg=mcfg)))
    one, out = runs[("osc-gi", 1, "fan")], []
    for spec, n, rig in m_runs:
        rs = runs[(spec, n, rig)]
        res, st = rs[0], rs[0].stats
        stages = {k: statistics.median([x.stages.get(k, 0.0) for x in rs]) for k in rs[0].stages}
        kstages = {k: statistics.median([x.stages_kernel.get(k, 0.0) for x in rs]) for k in rs[0].stages_kernel}
        ratios = [x.time_ms / max(o.time_ms, 1e-9) for x, o in zip(rs, one)]
        t = [x.time_ms for x in rs]
        out.append(dict(scene=s.name, viewers=n, setting=spec if rig == "fan" else f"{spec} ({nmax}-fan's view 0)",
                        rig=rig, target_overlap=preset["overlap"], time_ms=statistics.median(t), time_ms_reps=t,
                        time_vs_one=statistics.median(ratios), time_vs_one_reps=ratios,
                        time_vs_one_range=f"{min(ratios):.2f}-{max(ratios):.2f}", frames_timed=mf - mw_up, repeats=reps,
                        measured_overlap=st.get("measured_overlap"), memory_mb=res.memory_mb,
                        memory_per_viewer_mb=res.memory_mb / n, entries=st.get("active_entries"),
                        entries_updated=st.get("entries_updated"), secondary_cells=st.get("secondary_cells"),
                        flip_viewer0=res.metrics.get("flip"), method="osc-gi", resolution=f"{mw}x{mh}",
                        compiled_after_warmup=max(x.compiled_after_warmup for x in rs), **_split(stages),
                        stages_ms=stages, stages_kernel_ms=kstages))
    return out


def _memory_scaling(s, resolutions, seed) -> list:
    """osc-gi's memory at several resolutions (one viewer, 3 frames), primary + secondary in use
    fitted linearly in the pixel count and evaluated at 1920 x 1080 (the slides: 300-700 MB)."""
    out = []
    for w, h in resolutions:
        m = methods.create("osc-gi", s, seed=seed)
        run_sequence(s, m, views.single(s), RunConfig(width=w, height=h, frames=3, warmup=1, eval_frames=[],
                                                      seed=seed, measure_overlap=False))
        prim, sec = m.memory_log[-1]
        out.append({"scene": s.name, "resolution": f"{w}x{h}", "pixels": w * h,
                    "entries": int(m.cache.entries_allocated()), "primary_mb": prim / 2 ** 20,
                    "secondary_mb": sec / 2 ** 20, "secondary_table_mb": m.secondary.memory_bytes() / 2 ** 20})
    if len(out) >= 2:
        slope, icpt = np.polyfit([r["pixels"] for r in out], [r["primary_mb"] + r["secondary_mb"] for r in out], 1)
        for r in out:
            r["estimate_1080p_mb"] = float(slope * 1920 * 1080 + icpt)
    return out


def _scene(s, preset, cfg, specs, opts, out, bar, res) -> None:
    """Every part of the experiment on one scene; rows appended to ``res`` (a dict of lists)."""
    W, H = cfg.width, cfg.height
    srows = []
    for group, group_specs in specs.items():
        for spec in group_specs:
            row, r, m = _row(s, spec, group, cfg, bar, opts.seed)
            srows.append(row)
            if spec in ("osc-gi", "osc-gi:output=indirect", "pt:spp=1"):
                save_strip(out, s, row["label"], r)
            if spec == "osc-gi":
                res["hists"][s.name] = row["reuse_histogram"] = m.secondary.reuse_histogram()
                _reuse_plot(out / f"reuse_{s.name}.png", row["reuse_histogram"],
                            f"{s.name}: secondary-cache reuse ({W}x{H}, 1 viewer)")
    if opts.laps and not opts.only_multi:
        # the update's sub-stages (a separate run: the clock's syncs split kernels)
        m = methods.create("osc-gi", s, seed=opts.seed)
        m._profile, m._profile_skip = True, cfg.warmup
        m.reset()
        run_sequence(s, m, views.single(s), cfg)
        res["laps"][s.name] = {k: round(x, 2) for k, x in m.laps.per_frame().items()}
    _against_pt(srows)
    if opts.retime > 0 and srows:
        _retime(s, views.single(s), cfg, srows, opts, bar)
    for grp, what in (("full", "full light"), ("indirect", "indirect light")) if srows else ():
        plots.speed_error_plot(out / f"speed_error{'' if grp == 'full' else '_indirect'}_{s.name}.png", [
            r for r in srows if r["group"] == grp], f"{s.name}: {what}, time vs FLIP ({W}x{H})")
    res["rows"] += srows
    if not opts.no_multi:
        multi = _multi_viewer(s, preset, cfg, opts.seed)
        res["multi"] += multi
        mw, mh = preset["multi_res"]
        plots.time_vs_viewers_plot(out / f"time_vs_viewers_{s.name}.png",
                                        [r for r in multi if r["setting"] == "osc-gi" and r["rig"] == "fan"],
                                        f"{s.name}: osc-gi, {mw}x{mh} per viewer, overlap {preset['overlap']:.0%}")
    if not opts.no_memory and not opts.only_multi:
        res["memory"] += _memory_scaling(s, preset["memory_res"], opts.seed)


def run(opts) -> dict:
    preset = experiment.apply_common(opts, QUICK if opts.quick else FULL)
    if getattr(opts, "warmup", None) is not None:
        if not 0 <= opts.warmup < preset["frames"]:
            raise experiment.ExperimentError("--warmup must be at least 0 and below the frame count")
        preset["warmup"] = opts.warmup
    elif getattr(opts, "frames", None):
        # a short sequence keeps 3 warm-up frames (the kernels are built in frames 0-2) and times the rest
        preset["warmup"] = min(preset["warmup"], max(3, preset["frames"] // 3))
    for k in ("no_multi", "no_memory", "only_multi", "no_ablations", "laps"):      # (also for callers' namespaces)
        setattr(opts, k, bool(getattr(opts, k, False)))
    out = Path(opts.out) / NAME
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    cfg = RunConfig(width=preset["width"], height=preset["height"], frames=preset["frames"], warmup=preset["warmup"],
                    eval_frames=preset["eval_frames"], seed=opts.seed, ref_spp=preset["ref_spp"], measure_overlap=False)
    specs = {"full": ["osc-gi"] + DIRECT_VARIANTS + ["sharc"] + [f"pt:spp={n}" for n in preset["pt_spp"]],
             "indirect": (["osc-gi:output=indirect"]
                          + [f"pt:spp={n},output=indirect" for n in preset["pt_spp"][:preset["ind_pt"]]] + ["crc", "sharc:output=indirect"]),
             "ablation": [] if opts.no_ablations else list(preset["ablations"])}
    specs = {} if opts.only_multi else specs
    for spec in [x for group in specs.values() for x in group]:      # bad specs stop the run before any work
        parse_spec(spec, "method setting", MethodError)
    res = {"rows": [], "multi": [], "hists": {}, "laps": {}, "memory": []}
    n_runs = len(names) * sum(len(x) for x in specs.values())
    with tqdm(total=n_runs * preset["frames"], desc=NAME, unit="frame", disable=None) as bar:
        for s in experiment.each_scene(names):
            _scene(s, preset, cfg, specs, opts, out, bar, res)
    config = {"quick": bool(opts.quick), "scenes": names, **{k: v for k, v in preset.items() if k != "scenes"},
              "seed": opts.seed, "timing": "medians after warm-up on a shared 2-core CPU: ratios only",
              "reference": "full: ref_spp-sample direct ground truth + ref_spp-path indirect reference"}
    all_rows = res["rows"] + [dict(r, group="multi") for r in res["multi"]]
    results = experiment.results_object(NAME, config, experiment.strip_private(all_rows))
    results.update({k: res[r] for k, r in (("update_laps_ms", "laps"), ("memory_scaling", "memory")) if res[r]})
    report = experiment.load_part("osc_gi_report")
    experiment.write_results(out, results, md := report.markdown(sys.modules[__name__], res, names, cfg))
    print(md)
    print(f"results: {out / 'results.json'}")
    return results


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
