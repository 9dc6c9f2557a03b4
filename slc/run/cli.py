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

This module imports nothing that builds Mitsuba types: the group chooses the variant, then
imports what the commands do (:mod:`slc.run.commands`).
"""
from __future__ import annotations

import sys
from pathlib import Path

import click

from slc.core import backend, check
from slc.core.check import CheckError
from slc.core.errors import MethodError, SceneError
from slc.core.spec import SpecError
from slc.distributed import DEFAULT_THRESHOLD
from slc.run.errors import ExperimentError, JobsFailed

# bad input: one line, exit status 2, no results written
BAD_INPUT = (SceneError, MethodError, SpecError, ExperimentError, backend.BackendError, FileNotFoundError, CheckError)


def _commands():
    """:mod:`slc.run.commands`, once the variant is chosen."""
    # after --variant: the commands' modules build Mitsuba types on import
    from slc.run import commands
    return commands


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
        check.enable()
    try:
        backend.init(variant)
    except backend.BackendError as e:
        _fail(str(e))


@cli.command("scenes")
def scenes_cmd():
    """List the built-in scenes."""
    _commands().list_scenes()


@cli.command("methods")
def methods_cmd():
    """List the available methods."""
    _commands().list_methods()


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
    size = _parse_res(res)
    _commands().render(scene_name, method, viewers, rig, overlap, size, frames, warmup, seed, gt, out, nodes,
                       threshold, address)


@cli.command("run", add_help_option=False,
             context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.argument("experiment_name")
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def run_cmd(experiment_name, args):
    """Run an experiment (single-viewer, ...); options after the name."""
    _commands().run_experiment(experiment_name, list(args), prog=f"slc run {experiment_name}")


@cli.group("bench")
def bench_grp():
    """Micro-benchmarks."""


@bench_grp.command("rays")
@click.option("--scene", "scene_name", default="atrium", show_default=True)
@click.option("--res", default="320x180", show_default=True)
@click.option("--n", default=16, show_default=True, type=int, help="samples (rays) per pixel")
@click.option("--repeats", default=5, show_default=True, type=int, help="timed rounds, medians reported")
def bench_rays(scene_name, res, n, repeats):
    """RT-N throughput next to Mitsuba's raw scene.ray_test on the same rays, with Mitsuba's light sampler and the emitter table."""
    size = _parse_res(res)
    if n < 1 or repeats < 1:
        _fail("--n and --repeats must be at least 1")
    _commands().bench_rays(scene_name, size, n, repeats)


@bench_grp.command("update")
@click.option("--scene", "scene_name", default="atrium", show_default=True)
@click.option("--res", default="320x180", show_default=True)
@click.option("--frames", default=24, show_default=True, type=int, help="frames rendered")
@click.option("--warmup", default=10, show_default=True, type=int, help="first frames not timed")
@click.option("--repeats", default=5, show_default=True, type=int, help="timed rounds of the rays alone, medians reported")
@click.option("--method", default="slc", show_default=True, help="slc, with settings (slc:max_cones=2)")
def bench_update(scene_name, res, frames, warmup, repeats, method):
    """slc's frame time next to the rays its update traces, traced alone."""
    size = _parse_res(res)
    if frames <= warmup or warmup < 0:
        _fail(f"--warmup ({warmup}) must be at least 0 and below --frames ({frames})")
    if repeats < 1:
        _fail("--repeats must be at least 1")
    _commands().bench_update(scene_name, size, frames, warmup, repeats, method)


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
    size = _parse_res(res)
    if frames < 1 or repeats < 1:
        _fail("--frames and --repeat must be at least 1")
    if warmup is not None and not 0 <= warmup < frames:
        _fail(f"--warmup ({warmup}) must be at least 0 and below --frames ({frames})")
    _commands().bench_ab(spec_a, spec_b, scene_names, size, frames, warmup, repeats, seed, ref_spp, json_path)


def main(argv=None):
    try:
        cli.main(args=argv, prog_name="slc", standalone_mode=False)
    except click.exceptions.Abort:
        _fail("aborted")
    except click.ClickException as e:
        e.show()
        sys.exit(2)
    except BAD_INPUT as e:
        _fail(str(e))
    except JobsFailed as e:  # a run error, not bad input: exit 1, completed jobs kept for --resume
        click.echo(f"slc: error: {e}", err=True)
        sys.exit(1)
    except SystemExit as e:
        raise e
    return 0


def run_experiment_standalone(path: str) -> int:
    """Entry point of ``python experiments/NAME.py [options]`` (the variant: ``SLC_VARIANT`` or the
    automatic choice)."""
    try:
        backend.init()
        _commands().run_experiment(Path(path).stem, sys.argv[1:], prog=Path(path).name)
    except BAD_INPUT as e:
        click.echo(f"{Path(path).name}: error: {e}", err=True)
        return 2
    except JobsFailed as e:
        click.echo(f"{Path(path).name}: error: {e}", err=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
