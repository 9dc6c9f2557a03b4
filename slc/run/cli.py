"""The ``slc`` command line.

    slc scenes                      list scenes
    slc methods                     list methods
    slc render --scene S --method M --viewers N --res WxH --frames F --out DIR
    slc run EXPERIMENT [--quick] [--out DIR] [--scene NAME]... [experiment options]
    slc bench rays                  RT-N shadow-ray throughput vs raw ray_test
    slc bench update                slc's frame vs the rays of its own update, alone
    slc bench ab A B [--scene S]... two method settings timed in turn: time, ratio, FLIP, md5

Every command takes ``--variant`` (or ``SLC_VARIANT``) and ``--check`` (or
``SLC_CHECK=1``: stop at the first NaN/Inf or negative value, see
:mod:`slc.core.check`; ``slc run EXP --check`` and ``python experiments/EXP.py
--check`` work as well). Bad input (missing
file, unknown scene/method/experiment, a scene without emitters) prints one
line ``slc: error: ...`` and exits with status 2, writing no results.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import click

from slc.core import backend
from slc.distributed import DEFAULT_LEASE, DEFAULT_THRESHOLD


def _errors():
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.experiment import ExperimentError
    from slc.methods import MethodError
    from slc.scene.checks import SceneError
    from slc.core.check import CheckError
    return (SceneError, MethodError, ExperimentError, backend.BackendError, FileNotFoundError, CheckError)


def _jobs_failed():
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.jobs import JobsFailed
    return JobsFailed


def _fail(msg: str):
    click.echo(f"slc: error: {msg}", err=True)
    sys.exit(2)


def _parse_res(res: str) -> tuple[int, int]:
    try:
        w, h = res.lower().split("x")
        w, h = int(w), int(h)
        assert w > 0 and h > 0
        return w, h
    except Exception:
        _fail(f"bad resolution '{res}' (expected WxH, e.g. 320x180)")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--variant", default=None, help="Mitsuba variant (cuda_ad_rgb or llvm_ad_rgb); default: auto")
@click.option("--check", "check_mode", is_flag=True, default=False,
              help="check mode (= SLC_CHECK=1): stop at the first NaN/Inf or negative value")
def cli(variant, check_mode):
    """slc: shared caches of incoming light for many viewers."""
    if check_mode:
        # after --variant (the module builds Mitsuba types on import)
        from slc.core import check
        check.enable()
    try:
        backend.init(variant)
    except backend.BackendError as e:
        _fail(str(e))


@cli.command("scenes")
def scenes_cmd():
    """List the built-in scenes."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.scene import scenes
    for name, desc in scenes.describe_builtins():
        click.echo(f"{name:10s} {desc}")
    click.echo("(or any Mitsuba 3 scene: --scene path/to/scene.xml)")


@cli.command("methods")
def methods_cmd():
    """List the available methods."""
    # after --variant (the module builds Mitsuba types on import)
    from slc import methods
    for name, desc in sorted(methods.available().items()):
        click.echo(f"{name:10s} {desc}")


@cli.command("render")
@click.option("--scene", "scene_name", default="cornell", show_default=True)
@click.option("--method", default="rt16", show_default=True)
@click.option("--viewers", default=1, show_default=True, type=int)
@click.option("--rig", default="single", show_default=True, help="single, random, overlap, stereo, meeting")
@click.option("--overlap", default=1.0, show_default=True, type=float, help="overlap rig: target fraction 0..1")
@click.option("--res", default="320x180", show_default=True)
@click.option("--frames", default=8, show_default=True, type=int)
@click.option("--warmup", default=2, show_default=True, type=int)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--gt/--no-gt", default=False, show_default=True,
              help="compare the last frame with the reference of the method's output kind "
                   "(direct: ground truth; indirect: indirect reference; full: both)")
@click.option("--out", default="out/render", show_default=True)
@click.option("--nodes", default=0, show_default=True, type=int,
              help="render nodes (Ray actors) sharing one cache by owner-based sparse updates; viewers go "
                   "to nodes round-robin (0: one process, no Ray; a cache method with records: slc, sh, adaptive)")
@click.option("--threshold", default=None, type=float,
              help="with --nodes: an owner sends an entry's record again when it changed by more than this "
                   f"since the record the node holds (the payload's own measure, unitless; default {DEFAULT_THRESHOLD:g}, "
                   "docs/distributed.md)")
