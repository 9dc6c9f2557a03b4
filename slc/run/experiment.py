"""Shared plumbing of the experiment scripts in ``experiments/``.

An experiment script defines ``NAME``, ``add_arguments(parser)`` (optional)
and ``run(opts) -> dict`` returning the ``results.json`` object; it is run
alone (``python experiments/single_viewer.py --quick``) or through
``slc run single-viewer --quick``. This module finds the scripts, writes
``results.json`` / ``results.md`` atomically (a failed run leaves no partial
results), renders the Markdown table, and holds the options, presets, scene
loops, job runs and viewer-count experiments the scripts share. A row whose
timed frames built kernels (``compiled_after_warmup`` > 0) or recorded a frozen
function again (``recordings_after_warmup`` > 0) is flagged: a warning on
stderr, a mark in its time cell and a note in ``results.md``.
An experiment's images are written by :mod:`slc.run.images`, the
scene-variant sweeps run by :mod:`slc.run.sweeps`.
"""
from __future__ import annotations

import dataclasses
import gc
import importlib.util
import math
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

from slc import methods
from slc.core import io
from slc.core.backend import env_info
from slc.core.errors import MethodError
from slc.core.spec import parse_spec
from slc.run import jobs, jobspec
from slc.run.errors import ExperimentError
from slc.run.pipeline import RunConfig, run_sequence
from slc.run.plots import time_vs_viewers_plot
from slc.scene import checks, scenes
from slc.scene.scenes import REPO_ROOT

EXPERIMENTS_DIR = REPO_ROOT / "experiments"


def names() -> list[str]:
    if not EXPERIMENTS_DIR.is_dir():
        return []
    return sorted(p.stem.replace("_", "-") for p in EXPERIMENTS_DIR.glob("*.py") if not p.stem.startswith("_"))


def load(name: str):
    path = EXPERIMENTS_DIR / f"{name.replace('-', '_')}.py"
    if not path.exists():
        raise ExperimentError(f"unknown experiment '{name}' (available: {', '.join(names())})")
    return _load_file(path)


def load_part(name: str):
    """A part of the experiments that is no experiment itself (``experiments/_NAME.py``,
    e.g. an experiment's report), loaded once."""
    return sys.modules.get(f"slc_experiment__{name}") or _load_file(EXPERIMENTS_DIR / f"_{name}.py")


