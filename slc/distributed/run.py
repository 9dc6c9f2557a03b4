"""One rig of the strategy comparison: the single-process shared cache, independent caches per
node, full replication and owner-based sparse updates, from one run of the frames (the owners'
values are the single-process cache's, so every owner-based strategy shares its update).

Per frame and strategy: bytes sent per node (the cluster's bytes over its nodes; requests, keys
and records), update rays summed over nodes, each node's time; on the last frame FLIP against
the ground truth and against the single-process images. :func:`model_ms` turns bytes and rays
into a frame time at scale for a stated link (a model, not a measurement).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import drjit as dr
import numpy as np

from slc import methods
from slc.distributed import DEFAULT_LEASE
from slc.distributed.nodes import KINDS, SharedCacheNodes, Strategy
from slc.methods import FrameContext
from slc.reference import references
from slc.reference.metrics import evaluate
from slc.core.timing import StageTimer
from slc.scene import gbuffer as gbuf

# the links of the model column: (name, Gbit/s, one-way latency in ms)
LINKS = (("10g_1ms", 10.0, 1.0), ("100g_0.1ms", 100.0, 0.1))


@dataclass
class RigRun:
    """What one rig runs: ``frames`` frames (statistics over those after ``warmup``), FLIP on the
    last, ``n_nodes`` nodes, the cache method ``spec``, ``seed``."""
    width: int
    height: int
    frames: int
    warmup: int
    n_nodes: int
    spec: str = "slc"
    seed: int = 0
    gt_spp: int | None = None


def gbuffers(scene, viewers, frame: int, width: int, height: int) -> list:
    """One G-buffer per viewer (as the pipeline's), laid out as the frame's layers."""
    scene.set_frame(frame)
    out = [gbuf.render_gbuffer(scene, v.camera(frame), width, height, v.camera(frame - 1) if frame > 0 else None,
                               v.name) for v in viewers]
    gbuf.attach_layers(out)
    return out


def model_ms(compute_ms: float, bytes_per_node: float, delay: int, gbps: float, latency_ms: float,
             sharing: bool) -> float:
    """Modelled frame time of a node: its compute, plus for a sharing strategy the transfer of its
    bytes over the link and, with delay 0, a request and its records' round trip inside the frame
    (with a delay the transfer overlaps the next frames' work)."""
    transfer = 8.0 * bytes_per_node / (gbps * 1e9) * 1e3
    if not sharing:
        return compute_ms
    if delay == 0:
        return compute_ms + transfer + 2.0 * latency_ms
    return max(compute_ms, transfer)


def run_rig(scene, viewers, run: RigRun, strategies: list, extra: dict) -> list:
    """The rows of one rig (see the module); ``extra`` is added to every row.

    One function because the strategies' per-frame figures, images and timings are collected
    from one pass over the frames (the owners' update and the single-process images are shared
    by all of them) and turned into rows together."""
    method = methods.create(run.spec, scene, seed=run.seed)
    nodes = SharedCacheNodes(method, run.n_nodes, len(viewers), strategies)
    indep = [methods.create(run.spec, scene, seed=run.seed) for _ in range(run.n_nodes)]
    timer = StageTimer()
    labels = [s.label for s in strategies]
    acc = {k: {"bytes": [], "rays": [], "node": [], "time": [], "kinds": []} for k in ["single", "independent"] + labels}
    through = []
    for f in range(run.frames):
        gbs = gbuffers(scene, viewers, f, run.width, run.height)
        ctx = FrameContext(frame=f)
        timer.begin_frame()
        out = nodes.step(ctx, gbs, timer)
        timer.end_frame()
        # ------------------------------- independent caches: every node updates all it sees
        ind_imgs, ind_ms, ind_rays = {}, [], 0
        for n, m in enumerate(indep):
            vs = nodes.viewers.get(n, [])
            t0 = time.perf_counter()
            imgs = m.render(ctx, [gbs[v] for v in vs], timer)
            dr.eval(imgs)
            dr.sync_thread()
            ind_ms.append(1e3 * (time.perf_counter() - t0))
            ind_rays += int(dr.sum(m.update_rays)[0]) if m.update_rays is not None and dr.width(m.update_rays) else 0
            ind_imgs.update(zip(vs, imgs))
        if f < run.warmup:
            continue
        rays = out["rays"]
        through.append(rays / max(out["update_ms"], 1e-6))
        single_ms = out["update_ms"] + out["shade_ms"]
        _put(acc["single"], 0.0, rays, single_ms, single_ms)
        _put(acc["independent"], 0.0, ind_rays, statistics.mean(ind_ms), max(ind_ms))
        for s in strategies:
            tr = out[s.label]["traffic"]
            per = [out["update_ms"] * out["owned_rays"][n] / max(rays, 1) + tr.node_ms[n] for n in nodes.live]
            _put(acc[s.label], tr.total / len(nodes.live), rays, statistics.mean(per), max(per))
            acc[s.label]["kinds"].append({k: v / len(nodes.live) for k, v in tr.kinds.items()})
    # ------------------------------- FLIP of the last frame against the ground truth and single
    f = run.frames - 1
    single = out["single"]
    images = {"single": dict(enumerate(single)), "independent": ind_imgs}
    images.update({s.label: out[s.label]["images"] for s in strategies})
    flips = {k: _flips(scene, method, gbs, f, imgs, single, run.gt_spp) for k, imgs in images.items()}
    ray_rate = statistics.median(through) if through else 0.0      # rays per ms of the owners' update
    rows = []
    for k, kind, delay in [("single", "single", 0), ("independent", "independent", 0)] + \
            [(s.label, s.kind, s.delay) for s in strategies]:
        a, (flip, flip_single) = acc[k], flips[k]
        row = {"strategy": kind, "delay": delay, "bytes_per_frame": _m(a["bytes"]),
               "update_rays": _m(a["rays"]), "flip": flip, "flip_vs_single": flip_single,
               "node_time_ms": statistics.median(a["node"]) if a["node"] else 0.0,
               "time_ms": statistics.median(a["time"]) if a["time"] else 0.0,
               "nodes": run.n_nodes if kind != "single" else 1, "viewers": len(viewers),
               "ray_rate_per_ms": ray_rate, **extra}
        if kind == "sparse":     # bytes per frame and node by kind (slc.distributed.nodes.KINDS)
            row.update({f"bytes_{k}": _m([d[k] for d in a["kinds"]]) for k in KINDS})
        if kind == "sparse":
            row["threshold"] = next(s.threshold for s in strategies if s.label == k)
        sharing = kind in ("full", "sparse")
        rays_node = row["update_rays"] / (1 if kind == "single" else run.n_nodes)
        compute = rays_node / max(ray_rate, 1e-9) + _shade_share(out, run, kind)
        for name, gbps, lat in LINKS:
            row[f"model_ms_{name}"] = model_ms(compute, row["bytes_per_frame"], delay, gbps, lat, sharing)
        rows.append(row)
    return rows


def _shade_share(out: dict, run: RigRun, kind: str) -> float:
    """A node's shading time in the model: the single-process shading of all viewers over the
    nodes (one node for ``single``)."""
    return out["shade_ms"] / (1 if kind == "single" else run.n_nodes)


def _put(a: dict, b: float, rays: int, node_ms: float, frame_ms: float) -> None:
    a["bytes"].append(b)
    a["rays"].append(rays)
    a["node"].append(node_ms)
    a["time"].append(frame_ms)


def _m(v: list) -> float:
    return float(np.mean(v)) if v else 0.0


def _flips(scene, method, gbs, frame: int, imgs: dict, single: list, spp) -> tuple:
    """Mean FLIP over the viewers in ``imgs`` against the ground truth and against ``single``."""
    f_gt, f_single = [], []
    for v, img in imgs.items():
        gb = gbs[v]
        test = references.image_of(method.output, gb, img)
        gt = references.reference_for(method.output, scene, gb, frame, gb.viewer, spp=spp)
        exposure = references.exposure_for(method.output, scene, gt)
        f_gt.append(evaluate(gt, test, exposure)["flip"])
        f_single.append(evaluate(references.image_of(method.output, gb, single[v]), test, exposure)["flip"])
    return (float(np.mean(f_gt)), float(np.mean(f_single))) if f_gt else (float("nan"), float("nan"))


def strategies_for(delays, threshold: float, lease: int = DEFAULT_LEASE) -> list:
    """Full replication (delay 0) and owner-based sparse updates at every delay."""
    return [Strategy("full")] + [Strategy("sparse", int(d), float(threshold), int(lease)) for d in delays]
