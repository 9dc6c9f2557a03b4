"""distributed: viewers on several render nodes sharing one surface cache (docs/distributed.md).

Viewers go to nodes round-robin; every node shades its viewers from its own copy of the cache.
Strategies, all from one run of the frames per rig: the single-process shared cache
(``single``), independent caches per node (``independent``), full replication (``full``:
every record updated in the frame sent to the other nodes) and owner-based sparse updates
(``sparse``: an entry's owner updates it and sends a subscribed node its record when the node
holds none of it or it changed by more than the threshold since the one it holds, ``delay``
frames late; a node stays subscribed ``--lease`` frames after it last needed the entry). Rigs: the overlap rig at
the target overlaps and the random rig, each with a static and a moving camera. Bytes and rays
are means, times medians, over the frames after the warm-up; FLIP on the last frame over all
viewers. ``model_ms_*``: a model of the frame time per node at scale (see the table's note).

    slc run distributed --quick
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.distributed.nodes import KINDS  # noqa: E402
from slc.distributed import DEFAULT_LEASE, DEFAULT_THRESHOLD  # noqa: E402
from slc.distributed.run import LINKS, RigRun, run_rig, strategies_for  # noqa: E402
from slc.run import experiment as ex  # noqa: E402
from slc.run.errors import ExperimentError  # noqa: E402
from slc.scene import views  # noqa: E402
from slc.scene.camera import Viewer  # noqa: E402
from slc.scene.random_walks import random_viewers  # noqa: E402

NAME = "distributed"
FULL = dict(scenes=["atrium"], nodes=4, viewers=16, overlaps=[25, 50, 100], rigs=["overlap", "random"],
            delays=[0, 1, 2, 4], cameras=["static", "moving"], width=96, height=54, frames=60, warmup=30)
QUICK = dict(scenes=["atrium"], nodes=4, viewers=16, overlaps=[50], rigs=["overlap", "random"],
             delays=[0, 2], cameras=["static", "moving"], width=64, height=36, frames=40, warmup=20)


def add_arguments(p):
    ex.add_common_arguments(p)
    p.add_argument("--nodes", type=int, help="render nodes (default 4)")
    p.add_argument("--viewers", type=int, help="viewers over all nodes, round-robin (default 16)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD,
                   help="sparse updates: an owner sends a record again when the entry changed by more than this "
                        "since the record the node holds (slc: the largest change of a cone's radiance relative to "
                        "the entry's, or its turn in radians weighted by its share, times sqrt(C/255) for an "
                        f"entry of C samples; unitless; default {DEFAULT_THRESHOLD})")
    p.add_argument("--lease", type=int, default=DEFAULT_LEASE,
                   help="sparse updates: frames a node stays subscribed to an entry after its viewers last "
                        f"needed it (0: it cancels in the first frame it does not; default {DEFAULT_LEASE})")
    p.add_argument("--delays", type=int, nargs="+", help="frames a record takes to arrive (default 0 1 2 4)")


def _static(vs: list) -> list:
    """The viewers held at their frame-0 pose."""
    return [Viewer(v.name, (lambda t, v=v: v.pose(0.0)), v.rig) for v in vs]


def run(opts):
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    n_nodes, n_view = opts.nodes or pr["nodes"], opts.viewers or pr["viewers"]
    if n_nodes < 1 or n_view < n_nodes:
        raise ExperimentError(f"--nodes must be at least 1 and at most --viewers (got {n_nodes} and {n_view})")
    if opts.threshold < 0:
        raise ExperimentError(f"--threshold must be >= 0 (got {opts.threshold})")
    if opts.lease < 0:
        raise ExperimentError(f"--lease must be >= 0 (got {opts.lease})")
    delays = opts.delays or pr["delays"]
    if any(d < 0 for d in delays):
        raise ExperimentError(f"--delays must be >= 0 (got {delays})")
    specs = opts.methods or ["slc"]
    names = ex.load_and_validate(opts.scene or pr["scenes"], specs, bool(opts.scene))
    strategies = strategies_for(delays, opts.threshold, opts.lease)
    rows = []
    for s in ex.each_scene(names):
        for spec in specs:
            run_ = RigRun(pr["width"], pr["height"], pr["frames"], pr["warmup"], n_nodes, spec, opts.seed)
            for rig, overlap in [("overlap", o) for o in pr["overlaps"]] + [("random", None)]:
                base = (views.overlap_rig(s, n_view, overlap / 100.0, aspect=pr["width"] / pr["height"])
                        if rig == "overlap" else random_viewers(s, n_view, seed=opts.seed))
                for cam in pr["cameras"]:
                    vs = _static(base) if cam == "static" else base
                    print(f"{NAME}: {s.name} {spec} {rig} {overlap} {cam}", file=sys.stderr, flush=True)
                    extra = {"scene": s.name, "method": spec, "rig": rig, "overlap": overlap, "camera": cam}
                    rows += run_rig(s, vs, run_, strategies, extra)
    md = _markdown(rows, pr, n_nodes, n_view, f"{opts.threshold:g}, lease {opts.lease} frames")
    config = {"quick": bool(opts.quick), "scenes": names, "methods": specs, "nodes": n_nodes, "viewers": n_view,
              "threshold": opts.threshold, "lease": opts.lease, "delays": delays, "width": pr["width"],
              "height": pr["height"],
              "frames": pr["frames"], "warmup": pr["warmup"], "seed": opts.seed,
              "links": [{"name": n, "gbit_s": g, "latency_ms": lat} for n, g, lat in LINKS]}
    results = ex.results_object(NAME, config, rows)
    ex.write_results(Path(opts.out) / NAME, results, md)
    print(md)
    return results


COLUMNS = [("rig", "rig"), ("overlap", "overlap %"), ("camera", "camera"), ("strategy", "strategy"),
           ("delay", "delay"), ("bytes_per_frame", "bytes/frame/node"), ("update_rays", "update rays/frame"),
           ("flip", "FLIP"), ("flip_vs_single", "FLIP vs single"), ("node_time_ms", "node t [ms]"),
           ("time_ms", "t [ms]"), ("model_ms_10g_1ms", "model t 10G/1ms [ms]"),
           ("model_ms_100g_0.1ms", "model t 100G/0.1ms [ms]")]


def _markdown(rows: list, pr: dict, n_nodes: int, n_view: int, threshold: str) -> str:
    md = (f"# {NAME}\n\n{n_nodes} nodes x {n_view // n_nodes} viewers, {pr['width']}x{pr['height']}, "
          f"{pr['frames']} frames ({pr['warmup']} warm-up); sparse threshold {threshold}. Bytes per frame per "
          "node and update rays per frame (summed over nodes) are means over the frames after the warm-up; "
          "times are medians (node t: mean over nodes, t: the slowest node; the owners' update is measured "
          "once and shared out by each node's rays, as the nodes run in one process here). FLIP: mean over all "
          "viewers on the last frame, against the 2048-sample ground truth and against the single-process "
          "shared cache. **Model columns** (not measured): a node's frame time at scale = its update rays at "
          "the ray rate measured here plus its share of the shading, plus for a sharing strategy its bytes "
          "over the link and, with delay 0, a round trip of the link's latency (with a delay the transfer "
          "overlaps later frames).\n\n")
    md += ex.markdown_table(rows, COLUMNS)
    md += ("\n\n## Where sparse's bytes go\n\nBytes per frame and node by kind (slc.distributed.nodes.KINDS): "
           "requests (subscriptions and cancellations), records of new entries, first records of an entry the "
           "node does not hold, and records sent again because the entry changed, by its state (young: in its "
           "first new_updates updates; moving: in a motion phase; settled).\n\n")
    md += ex.markdown_table([r for r in rows if r["strategy"] == "sparse"],
                            [("rig", "rig"), ("overlap", "overlap %"), ("camera", "camera"), ("delay", "delay"),
                             ("bytes_per_frame", "total")] + [(f"bytes_{k}", k) for k in KINDS])
    md += "\n\n## Targets (measured in this run)\n\n"
    for key in sorted({(r["rig"], r["overlap"], r["camera"]) for r in rows}, key=str):
        get = {(r["strategy"], r["delay"]): r for r in rows if (r["rig"], r["overlap"], r["camera"]) == key}
        single, full, sp = get.get(("single", 0)), get.get(("full", 0)), get.get(("sparse", 0))
        if not (single and full and sp):
            continue
        ratio = full["bytes_per_frame"] / max(sp["bytes_per_frame"], 1e-9)
        md += (f"- {key[0]} {key[1] if key[1] is not None else ''} {key[2]}: sparse sends 1/{ratio:.0f} of full "
               f"replication's bytes (target <= 1/65); FLIP {sp['flip']:.4f} = "
               f"{sp['flip'] / max(single['flip'], 1e-9):.3f}x single's {single['flip']:.4f} (target <= 1.02x); "
               f"update rays {sp['update_rays'] / max(single['update_rays'], 1e-9):.2f}x single's (target <= "
               f"1.1x); delays: " + ", ".join(f"{d}: FLIP {get[('sparse', d)]['flip']:.4f}"
                                             for d in sorted(d for k, d in get if k == "sparse")) + "\n")
    return md


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
