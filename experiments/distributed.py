"""distributed: viewers on several render nodes sharing one surface cache (docs/distributed.md).

A process per node (Ray actors on a local instance; ``--address`` for a cluster, ``--in-process``
for one process), viewer v on node v mod K, each node rendering its own viewers' G-buffers
only. Strategies, each its own run of the frames per rig: the single-process shared cache
(``single``, one node), independent caches per node (``independent``), full replication
(``full``: every updated record to every node) and owner-based sparse updates (``sparse``: a
record a node needs and does not hold, or one changed by more than the threshold since the one
it holds), messages ``delay`` frames late; at a delay, a row per latency hiding (none, requests
from the cameras' extrapolated motion, bootstrap rays, both). Rigs: the overlap rig at the
target overlaps and the random rig, each with a static and a moving camera; and the random rig
at 2 and K nodes with the viewers per node fixed. Bytes and rays are means, times medians, over
the frames after the warm-up; FLIP on the last frame over all viewers.

    slc run distributed --quick
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os  # noqa: E402 (after the path of a standalone run)

from slc import methods  # noqa: E402
from slc.core import io  # noqa: E402
from slc.distributed import DEFAULT_BOOTSTRAP, DEFAULT_LEASE, DEFAULT_THRESHOLD  # noqa: E402
from slc.distributed.node import KINDS  # noqa: E402
from slc.distributed.rig import Strategy  # noqa: E402
from slc.distributed.run import LINKS, Processes, RigRun, flips, poses_of, row, run_strategy  # noqa: E402
from slc.run import experiment as ex, plots  # noqa: E402
from slc.run.errors import ExperimentError  # noqa: E402
from slc.scene import views  # noqa: E402
from slc.scene.camera import Viewer  # noqa: E402
from slc.scene.random_walks import random_viewers  # noqa: E402

NAME = "distributed"
FULL = dict(scenes=["atrium"], nodes=4, viewers=16, overlaps=[25, 50, 100], delays=[0, 1, 2, 4],
            cameras=["static", "moving"], width=96, height=54, frames=60, warmup=30, scale_nodes=[2])
QUICK = dict(scenes=["atrium"], nodes=4, viewers=16, overlaps=[50], delays=[0, 2],
             cameras=["static", "moving"], width=64, height=36, frames=40, warmup=20, scale_nodes=[2])
# latency hiding, (predict, bootstrap on): at delay 2 each part alone and both; at other delays none and both
HIDING = ((False, 0), (True, 0), (False, 1), (True, 1))
EACH_PART_AT = 2


def add_arguments(p):
    ex.add_common_arguments(p)
    p.add_argument("--nodes", type=int, help="render nodes, one process each (default 4)")
    p.add_argument("--viewers", type=int, help="viewers over all nodes, round-robin (default 16)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD,
                   help="sparse updates: an owner sends a record again when the entry changed by more than this "
                        "since the record the node holds (slc: the largest change of a cone's radiance relative to "
                        "the entry's, or its turn in radians weighted by its share, times sqrt(C/255) for an "
                        f"entry of C samples; unitless; default {DEFAULT_THRESHOLD})")
    p.add_argument("--lease", type=int, default=DEFAULT_LEASE,
                   help="sparse updates: frames a node stays subscribed to an entry after its viewers last "
                        f"needed it (0: it cancels in the first frame it does not; default {DEFAULT_LEASE})")
    p.add_argument("--delays", type=int, nargs="+", help="frames a message takes (default 0 1 2 4; quick 0 2)")
    p.add_argument("--bootstrap", type=int, default=DEFAULT_BOOTSTRAP,
                   help="latency hiding: update rays per frame a node spends on an entry its viewers need and "
                        f"that it holds no record of, until the record arrives (default {DEFAULT_BOOTSTRAP})")
    p.add_argument("--in-process", action="store_true",
                   help="run the nodes in this process, one after another (no Ray; processes = 1)")


def _static(vs: list) -> list:
    """The viewers held at their frame-0 pose."""
    return [Viewer(v.name, (lambda t, v=v: v.pose(0.0)), v.rig) for v in vs]


def _check(opts, n_nodes: int, n_view: int, delays: list) -> None:
    if n_nodes < 1 or n_view < n_nodes:
        raise ExperimentError(f"--nodes must be at least 1 and at most --viewers (got {n_nodes} and {n_view})")
    for name, v in (("--threshold", opts.threshold), ("--lease", opts.lease), ("--bootstrap", opts.bootstrap)):
        if v < 0:
            raise ExperimentError(f"{name} must be >= 0 (got {v})")
    if any(d < 0 for d in delays):
        raise ExperimentError(f"--delays must be >= 0 (got {delays})")
    if opts.workers or opts.resume:
        raise ExperimentError("--workers and --resume do not apply: the nodes are the processes (--nodes)")


def strategies(delays: list, opts) -> list:
    """Full replication (delay 0) and sparse updates at every delay; at delay 0 also with each
    part of the protocol left out alone (seeds asked of their owners exactly; regions owned by
    their home, not by a node that needs them); at a delay, without and with latency hiding
    (:data:`HIDING`: each part alone at delay :data:`EACH_PART_AT`)."""
    t, lease = float(opts.threshold), int(opts.lease)
    out = [Strategy("full")]
    for d in delays:
        for predict, boot in (HIDING[:1] if d == 0 else HIDING if d == EACH_PART_AT else HIDING[::3]):
            out.append(Strategy("sparse", int(d), t, lease, predict, int(opts.bootstrap) if boot else 0))
        if d == 0 and t > 0:
            out += [Strategy("sparse", 0, t, lease, seeds="exact"), Strategy("sparse", 0, t, lease, delegate=False)]
    return out


@dataclass(frozen=True)
class _RigCase:
    """One rig of the run: ``rig`` (overlap or random) at ``overlap`` percent (overlap rigs),
    ``camera`` (moving or static), its viewers spread over ``nodes`` nodes."""
    rig: str
    overlap: float | None
    camera: str
    nodes: int
    viewers: int


def run(opts):
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    n_nodes, n_view = opts.nodes or pr["nodes"], opts.viewers or pr["viewers"]
    delays = opts.delays or pr["delays"]
    _check(opts, n_nodes, n_view, delays)
    specs = opts.methods or ["slc"]
    names = ex.load_and_validate(opts.scene or pr["scenes"], specs, bool(opts.scene))
    per_node = n_view // n_nodes
    scale = sorted({k for k in pr["scale_nodes"] if 1 < k < n_nodes})
    rows, images = [], {}
    for s, name in zip(ex.each_scene(names), names):
        procs = _processes(opts, s, name, n_nodes)
        try:
            for spec in specs:
                run_ = RigRun(pr["width"], pr["height"], pr["frames"], pr["warmup"], spec, opts.seed)
                rigs = [_RigCase("overlap", o, c, n_nodes, n_view) for o in pr["overlaps"] for c in pr["cameras"]]
                rigs += [_RigCase("random", None, c, n_nodes, n_view) for c in pr["cameras"]]
                rigs += [_RigCase("random", None, "moving", k, k * per_node) for k in scale]
                for r in rigs:
                    base = (views.overlap_rig(s, r.viewers, r.overlap / 100.0, aspect=pr["width"] / pr["height"])
                            if r.rig == "overlap" else random_viewers(s, r.viewers, seed=opts.seed))
                    vs = _static(base) if r.camera == "static" else base
                    extra = {"scene": s.name, "method": spec, "rig": r.rig, "overlap": r.overlap, "camera": r.camera,
                             "block": "scale" if r.nodes != n_nodes else "main"}
                    rows += _rig_rows(s, procs, vs, run_, r.nodes, strategies(delays, opts) if r.nodes == n_nodes
                                      else [Strategy("sparse", 0, opts.threshold, opts.lease)], extra, images)
        finally:
            procs.close()
    md = _markdown(rows, pr, n_nodes, n_view, opts)
    config = {"quick": bool(opts.quick), "scenes": names, "methods": specs, "nodes": n_nodes, "viewers": n_view,
              "threshold": opts.threshold, "lease": opts.lease, "delays": delays, "bootstrap": opts.bootstrap,
              "width": pr["width"], "height": pr["height"], "frames": pr["frames"], "warmup": pr["warmup"],
              "seed": opts.seed, "in_process": bool(opts.in_process), "address": opts.address,
              "threads": opts.threads, "links": [{"name": n, "gbit_s": g, "latency_ms": lat} for n, g, lat in LINKS]}
    results = ex.results_object(NAME, config, rows)
    out = Path(opts.out) / NAME
    ex.write_results(out, results, md)
    _figures(out, rows, images)
    print(md)
    return results


class _Procs:
    """:class:`Processes` and the Ray instance this run started (shut down by :meth:`close`)."""

    def __init__(self, procs: Processes, own_ray: bool):
        self.procs, self.own_ray = procs, own_ray

    def __getattr__(self, name):
        return getattr(self.procs, name)

    def close(self) -> None:
        if self.own_ray:
            import ray  # Ray: only when the nodes are processes (not --in-process)
            ray.shutdown()


def _processes(opts, scene, name: str, n_nodes: int) -> _Procs:
    if opts.in_process:
        return _Procs(Processes(scene, name, n_nodes, ray_nodes=False), False)
    from slc.distributed.actors import start_ray  # imports Ray: only when the nodes are processes
    threads = opts.threads or max((os.cpu_count() or 1) // n_nodes, 1)
    own = start_ray(n_nodes, opts.address)
    try:
        return _Procs(Processes(scene, name, n_nodes, ray_nodes=True, threads=threads), own)
    except Exception:
        if own:
            import ray  # Ray: only when the nodes are processes
            ray.shutdown()
        raise


def _rig_rows(s, procs, vs: list, run_: RigRun, n_nodes: int, strats: list, extra: dict, images: dict) -> list:
    """The rows of one rig: the single-process cache first (the images every other run is
    compared with), independent caches, then ``strats``."""
    poses = poses_of(vs, run_.frames)
    print(f"{NAME}: {extra['scene']} {extra['method']} {extra['rig']} {extra['overlap']} {extra['camera']} "
          f"{n_nodes} nodes", file=sys.stderr, flush=True)
    output = methods.create(run_.spec, s).output
    runs = [(Strategy("single"), 1)] + ([(Strategy("independent"), n_nodes)] if extra["block"] == "main" else [])
    runs += [(st, n_nodes) for st in strats]
    rows, single = [], None
    for st, k in runs:
        res = run_strategy(procs, st, poses, k, run_)
        single = res["images"] if single is None else single
        f = flips(s, output, vs, run_, res["images"], single)
        variant = ("owners by home" if st.kind == "sparse" and not st.delegate else
                   "seeds exact" if st.kind == "sparse" and st.seeds == "exact" and st.threshold > 0 else "")
        rows.append({**row(st, res, f, k, len(vs), 2 if st.seeds == "exact" else 1), **extra, "variant": variant})
        if extra["camera"] == "moving" and extra["block"] == "main" and f["strip"] is not None:
            images[(extra["rig"], extra["overlap"], st.label)] = f["strip"]
    return rows


COLUMNS = [("rig", "rig"), ("overlap", "overlap %"), ("camera", "camera"), ("strategy", "strategy"),
           ("owners", "owners"), ("seeds", "seeds"), ("delay", "delay"), ("hiding", "hiding"), ("nodes", "nodes"),
           ("processes", "processes"),
           ("gbuffer_viewers_per_node", "G-buffer viewers/node"),
           ("bytes_per_frame", "bytes/frame/node"), ("serialized_bytes_per_frame", "pickled bytes/frame/node"),
           ("update_rays", "update rays/frame"), ("flip", "FLIP"), ("flip_vs_single", "FLIP vs single"),
           ("time_ms", "t slowest node [ms]"), ("cpu_ms", "CPU slowest node [ms]"), ("gbuffer_ms", "G-buffers [ms]"),
           ("frame_ms", "frame (driver) [ms]"), ("node_memory_mb", "node memory [MB]"),
           ("model_ms_10g_1ms", "model t 10G/1ms [ms]"), ("model_ms_100g_0.1ms", "model t 100G/0.1ms [ms]")]


def _key(r: dict) -> tuple:
    return (r["rig"], r["overlap"], r["camera"], r["block"], r["viewers"])


def _fmt_rig(r: dict) -> str:
    return f"{r['rig']}{'' if r['overlap'] is None else ' ' + str(r['overlap']) + '%'}, {r['camera']}"


def _markdown(rows: list, pr: dict, n_nodes: int, n_view: int, opts) -> str:
    md = (f"# {NAME}\n\n{n_nodes} nodes x {n_view // n_nodes} viewers, {pr['width']}x{pr['height']}, "
          f"{pr['frames']} frames ({pr['warmup']} warm-up); sparse threshold {opts.threshold:g}, lease "
          f"{opts.lease} frames, bootstrap {opts.bootstrap} rays. "
          + ("Nodes in this process, one after another. " if opts.in_process else
             "One Ray actor process per node, each rendering its own viewers' G-buffers only. ")
          + "**Measured**: bytes per frame and node (the protocol's count: the addresses as varint differences, "
          "the payload's record bytes, the need bits' changes, deflated when shorter; and the messages pickled, "
          "protocol 5, as Ray carries them from one process to another) and "
          "update rays per frame summed over nodes (bootstrap rays included) are means over the frames after the "
          "warm-up; times are medians over those frames: t and CPU of the slowest node's work in the frame "
          "(G-buffers apart), the driver's wall time of the frame (every phase's round trip through Ray "
          "included); node memory: the largest node's cache, payload and protocol state. FLIP: mean over all "
          "viewers on the last frame, against the 2048-sample ground truth and against the single-process "
          "shared cache. **Model columns** (not measured): the slowest node's CPU time, plus for a sharing "
          "strategy its bytes over the link and, with delay 0, the round trips of the link's latency in the "
          "frame (requests and records: 1; with seeds exact, seed queries and replies: 2), or with a delay the "
          "larger of compute and transfer.\n\n")
    every = [r for r in rows if r["block"] == "main"]
    main = [r for r in every if not r["variant"]]
    md += ex.markdown_table(every, COLUMNS)
    md += ("\n\n## Where sparse's bytes go\n\nBytes per frame and node by kind (slc.distributed.node.KINDS): "
           "requests (subscriptions and cancellations), need bits, seed queries and replies, records of entries "
           "new at their owner, first records of an entry the node does not hold, and records sent again "
           "because the entry changed, by its state (young: in its first new_updates updates; moving: in a "
           "motion phase; settled).\n\n")
    md += ex.markdown_table([r for r in main if r["strategy"] == "sparse" and r["hiding"] == "none"],
                            [("rig", "rig"), ("overlap", "overlap %"), ("camera", "camera"), ("delay", "delay"),
                             ("bytes_per_frame", "total")] + [(f"bytes_{k}", k) for k in KINDS])
    md += _parts_table(every)
    md += _hiding_table(main)
    md += _scale_table(rows, n_nodes)
    md += _targets(main, n_nodes, n_view)
    return md


def _parts_table(rows: list) -> str:
    """Sparse updates at delay 0 with each part of the protocol left out alone."""
    out = ("\n\n## Each part of sparse updates\n\nDelay 0: the protocol as run (new regions owned by a node "
           "that needs them, a new entry seeded from what its owner holds), with LOD seeds asked of their owners "
           "exactly, and with every region owned by its home: bytes against full replication's, FLIP against the "
           "single cache's.\n\n| rig | protocol | bytes vs full | FLIP vs single's |\n|---|---|---|---|\n")
    for key in sorted({_key(r) for r in rows}, key=str):
        get = [r for r in rows if _key(r) == key]
        single = next((r for r in get if r["strategy"] == "single"), None)
        full = next((r for r in get if r["strategy"] == "full"), None)
        for r in get:
            if r["strategy"] == "sparse" and r["delay"] == 0 and single and full:
                out += (f"| {_fmt_rig(r)} | {r['variant'] or 'as run'} | "
                        f"1/{full['bytes_per_frame'] / max(r['bytes_per_frame'], 1e-9):.0f} | "
                        f"{r['flip'] / max(single['flip'], 1e-9):.3f}x |\n")
    return out


def _hiding_table(rows: list) -> str:
    out = ("\n\n## Latency hiding\n\nMoving cameras: FLIP of sparse updates at each delay and hiding, against "
           "delay 0's (target at delay 2: at most 1.05x), with the bytes and update rays (bootstrap included) "
           "against delay 0's.\n\n| rig | delay | hiding | FLIP | vs delay 0 | bytes vs delay 0 | rays vs delay 0 |\n"
           "|---|---|---|---|---|---|---|\n")
    for key in sorted({_key(r) for r in rows if r["camera"] == "moving"}, key=str):
        rs = [r for r in rows if _key(r) == key and r["strategy"] == "sparse"]
        d0 = next((r for r in rs if r["delay"] == 0), None)
        if d0 is None:
            continue
        for r in sorted(rs, key=lambda r: (r["delay"], r["hiding"])):
            out += (f"| {_fmt_rig(r)} | {r['delay']} | {r['hiding']} | {r['flip']:.4f} | "
                    f"{r['flip'] / max(d0['flip'], 1e-9):.3f}x | {r['bytes_per_frame'] / max(d0['bytes_per_frame'], 1e-9):.2f}x | "
                    f"{r['update_rays'] / max(d0['update_rays'], 1e-9):.2f}x |\n")
    return out


def _scale_table(rows: list, n_nodes: int) -> str:
    rs = [r for r in rows if r["rig"] == "random" and r["camera"] == "moving" and r["strategy"] == "sparse"
          and r["delay"] == 0 and r["hiding"] == "none" and not r["variant"]]
    if len({r["nodes"] for r in rs}) < 2:
        return ""
    out = ("\n\n## A node's work as nodes are added\n\nThe random rig, moving cameras, sparse updates at delay 0, "
           "the viewers per node fixed: the slowest node's work (wall and CPU; the wall time includes waiting for a "
           "core when the nodes outnumber this machine's cores), its G-buffers, its memory, its bytes.\n\n"
           "| nodes | viewers | G-buffer viewers/node | t [ms] | CPU [ms] | G-buffers [ms] | node memory [MB] | "
           "bytes/frame/node | update rays/frame/node |\n|---|---|---|---|---|---|---|---|---|\n")
    for r in sorted(rs, key=lambda r: r["nodes"]):
        out += (f"| {r['nodes']} | {r['viewers']} | {r['gbuffer_viewers_per_node']} | {r['time_ms']:.2f} | "
                f"{r['cpu_ms']:.2f} | {r['gbuffer_ms']:.2f} | {r['node_memory_mb']:.1f} | {r['bytes_per_frame']:.0f} | "
                f"{r['update_rays'] / r['nodes']:.0f} |\n")
    return out


def _targets(main: list, n_nodes: int, n_view: int) -> str:
    out = "\n\n## Targets (measured in this run)\n\n"
    shared = [r for r in main if r["strategy"] in ("full", "sparse", "independent")]
    out += (f"- processes: {sorted({r['processes'] for r in shared})} (target: the nodes, {n_nodes}); G-buffer "
            f"viewers per node: {sorted({r['gbuffer_viewers_per_node'] for r in shared})} (target "
            f"{n_view // n_nodes})\n")
    for key in sorted({_key(r) for r in main}, key=str):
        get = {(r["strategy"], r["delay"], r["hiding"]): r for r in main if _key(r) == key}
        single, full, sp = get.get(("single", 0, "none")), get.get(("full", 0, "none")), get.get(("sparse", 0, "none"))
        if not (single and full and sp):
            continue
        ratio = full["bytes_per_frame"] / max(sp["bytes_per_frame"], 1e-9)
        ratio_p = full["serialized_bytes_per_frame"] / max(sp["serialized_bytes_per_frame"], 1e-9)
        target = 65 if sp["camera"] == "static" else 40
        line = (f"- {_fmt_rig(sp)}: sparse sends 1/{ratio:.0f} of full replication's bytes (pickled: 1/{ratio_p:.0f}; "
                f"target <= 1/{target}); FLIP {sp['flip']:.4f} = {sp['flip'] / max(single['flip'], 1e-9):.3f}x "
                f"single's {single['flip']:.4f} (target <= 1.02x); update rays "
                f"{sp['update_rays'] / max(single['update_rays'], 1e-9):.2f}x single's (target <= 1.1x)")
        delayed = sorted((r for (k, d, h), r in get.items() if k == "sparse" and d > 0), key=lambda r: (r["delay"], r["hiding"]))
        if delayed:
            line += "; FLIP vs delay 0: " + ", ".join(
                f"d{r['delay']} {r['hiding']} {r['flip'] / max(sp['flip'], 1e-9):.3f}x" for r in delayed)
        out += line + "\n"
    return out


def _figures(out: Path, rows: list, images: dict) -> None:
    """FLIP against the delay per latency hiding (moving cameras), and viewer 0's last frame under
    the single cache and sparse updates at the largest delay without and with both hidings."""
    plt = plots.pyplot()
    main = [r for r in rows if r["block"] == "main" and r["strategy"] == "sparse" and r["camera"] == "moving"
            and not r["variant"]]
    keys = sorted({_key(r) for r in main}, key=str)
    if keys:
        fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.8), layout="constrained", squeeze=False)
        for ax, key in zip(axes[0], keys):
            rs = [r for r in main if _key(r) == key]
            d0 = [r for r in rs if r["delay"] == 0]
            for h in sorted({r["hiding"] for r in rs if r["delay"] > 0}):
                line = sorted(d0 + [r for r in rs if r["delay"] > 0 and r["hiding"] == h], key=lambda r: r["delay"])
                ax.plot([r["delay"] for r in line], [r["flip"] for r in line], "o-", ms=4, label=h)
            ax.set_title(_fmt_rig(rs[0]), fontsize=9)
            ax.set_xlabel("delay [frames]")
            ax.set_ylabel("FLIP")
            ax.grid(alpha=0.3)
        fig.legend(*axes[0][0].get_legend_handles_labels(), loc="outside lower center", ncol=4, fontsize=7,
                   frameon=False)
        io.write_figure(out / "flip_vs_delay.png", fig, dpi=120)
        plt.close(fig)
    _strips(out, rows, images)


def _strips(out: Path, rows: list, images: dict) -> None:
    """Viewer 0's last frame per moving rig and strategy: ground truth | image | FLIP map."""
    for (rig, overlap, label), (gt, img, fmap, exposure) in images.items():
        io.comparison_strip(out / "images" / f"{rig}{overlap or ''}_moving_{label}_v0.png", gt, img, fmap, exposure)