def _load_file(path: Path):
    """The module at ``path``, registered in ``sys.modules`` as ``slc_experiment_STEM`` (so
    that its parts can name it, e.g. ``sys.modules[__name__]``)."""
    spec = importlib.util.spec_from_file_location(f"slc_experiment_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def results_object(name: str, config: dict, rows: list[dict]) -> dict:
    return {"experiment": name, "config": config, "env": env_info(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "rows": rows}


def _fmt(v, nd=3):
    if isinstance(v, float):
        if math.isinf(v):
            return "inf"
        if math.isnan(v):
            return "-"
        return f"{v:.{nd}f}" if abs(v) < 1e4 else f"{v:.3g}"
    return str(v)


DEFAULT_COLUMNS = [("scene", "scene"), ("method", "method"), ("viewers", "viewers"),
                   ("time_ms", "t [ms]"), ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"),
                   ("memory_mb", "memory [MB]")]


COMPILED_MARK = "⚠"   # marks a time cell whose timed frames built kernels (or recorded frozen functions)


def _cell(r: dict, k: str, nd: int) -> str:
    text = _fmt(r.get(k, "-"), nd)
    if k == "time_ms" and (r.get("compiled_after_warmup") or r.get("recordings_after_warmup")):
        text += f" {COMPILED_MARK}{int(r.get('compiled_after_warmup') or 0)}"
        if r.get("recordings_after_warmup"):
            text += f"/{int(r['recordings_after_warmup'])}r"
    return text


def markdown_table(rows: list[dict], columns=None) -> str:
    """A Markdown table of ``rows``; a time whose timed frames built kernels is
    followed by the mark and the number of kernels (``12.34 ⚠2``), and of recordings
    when frozen functions recorded again (``12.34 ⚠2/1r``)."""
    columns = columns or DEFAULT_COLUMNS
    cols = [(k, h) for k, h in columns if any(k in r for r in rows)]
    nd = {"time_ms": 2, "flip": 4, "psnr": 2, "ssim": 4, "memory_mb": 3}
    out = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        out.append("| " + " | ".join(_cell(r, k, nd.get(k, 3)) for k, _ in cols) + " |")
    return "\n".join(out)


def compiled_rows(rows: list[dict]) -> list[str]:
    """One line per row whose timed frames built (compiled or loaded from
    the disk cache) Dr.Jit kernels or recorded frozen functions again: its time
    is not steady state."""
    out = []
    for r in rows:
        n, rec = r.get("compiled_after_warmup"), r.get("recordings_after_warmup")
        if n or rec:
            where = ", ".join(f"{k}={r[k]}" for k in ("scene", "label", "rig", "viewers", "overlap") if k in r)
            what = [f"{int(n)} kernel(s) built"] if n else []
            what += [f"{int(rec)} frozen-function recording(s)"] if rec else []
            out.append(f"{where}: {' and '.join(what)} after warm-up")
    return out


def flag_compiled(results: dict, markdown: str) -> str:
    """Warn on stderr about every row with ``compiled_after_warmup`` > 0 and
    return ``markdown`` with a note listing them (unchanged when none)."""
    lines = compiled_rows(results.get("rows", []))
    if not lines:
        return markdown
    for line in lines:
        print(f"warning: {results.get('experiment', '?')}: {line}; its time depends on the kernel cache",
              file=sys.stderr)
    note = ("\n\n## Warning: kernels built in timed frames\n\n"
            f"Times marked {COMPILED_MARK}N include N Dr.Jit kernels compiled or loaded from the disk cache "
            "after the warm-up frames (`compiled_after_warmup`; N/Mr: and M frozen functions recorded again, "
            "`recordings_after_warmup`), so they depend on the state of the kernel "
            "cache and are not steady-state figures:\n\n" + "\n".join(f"- {x}" for x in lines) + "\n")
    return markdown.rstrip("\n") + note


def write_results(out_dir: Path, results: dict, markdown: str) -> None:
    """``results.json`` and ``results.md``, each written atomically; rows that
    built kernels after warm-up are flagged (:func:`flag_compiled`)."""
    markdown = flag_compiled(results, markdown)
    out_dir.mkdir(parents=True, exist_ok=True)
    io.write_json(out_dir / "results.json", results)
    io.write_text(out_dir / "results.md", markdown)


# -----------------------------------------------------------------------------
# Pieces shared by the experiment scripts
# -----------------------------------------------------------------------------

def add_common_arguments(p, default_out: str = "out") -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--methods", nargs="+", help="methods to compare (default: the experiment's)")
    p.add_argument("--out", default=default_out, help="output folder (results go to OUT/EXPERIMENT)")
    p.add_argument("--res", help="image size WxH in pixels (default: the experiment's preset)")
    p.add_argument("--frames", type=int, help="frames per sequence, at least 1 (default: the experiment's preset)")
    p.add_argument("--seed", type=int, default=0, help="seed of every method's random numbers (default 0)")
    g = p.add_argument_group("jobs (docs/cluster.md)")
    g.add_argument("--workers", type=int, help="run the jobs on N Ray workers (a local Ray instance unless --address)")
    g.add_argument("--address", help="run the jobs on a running Ray cluster: 'auto' or HOST:PORT")
    g.add_argument("--threads", type=int, help="Dr.Jit threads per worker (default: cores // workers locally, "
                                                "the smallest node's CPUs on a cluster; serial: all cores)")
    g.add_argument("--resume", action="store_true",
                   help="keep the jobs already committed in OUT/EXPERIMENT/rows/ and run only the missing ones")
    g.add_argument("--retries", type=int, default=2, help="attempts after a failed job before it is reported")


def apply_common(opts, preset: dict) -> dict:
    """Override a preset by --res/--frames; returns a new dict."""
    preset = dict(preset)
    if getattr(opts, "res", None):
        w, _, h = opts.res.lower().partition("x")
        try:
            preset["width"], preset["height"] = int(w), int(h)
        except ValueError:
            raise ExperimentError(f"bad resolution '{opts.res}' (expected WxH, e.g. 320x180)") from None
        if preset["width"] < 1 or preset["height"] < 1:
            raise ExperimentError(f"bad resolution '{opts.res}' (width and height at least 1)")
    viewers = getattr(opts, "viewers", None)
    if viewers is not None and min(viewers if isinstance(viewers, list) else [viewers]) < 1:
        raise ExperimentError("--viewers must be at least 1")
    if getattr(opts, "frames", None) is not None:
        f = opts.frames
        if f < 1:
            raise ExperimentError("--frames must be at least 1")
        preset["frames"] = f
        preset["eval_frames"] = [x for x in preset.get("eval_frames", []) if x < f] or [f - 1]
        preset["warmup"] = min(preset.get("warmup", 0), max(f - 1, 0))
    return preset


def available_methods(wanted: list[str]) -> list[str]:
    """``wanted`` without the methods that are not implemented (yet)."""
    return [spec for spec in wanted if methods.known(parse_spec(spec, "method setting", MethodError)[0])]


def load_and_validate(scene_names: list[str], method_specs: list[str], explicit_scenes: bool) -> list[str]:
    """Load every scene and instantiate every method once before any work,
    so bad input stops the run before anything is written; returns the names
    to run. Sponza is skipped with a note when it was only in the default
    list and is absent. The scenes are released again: see :func:`each_scene`."""
    names = []
    for name in scene_names:
        try:
            s = scenes.load(name)
        except checks.SceneError as e:
            if name == "sponza" and not explicit_scenes:
                print(f"note: skipping sponza ({e})", file=sys.stderr)
                continue
            raise
        for spec in method_specs:
            if methods.create(spec, s).output != "direct":
                raise ExperimentError(f"method '{spec}' renders indirect light; this experiment compares direct "
                                      f"light (use 'slc run megaviews')")
        names.append(name)
        del s
    release_scenes()
    return names


def release_scenes() -> None:
    """Free the scenes no longer referenced (see :func:`each_scene`)."""
    gc.collect()
    gc.collect()


def each_scene(names: list[str]):
    """Yield the scenes one at a time, releasing each before loading the next.

    Timing depends on it: every live Mitsuba object joins Dr.Jit's virtual
    call tables, so with all five Table-1 scenes alive at once every BSDF,
    emitter and shape call is traced and dispatched over all of them; the
    atrium's ``slc`` frame measured 110 ms instead of 49 ms, ``restir`` 142
    instead of 44 (``rt48`` was barely affected)."""
    for name in names:
        s = scenes.load(name)
        s.source = name  # what loads it again (jobs run elsewhere)
        yield s
        del s
        release_scenes()


def strip_private(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]


def ratio(a, b):
    """a / b, None when b is 0 or missing."""
    try:
        return a / b if b else None
    except TypeError:
        return None


def runs_in_turn(scene, cases, cfg, repeats: int = 3, seed: int = 0, alternate: bool = True,
                 first_cfg=None, before=None) -> list[list]:
    """Run ``cases`` ((method, viewers) pairs; the method a spec, or a function that makes a new
    one, its settings as data) again, in turn: ``repeats``
    repetitions of every case, each a whole :func:`slc.run.pipeline.run_sequence` of
    ``cfg`` with a new method instance; with ``alternate`` every other repetition
    runs the cases in reverse order (a load that drifts during the repetitions
    then weighs on both ends alike). ``first_cfg`` (default ``cfg``): the first
    repetition's config (e.g. with frames evaluated); ``before(i)`` is called
    before each run of case i (a progress bar). Returns per case its results, one
    per repetition. Rows of an experiment run minutes apart, under whatever load
    the shared cores had then; ratios of runs side by side move less."""
    out = [[] for _ in cases]
    order = list(range(len(cases)))
    for rep in range(repeats):
        for i in (order if rep % 2 == 0 or not alternate else order[::-1]):
            if before is not None:
                before(i)
            spec, viewers = cases[i]
            c = first_cfg if rep == 0 and first_cfg is not None else cfg
            m = spec() if callable(spec) else methods.create(spec, scene, seed=seed)
            out[i].append(run_sequence(scene, m, viewers, c))
    return out


def ratio_in_turn(scene, spec: str, base, top, cfg, repeats: int = 3, seed: int = 0) -> dict:
    """Time one method on two rigs again, in turn (:func:`runs_in_turn`: base, top; top,
    base; ...; no evaluation), the ratio top / base taken within each repetition. Returns
    the median ratio, every repetition's ratio and times, and the most kernels any run
    built after its warm-up."""
    c = dataclasses.replace(cfg, eval_frames=[], keep_images=False, measure_overlap=False)
    b, t = runs_in_turn(scene, [(spec, base), (spec, top)], c, repeats, seed)
    ratios = [x.time_ms / max(y.time_ms, 1e-9) for x, y in zip(t, b)]
    return {"ratio": statistics.median(ratios) if ratios else float("nan"), "ratios": ratios,
            "base_ms": [x.time_ms for x in b], "top_ms": [x.time_ms for x in t],
            "compiled_after_warmup": max((x.compiled_after_warmup for x in b + t), default=0),
            "recordings_after_warmup": max((x.recordings_after_warmup for x in b + t), default=0)}


def setup(opts, quick: dict, full: dict, methods: list[str]):
    """The common start of a multi-viewer experiment: the preset (with
    --res/--frames applied), the method specs, the validated scenes and the
    RunConfig. Returns (preset, specs, scene names, cfg)."""
    pr = apply_common(opts, quick if opts.quick else full)
    specs = opts.methods or available_methods(methods)
    names = load_and_validate(opts.scene or pr["scenes"], specs, bool(opts.scene))
    cfg = RunConfig(width=pr["width"], height=pr["height"], frames=pr["frames"], warmup=pr["warmup"],
                    eval_frames=pr["eval_frames"], eval_viewers=pr.get("eval_viewers"), seed=opts.seed)
    return pr, specs, names, cfg


def add_viewer_arguments(p) -> None:
    """Common options plus --viewers (viewer counts)."""
    add_common_arguments(p)
    p.add_argument("--viewers", type=int, nargs="+", help="viewer counts, each at least 1 (default: the experiment's preset)")


def viewer_count_experiment(opts, name: str, quick: dict, full: dict, methods: list[str], rig: str,
                            make_viewers, plot_title):
    """Every method on ``make_viewers(scene, n)`` for each viewer count, one
    time-against-viewers plot per scene. Returns (rows, scene names, cfg,
    out folder, viewer counts)."""
    pr, specs, names, cfg = setup(opts, quick, full, methods)
    counts = opts.viewers or pr["viewers"]
    rows = run_per_scene(names, lambda s: [(spec, make_viewers(s, n), {"rig": rig})
                                           for spec in specs for n in counts], cfg, name, opts.seed)
    out = Path(opts.out) / name
    for scene in names:
        time_vs_viewers_plot(out / f"time_vs_viewers_{scene}.png", [r for r in rows if r["scene"] == scene],
                             plot_title(scene, cfg))
    return rows, names, specs, cfg, out, counts


def at_viewers(rows: list[dict], scene: str, n: int) -> dict:
    """Rows of one scene at ``n`` viewers, keyed by setting."""
    return {r["setting"]: r for r in rows if r["scene"] == scene and r["viewers"] == n}


def run_per_scene(names, make_cases, cfg, desc: str, seed: int = 0, keep_images: bool = False,
                  on_result=None) -> list[dict]:
    """For each scene (one alive at a time), ``make_cases(scene)`` gives
    (spec, viewers, extra-fields) tuples; returns all rows, in that order.

    The cases of every scene become jobs first (:func:`slc.run.jobspec.jobs_from_cases`:
    the viewers are frozen into cameras, so no live scene is kept), then all
    jobs run under one progress bar, serially or on Ray (``--workers``,
    ``--address``), resumable (``--resume``). ``keep_images``/``on_result``:
    see :meth:`slc.run.jobs.Session.run`."""
    session = jobs.current(desc.split()[0])
    js, n, live = [], 0, {}
    for i, s in enumerate(each_scene(names)):
        cases = [(s, *c) for c in make_cases(s)]
        js += jobspec.jobs_from_cases(session.experiment, cases, cfg, seed, keep_images, start=n)
        n += len(cases)
        del cases
        if i == len(names) - 1 and not session.distributed:
            live = {jobspec.scene_source(s): s}  # a serial run starts with the scene still loaded
        del s
    js.sort(key=lambda j: j.scene not in live)  # stable: that scene's jobs first
    rows = session.run(js, desc, scenes=live, on_result=on_result)
    live.clear()
    return _in_case_order(js, rows)


def run_cases(cases, cfg, desc: str, seed: int = 0, keep: bool = False) -> list[dict]:
    """Run (scene, spec, viewers, extra-fields) cases as jobs (one per scene
    and viewers, every method of a comparison in the same job) with one
    progress bar; rows in the order of ``cases``. ``keep`` gives each row a
    ``_result`` whose ``images`` are the evaluated images (for
    :func:`slc.run.images.save_strip`)."""
    session = jobs.current(desc.split()[0])
    js = jobspec.jobs_from_cases(session.experiment, cases, cfg, seed, keep_images=keep)
    live = {jobspec.scene_source(s): s for s, *_ in cases}
    rows = _in_case_order(js, session.run(js, desc, scenes=live))
    if keep:  # from this run, or committed with the job by the run that --resume continues
        images = {c.index: im for j in js for c, im in zip(j.cases, jobs.images_of(session, j))}
        for r, i in zip(rows, sorted(images)):
            r["_result"] = SimpleNamespace(images=images[i])
    return rows


def _in_case_order(js, rows: list[dict]) -> list[dict]:
    """Rows of ``js`` (job order, each job's cases in order) back in the order
    the cases were given."""
    index = [c.index for j in js for c in j.cases]
    return [r for _, r in sorted(zip(index, rows), key=lambda t: t[0])]


def finish(name: str, out: Path, opts, cfg, names, specs, rows, md_body: str, extra_config=None) -> dict:
    """Write results.json / results.md for a multi-viewer experiment and print the table."""
    config = {"quick": bool(opts.quick), "methods": specs, "scenes": sorted({r["scene"] for r in rows}),
              "width": cfg.width, "height": cfg.height, "frames": cfg.frames, "warmup": cfg.warmup,
              "eval_frames": cfg.evaluated(), "eval_viewers": cfg.eval_viewers, "seed": cfg.seed,
              **(extra_config or {})}
    header = (f"# {name}\n\n{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up); time = median DI ms "
              f"per frame for all viewers together; quality of the first {cfg.eval_viewers} viewer(s) on frames "
              f"{cfg.evaluated()} against 2048-sample ground truth; measured overlap = % of visible surface cells "
              f"seen by more than one viewer.\n\n")
    md = header + md_body
    results = results_object(name, config, strip_private(rows))
    write_results(out, results, md)
    print(md)
    return results


MULTI_COLUMNS = [("scene", "scene"), ("method", "method"), ("rig", "rig"), ("viewers", "viewers"),
                 ("measured_overlap", "measured overlap %"), ("time_ms", "t [ms]"), ("flip", "FLIP"),
                 ("psnr", "PSNR"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]


# -----------------------------------------------------------------------------
# Start-up against steady state
# -----------------------------------------------------------------------------

SETTLE_FRAMES = 8    # default update policy: an entry gets 8 rays for its first 8 updates, then 1
STEADY_WARMUP = 10   # warm-up of every preset: kernel builds, then the first frame's entries settle


def add_startup(rows: list[dict], settle: int = SETTLE_FRAMES) -> list[dict]:
    """Add ``startup_ms`` to every row: the median DI time of frames 1 ..
    ``settle - 1``, while the entries requested in frame 0 are still in
    their 8-ray start-up (frame 0 and frames that built kernels, when the
    row's ``frames_ms`` counts them, are left out). ``time_ms`` stays the
    median after the warm-up, i.e. the steady state when the warm-up is at
    least ``settle`` frames. Per-viewer methods have no start-up; their
    figure shows the same frames for comparison."""
    for r in rows:
        fr = r.get("frames_ms") or []
        ts = [f.get("total", 0.0) for i, f in enumerate(fr[:settle]) if i >= 1 and not f.get("compiled")]
        r["startup_ms"] = statistics.median(ts) if ts else None
    return rows