@click.option("--address", default=None, help="with --nodes: a running Ray cluster (HOST:PORT); default a local instance")
def render_cmd(scene_name, method, viewers, rig, overlap, res, frames, warmup, seed, gt, out, nodes, threshold,
               address):
    """Render a sequence with one method; write images and timings."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.core import io
    from slc import methods
    from slc.scene import scenes, views
    from slc.run.pipeline import RunConfig, run_sequence
    w, h = _parse_res(res)
    if viewers < 1 or frames < 1:
        _fail("--viewers and --frames must be at least 1")
    s = scenes.load(scene_name)
    m = methods.create(method, s, seed=seed)
    try:
        vs = views.make_rig(s, rig, viewers, overlap)
    except ValueError as e:
        _fail(str(e))
    if nodes:
        _render_on_nodes(scene_name, method, s, m, vs, nodes, threshold, address, (w, h), frames, seed, gt, out)
        return
    cfg = RunConfig(width=w, height=h, frames=frames, warmup=min(warmup, frames - 1), seed=seed,
                    eval_frames=[frames - 1] if gt else [])
    from tqdm import tqdm
    with tqdm(total=frames, desc=f"{s.name}/{m.name}", unit="frame", disable=None) as bar:
        r = run_sequence(s, m, vs, cfg, progress=bar)
    outd = Path(out)
    for vname, img in r.last.items():
        io.write_hdr_and_png(outd / f"{s.name}_{m.name}_{vname}", img, s.exposure)
    for vname, im in r.images.items():
        io.comparison_strip(outd / f"{s.name}_{m.name}_{vname}_strip.png", im["gt"], im["img"],
                            im["flip_map"], im["exposure"])
    row = {"scene": s.name, **r.row(), "per_frame_ms": r.per_frame_ms}
    io.write_json(outd / "timings.json", row)
    click.echo(f"{s.name} {m.name} ({m.output} light) viewers={len(vs)}: {r.time_ms:.2f} ms/frame (median after "
               f"{cfg.warmup} warm-up)" + "".join(f", {k} {v:.4f}" for k, v in r.metrics.items())
               + (f" vs the {m.output} reference" if r.metrics else ""))
    click.echo(f"wrote {outd}")


def _render_on_nodes(scene_name, spec, s, m, vs, nodes, threshold, address, size, frames, seed, gt, out):
    """``slc render --nodes K``: the viewers ``vs`` on K Ray render nodes, one process each
    (:func:`slc.distributed.actors.render_on_nodes`); ``s``, ``m``: the scene and method loaded
    here to check the input before Ray starts."""
    # after --variant (the modules build Mitsuba types on import)
    from slc.core import io
    from slc.methods.cache_method import PayloadMethod
    if nodes < 1 or nodes > len(vs):
        _fail(f"--nodes must be between 1 and the number of viewers ({len(vs)}), got {nodes}")
    if not isinstance(m, PayloadMethod):
        _fail(f"--nodes needs a cache method whose entries are records (slc, sh, adaptive); '{m.name}' has none")
    if gt:
        _fail("--gt is not available with --nodes (slc run distributed compares the nodes' images)")
    # Ray and the actors only when nodes are asked for
    from slc.distributed.actors import render_on_nodes
    t = DEFAULT_THRESHOLD if threshold is None else threshold
    if t < 0:
        _fail(f"--threshold must be >= 0, got {t}")
    res = render_on_nodes(s, scene_name, spec, vs, nodes, *size, frames, t, DEFAULT_LEASE, seed=seed,
                          address=address, output=m.output)
    outd = Path(out)
    for v, img in sorted(res["images"].items()):
        io.write_hdr_and_png(outd / f"{s.name}_{m.name}_node{v % nodes}_{vs[v].name}", img, s.exposure)
    sent = res["bytes_per_frame"]
    io.write_json(outd / "nodes.json", {"scene": s.name, "method": spec, "nodes": nodes, "threshold": t,
                                        "processes": res["processes"], "bytes_per_frame": sent,
                                        "serialized_bytes_per_frame": res["serialized_bytes_per_frame"]})
    click.echo(f"{s.name} {m.name} on {nodes} nodes, viewers={len(vs)}: {sum(sent) / max(len(sent), 1):.0f} bytes "
               f"per frame sent (mean over {len(sent)} frames), threshold {t:g}")
    click.echo(f"wrote {outd}")


@cli.command("run", add_help_option=False,
             context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.argument("experiment_name")
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def run_cmd(experiment_name, args):
    """Run an experiment (single-viewer, ...); options after the name."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.run import experiment
    mod = experiment.load(experiment_name)
    _run_module(mod, list(args), prog=f"slc run {experiment_name}")


def _run_module(mod, argv, prog):
    p = argparse.ArgumentParser(prog=prog, description=(mod.__doc__ or "").strip().splitlines()[0])
    if hasattr(mod, "add_arguments"):
        mod.add_arguments(p)
    p.add_argument("--check", action="store_true",
                   help="check mode (= SLC_CHECK=1): stop at the first NaN/Inf or negative value")
    opts = p.parse_args(argv)
    if opts.check:
        # after --variant (the module builds Mitsuba types on import)
        from slc.core import check
        check.enable()
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.jobs import session_for
    with session_for(getattr(mod, "NAME", prog.split()[-1]), opts):
        mod.run(opts)


