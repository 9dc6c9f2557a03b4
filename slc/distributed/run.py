"""One rig under one sharing strategy, on render nodes (``slc run distributed``): the frames run
on a :class:`~slc.distributed.cluster.Cluster` of nodes in their own processes (Ray actors,
:class:`Processes`) or in this one, and the run's figures become a row.

Measured per frame: the bytes the nodes send (the protocol's count, by kind, and pickled), the
update rays summed over nodes, each node's wall and CPU time (its work, and its G-buffers apart),
the driver's wall time of the frame; on the last frame every viewer's image, compared (FLIP)
with the 2048-sample ground truth and with the single-process cache's image. :func:`model_ms`
turns a node's measured compute and bytes into a frame time over a stated link: a model, not a
measurement.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from slc import methods
from slc.distributed.cluster import Cluster, InProcess
from slc.distributed.node import KINDS, Node
from slc.distributed.rig import Strategy, ViewerPoses, assignment
from slc.methods.frames import Frame, FrameLoop
from slc.reference import references
from slc.reference.metrics import evaluate
from slc.scene import gbuffer as gbuf

# the links of the model columns: (name, Gbit/s, one-way latency in ms)
LINKS = (("10g_1ms", 10.0, 1.0), ("100g_0.1ms", 100.0, 0.1))


@dataclass
class RigRun:
    """What one run renders: ``frames`` frames (figures over those after ``warmup``), FLIP on
    the last, the cache method ``spec``, ``seed``, ground truth of ``gt_spp`` samples."""
    width: int
    height: int
    frames: int
    warmup: int
    spec: str = "slc"
    seed: int = 0
    gt_spp: int | None = None


class Processes:
    """Where the nodes of a run live: ``n`` Ray actor processes holding the scene ``scene_name``
    (``ray_nodes``; :func:`slc.distributed.actors.node_actors`), or this process (``scene``)."""

    def __init__(self, scene, scene_name: str, n: int, ray_nodes: bool = True, threads: int | None = None):
        self.scene, self.actors = scene, None
        if ray_nodes:
            # Ray only when the nodes run in processes of their own
            from slc.distributed.actors import node_actors
            self.actors = node_actors(scene_name, n, threads)

    def cluster(self, strategy: Strategy, assign: dict, run: RigRun) -> tuple:
        """(a :class:`Cluster` of the nodes of ``assign`` ({node: {viewer index: ViewerPoses}})
        under ``strategy``, the pids of their processes)."""
        live = sorted(assign)
        method = methods.parse(run.spec)        # checked once; every node makes the method from this data
        if self.actors is None:
            nodes = {n: Node(n, live, self.scene, method, assign[n], run.width, run.height, strategy, run.seed)
                     for n in live}
            return Cluster(InProcess(nodes), live, strategy.delay), [nodes[n].pid for n in live]
        # Ray only when the nodes run in processes of their own
        import ray
        from slc.distributed.actors import RayNodes
        actors = {n: self.actors[i] for i, n in enumerate(live)}
        pids = ray.get([actors[n].start.remote(n, live, method, assign[n], run.width, run.height, strategy,
                                               run.seed) for n in live])
        return Cluster(RayNodes(actors), live, strategy.delay), pids


def run_strategy(procs: Processes, strategy: Strategy, poses: list, n_nodes: int, run: RigRun) -> dict:
    """The frames of one rig (``poses``: :class:`ViewerPoses` of every viewer) on ``n_nodes``
    nodes under ``strategy``, walked by the frame loop (:class:`slc.methods.frames.FrameLoop`), a
    frame a :meth:`Cluster.step`. Returns the per-frame figures (after the warm-up), the last
    frame's images (viewer -> (3, pixels) numpy), the processes' pids."""
    cluster, pids = procs.cluster(strategy, assignment(poses, n_nodes), run)
    frames, images = [], {}

    def done(fr: Frame, out: dict) -> None:
        res = out["results"]
        if fr.evaluated:
            for r in res.values():
                images.update(r["images"])
        if fr.warm:
            return
        live = max(len(res), 1)
        frames.append({
            "bytes": out["bytes"] / live, "serialized": out["serialized"] / live,
            "messages": out["messages"] / live, "links": out["links"] / live,
            "kinds": {k: v / live for k, v in out["kinds"].items()}, "frame_ms": out["frame_ms"],
            "rays": sum(r["rays"] + r["boot_rays"] for r in res.values()),
            "boot_rays": sum(r["boot_rays"] for r in res.values()),
            "work": {n: r["clock"].wall.get("work", 0.0) for n, r in res.items()},
            "cpu": {n: r["clock"].cpu.get("work", 0.0) for n, r in res.items()},
            "gbuffer": {n: r["clock"].wall.get("gbuffer", 0.0) for n, r in res.items()},
            "memory": {n: r["memory"] for n, r in res.items()}})

    # the nodes make their own G-buffers; the images of the last frame are evaluated (flips)
    FrameLoop(run.frames, run.warmup, evaluated=frozenset({run.frames - 1})).run(
        lambda fr: cluster.step(fr.number, images=fr.evaluated), done)
    return {"frames": frames, "images": images, "pids": pids, "lost": list(cluster.lost),
            "viewers_per_node": max(len(v) for v in assignment(poses, n_nodes).values())}


def model_ms(compute_ms: float, bytes_per_node: float, strategy: Strategy, gbps: float, latency_ms: float,
             round_trips: int) -> float:
    """Modelled frame time of a node: its compute, plus for a sharing strategy the transfer of its
    bytes over the link and, with delay 0, ``round_trips`` round trips of the link's latency
    inside the frame (with a delay the transfer overlaps the next frames' work)."""
    if not strategy.sharing:
        return compute_ms
    transfer = 8.0 * bytes_per_node / (gbps * 1e9) * 1e3
    if strategy.delay == 0:
        return compute_ms + transfer + 2.0 * round_trips * latency_ms
    return max(compute_ms, transfer)


def _m(v: list) -> float:
    return float(np.mean(v)) if v else 0.0


def _med(v: list) -> float:
    return float(statistics.median(v)) if v else 0.0


def row(strategy: Strategy, res: dict, flip: dict, n_nodes: int, n_viewers: int, round_trips: int) -> dict:
    """The results row of one run (:func:`run_strategy`'s ``res``; ``flip``: :func:`flips`)."""
    fr = res["frames"]
    nodes = sorted(fr[0]["work"]) if fr else []
    slowest = [max(f["work"].values()) for f in fr]
    sparse = strategy.kind == "sparse"
    r = {"strategy": strategy.kind, "delay": strategy.delay, "hiding": strategy.hiding,
         "owners": ("a node that needs it" if strategy.delegate else "home") if sparse else None,
         "seeds": strategy.seeds if strategy.sharing else None,
         "threshold": strategy.threshold if strategy.kind == "sparse" else None,
         "lease": strategy.lease if strategy.kind == "sparse" else None, "bootstrap": strategy.bootstrap,
         "nodes": n_nodes, "viewers": n_viewers, "processes": len(set(res["pids"])),
         "gbuffer_viewers_per_node": res["viewers_per_node"],
         "bytes_per_frame": _m([f["bytes"] for f in fr]),
         "serialized_bytes_per_frame": _m([f["serialized"] for f in fr]),
         "update_rays": _m([f["rays"] for f in fr]), "bootstrap_rays": _m([f["boot_rays"] for f in fr]),
         "messages_per_frame": _m([f["messages"] for f in fr]), "peers_per_frame": _m([f["links"] for f in fr]),
         "flip": flip["flip"], "flip_vs_single": flip["flip_vs_single"],
         "time_ms": _med(slowest),
         "node_time_ms": _m([_med([f["work"][n] for f in fr]) for n in nodes]),
         "cpu_ms": _med([max(f["cpu"].values()) for f in fr]),
         "gbuffer_ms": _med([max(f["gbuffer"].values()) for f in fr]),
         "frame_ms": _med([f["frame_ms"] for f in fr]),
         "node_memory_mb": max(fr[-1]["memory"].values()) / 2 ** 20 if fr else 0.0,
         "lost_nodes": len(res["lost"])}
    r.update({f"bytes_{k}": _m([f["kinds"][k] for f in fr]) for k in KINDS})
    for name, gbps, lat in LINKS:
        r[f"model_ms_{name}"] = model_ms(r["cpu_ms"], r["bytes_per_frame"], strategy, gbps, lat, round_trips)
    return r


def flips(scene, output: str, viewers: list, run: RigRun, images: dict, single: dict) -> dict:
    """Mean FLIP over the viewers of ``images`` on the last frame, against the ground truth
    (``flip``) and against ``single`` (the single-process cache's images, ``flip_vs_single``);
    ``strip``: viewer 0's (ground truth, image, FLIP map, exposure)."""
    f = run.frames - 1
    gbs = gbuf.frame_gbuffers(scene, viewers, f, run.width, run.height)
    f_gt, f_single, strip = [], [], None
    for v, img in sorted(images.items()):
        gb = gbs[v]
        test = references.image_of(output, gb, mi.Color3f(img))
        gt = references.reference_for(output, scene, gb, f, gb.viewer, spp=run.gt_spp)
        exposure = references.exposure_for(output, scene, gt)
        m = evaluate(gt, test, exposure, with_map=v == 0)
        f_gt.append(m["flip"])
        if v == 0:
            strip = (gt, test, m["flip_map"], exposure)
        f_single.append(evaluate(references.image_of(output, gb, mi.Color3f(single[v])), test, exposure)["flip"])
    nan = float("nan")
    return {"flip": float(np.mean(f_gt)) if f_gt else nan, "flip_vs_single": float(np.mean(f_single)) if f_gt else nan,
            "strip": strip}


def poses_of(viewers: list, frames: int) -> list:
    return [ViewerPoses.of(v, frames) for v in viewers]
