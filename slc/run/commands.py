"""What the commands of :mod:`slc.run.cli` do, imported by it once the Mitsuba variant is chosen
(the modules imported here build Mitsuba types on import)."""
from __future__ import annotations

import argparse
from pathlib import Path

import click
from tqdm import tqdm

from slc import methods
from slc.core import check, io
from slc.distributed import DEFAULT_LEASE, DEFAULT_THRESHOLD
from slc.methods.cache_method import PayloadMethod
from slc.run import bench, experiment
from slc.run.errors import ExperimentError
from slc.run.jobs import session_for
from slc.run.pipeline import RunConfig, run_sequence
from slc.scene import scenes, views


def list_scenes() -> None:
    """``slc scenes``."""
    for name, desc in scenes.describe_builtins():
        click.echo(f"{name:10s} {desc}")
    click.echo("(or any Mitsuba 3 scene: --scene path/to/scene.xml)")


def list_methods() -> None:
    """``slc methods``."""
    for name, desc in sorted(methods.available().items()):
        click.echo(f"{name:10s} {desc}")


def check_out(out) -> None:
    """``--out``: a folder, or a path where one can be made; a file there or on the way to it is
    bad input, reported before anything runs."""
    p = Path(out)
    for q in (p, *p.parents):
        if q.exists():
            if not q.is_dir():
                raise ExperimentError(f"--out {out}: {q} is a file, not a folder")
            return


def render(scene_name, method, viewers, rig, overlap, size, frames, warmup, seed, gt, out, nodes, threshold,
           address) -> None:
    """``slc render``: a sequence of one method, its images and timings written to ``out``."""
    if viewers < 1 or frames < 1:
        raise ExperimentError("--viewers and --frames must be at least 1")
    check_out(out)
    s = scenes.load(scene_name)
    # on nodes the spec is checked here once, without making the method: the nodes make it from its data
    m = methods.parse(method) if nodes else methods.create(method, s, seed=seed)
    try:
        vs = views.make_rig(s, rig, viewers, overlap)
    except ValueError as e:
        raise ExperimentError(str(e)) from None
    if nodes:
        render_nodes(scene_name, m, s, vs, nodes, threshold, address, size, frames, seed, gt, out)
        return
    w, h = size
    cfg = RunConfig(width=w, height=h, frames=frames, warmup=min(warmup, frames - 1), seed=seed,
                    eval_frames=[frames - 1] if gt else [])
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


def render_nodes(scene_name, ms, s, vs, nodes, threshold, address, size, frames, seed, gt, out) -> None:
    """``slc render --nodes K``: the viewers ``vs`` on K Ray render nodes, one process each
    (:func:`slc.distributed.actors.render_on_nodes`); ``s``: the scene loaded here (the rig, the
    images' composition), ``ms``: the method spec checked here (:class:`slc.methods.MethodSpec`),
    before Ray starts, and shipped to the nodes as data."""
    if nodes < 1 or nodes > len(vs):
        raise ExperimentError(f"--nodes must be between 1 and the number of viewers ({len(vs)}), got {nodes}")
    cls = ms.cls
    if cls is None or not issubclass(cls, PayloadMethod):
        raise ExperimentError(f"--nodes needs a cache method whose entries are records (slc, sh, adaptive); "
                              f"'{ms.name}' has none")
    name = cls.name                  # the method's name in the files written, as one process names them
    if gt:
        raise ExperimentError("--gt is not available with --nodes (slc run distributed compares the nodes' images)")
    t = DEFAULT_THRESHOLD if threshold is None else threshold
    if t < 0:
        raise ExperimentError(f"--threshold must be >= 0, got {t}")
    from slc.distributed.actors import render_on_nodes  # imports Ray: only when nodes are asked for
    res = render_on_nodes(s, scene_name, ms, vs, nodes, *size, frames, t, DEFAULT_LEASE, seed=seed, address=address)
    outd = Path(out)
    for v, img in sorted(res["images"].items()):
        io.write_hdr_and_png(outd / f"{s.name}_{name}_node{v % nodes}_{vs[v].name}", img, s.exposure)
    sent = res["bytes_per_frame"]
    io.write_json(outd / "nodes.json", {"scene": s.name, "method": ms.spec, "nodes": nodes, "threshold": t,
                                        "processes": res["processes"], "bytes_per_frame": sent,
                                        "serialized_bytes_per_frame": res["serialized_bytes_per_frame"]})
    click.echo(f"{s.name} {name} on {nodes} nodes, viewers={len(vs)}: {sum(sent) / max(len(sent), 1):.0f} bytes "
               f"per frame sent (mean over {len(sent)} frames), threshold {t:g}")
    click.echo(f"wrote {outd}")


def run_experiment(name: str, argv: list, prog: str) -> None:
    """``slc run NAME ARGS`` and ``python experiments/NAME.py ARGS``: the experiment's options parsed,
    then its ``run`` in a job session."""
    mod = experiment.load(name)
    p = argparse.ArgumentParser(prog=prog, description=(mod.__doc__ or "").strip().splitlines()[0])
    if hasattr(mod, "add_arguments"):
        mod.add_arguments(p)
    p.add_argument("--check", action="store_true",
                   help="check mode (= SLC_CHECK=1): stop at the first NaN/Inf or negative value")
    opts = p.parse_args(argv)
    if getattr(opts, "out", None):
        check_out(opts.out)
    if opts.check:
        check.enable()
    with session_for(getattr(mod, "NAME", prog.split()[-1]), opts):
        mod.run(opts)


def bench_rays(scene_name, size, n, repeats) -> None:
    """``slc bench rays``."""
    for line in bench.report_lines(bench.bench_rays(scene_name, *size, n, repeats)):
        click.echo(line)


def bench_update(scene_name, size, frames, warmup, repeats, method) -> None:
    """``slc bench update``."""
    for line in bench.update_report_lines(bench.bench_update(scene_name, *size, frames, warmup, repeats, method)):
        click.echo(line)


def bench_ab(spec_a, spec_b, scene_names, size, frames, warmup, repeats, seed, ref_spp, json_path) -> None:
    """``slc bench ab``: one comparison per scene, its lines printed, all of them in ``json_path``."""
    out = []
    for name in scene_names:
        r = bench.bench_ab(name, spec_a, spec_b, *size, frames, warmup, repeats, seed, ref_spp)
        out.append(r)
        for line in bench.ab_report_lines(r):
            click.echo(line)
    if json_path:
        io.write_json(Path(json_path), out)