@cli.group("bench")
def bench_grp():
    """Micro-benchmarks."""


@bench_grp.command("rays")
@click.option("--scene", "scene_name", default="atrium", show_default=True)
@click.option("--res", default="320x180", show_default=True)
@click.option("--n", default=16, show_default=True, type=int, help="samples (rays) per pixel")
@click.option("--repeats", default=5, show_default=True, type=int)
def bench_rays(scene_name, res, n, repeats):
    """RT-N throughput next to Mitsuba's raw scene.ray_test on the same rays, with Mitsuba's light sampler and the emitter table."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.bench import bench_rays as run, report_lines
    w, h = _parse_res(res)
    for line in report_lines(run(scene_name, w, h, n, repeats)):
        click.echo(line)


@bench_grp.command("update")
@click.option("--scene", "scene_name", default="atrium", show_default=True)
@click.option("--res", default="320x180", show_default=True)
@click.option("--frames", default=24, show_default=True, type=int)
@click.option("--warmup", default=10, show_default=True, type=int)
@click.option("--repeats", default=5, show_default=True, type=int)
@click.option("--method", default="slc", show_default=True, help="slc, with settings (slc:max_cones=2)")
def bench_update(scene_name, res, frames, warmup, repeats, method):
    """slc's frame time next to the rays its update traces, traced alone."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.bench import bench_update as run, update_report_lines
    w, h = _parse_res(res)
    if frames <= warmup:
        raise click.BadParameter(f"--frames ({frames}) must exceed --warmup ({warmup})")
    for line in update_report_lines(run(scene_name, w, h, frames, warmup, repeats, method)):
        click.echo(line)


@bench_grp.command("ab")
@click.argument("spec_a")
@click.argument("spec_b")
@click.option("--scene", "scene_names", multiple=True, default=["cornell"], show_default=True,
              help="scene name or .xml path (repeatable: one comparison per scene)")
@click.option("--res", default="160x90", show_default=True, help="image size WxH [pixels]")
@click.option("--frames", default=24, show_default=True, type=int, help="frames per run")
@click.option("--warmup", default=None, type=int, help="frames whose times are dropped [default: frames // 3]")
@click.option("--repeat", "repeats", default=3, show_default=True, type=int,
              help="repetitions of the pair, in turn (A B, B A, ...)")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--ref-spp", default=None, type=int,
              help="samples per pixel of an indirect reference [default: the references' own]")
@click.option("--json", "json_path", default=None, help="also write the figures to this JSON file")
def bench_ab(spec_a, spec_b, scene_names, res, frames, warmup, repeats, seed, ref_spp, json_path):
    """Two method settings (e.g. osc-gi osc-gi:sharp=0.2) timed in turn in one process on one viewer:
    median time per frame of each, the ratio B / A within each repetition, the metrics of the last
    frame against its reference and each image's md5 (a bit-identical refactor shows equal digests)."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.run.bench import ab_report_lines, bench_ab as run
    w, h = _parse_res(res)
    if frames < 1 or repeats < 1:
        _fail("--frames and --repeat must be at least 1")
    if warmup is not None and not 0 <= warmup < frames:
        _fail(f"--warmup ({warmup}) must be at least 0 and below --frames ({frames})")
    out = []
    for name in scene_names:
        r = run(name, spec_a, spec_b, w, h, frames, warmup, repeats, seed, ref_spp)
        out.append(r)
        for line in ab_report_lines(r):
            click.echo(line)
    if json_path:
        from slc.core import io  # after --variant, as above
        io.write_json(Path(json_path), out)


def main(argv=None):
    try:
        cli.main(args=argv, prog_name="slc", standalone_mode=False)
    except click.exceptions.Abort:
        _fail("aborted")
    except click.ClickException as e:
        e.show()
        sys.exit(2)
    except _errors() as e:
        _fail(str(e))
    except _jobs_failed() as e:  # a run error, not bad input: exit 1, completed jobs kept for --resume
        click.echo(f"slc: error: {e}", err=True)
        sys.exit(1)
    except SystemExit as e:
        raise e
    return 0


def run_experiment_standalone(path: str) -> int:
    """Entry point of ``python experiments/NAME.py [options]``."""
    # after --variant (the module builds Mitsuba types on import)
    from slc.run import experiment
    try:
        mod = experiment.load(Path(path).stem)
        _run_module(mod, sys.argv[1:], prog=Path(path).name)
    except _errors() as e:
        click.echo(f"{Path(path).name}: error: {e}", err=True)
        return 2
    except _jobs_failed() as e:
        click.echo(f"{Path(path).name}: error: {e}", err=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
