"""Render nodes as Ray actors: one process per node, each holding the scene and a
:class:`~slc.distributed.node.Node`; :class:`RayNodes` is the transport of
:class:`slc.distributed.cluster.Cluster` that calls them.

An actor process sets Dr.Jit's thread count (``threads``: by default the machine's cores over
the local nodes, at least 1), loads the scene once and builds a new node for every run
(:meth:`NodeActor.start`), so that a sequence of runs (the strategies of ``slc run
distributed``) pays the scene load and the kernel builds once per process.
"""
from __future__ import annotations

import os
from pathlib import Path

import drjit as dr
import mitsuba as mi
import ray

from slc.core import backend
from slc.distributed.cluster import DEAD, Cluster
from slc.distributed.node import Node
from slc.distributed.rig import Strategy, ViewerPoses, assignment
from slc.methods import MethodSpec
from slc.methods.frames import Frame, FrameLoop
from slc.reference.references import image_of
from slc.scene import gbuffer as gbuf
from slc.scene import scenes

ROOT = str(Path(__file__).resolve().parents[2])


@ray.remote(max_restarts=0, max_task_retries=0)
class NodeActor:
    """A render node's process (see the module)."""

    def __init__(self, scene: str, threads: int | None = None):
        if threads:
            dr.set_thread_count(int(threads))
        self.scene = scenes.load(scene)
        self.node = None

    def pid(self) -> int:
        return os.getpid()

    def start(self, node: int, live: list, method, viewers: dict, width: int, height: int, strategy,
              seed: int = 0) -> int:
        """A new :class:`~slc.distributed.node.Node` of the cache method ``method`` (a spec, or the
        driver's :class:`~slc.methods.MethodSpec`: the node makes the method from its data); the
        last node's state dropped; its pid."""
        self.node = None
        self.node = Node(node, live, self.scene, method, viewers, width, height, strategy, seed)
        return os.getpid()

    def call(self, phase: str, *args):
        return getattr(self.node, phase)(*args)

    def drop(self, dead: int, live_before: list) -> None:
        self.node.drop(dead, live_before)


class RayNodes:
    """The transport of :class:`~slc.distributed.cluster.Cluster` over :class:`NodeActor` handles
    ({node: actor}); a node whose process died answers DEAD."""

    def __init__(self, actors: dict):
        self.actors = dict(actors)

    def call(self, phase: str, args: dict) -> dict:
        refs = {n: self.actors[n].call.remote(phase, *a) for n, a in args.items() if n in self.actors}
        out = {n: DEAD for n in args if n not in self.actors}
        for n, ref in refs.items():
            try:
                out[n] = ray.get(ref)
            except ray.exceptions.RayActorError:
                self.actors.pop(n, None)
                out[n] = DEAD
        return out

    def kill(self, node: int) -> None:
        """End node ``node``'s process (as a crash would)."""
        ray.kill(self.actors[node], no_restart=True)

    def drop(self, dead: int, live_before: list, survivors: list) -> None:
        self.actors.pop(dead, None)
        ray.get([self.actors[n].drop.remote(dead, live_before) for n in survivors if n in self.actors])


def worker_env() -> dict:
    """What a node's process needs of this one: the Mitsuba variant, the reference cache, this
    checkout first on the path."""
    env = {"SLC_VARIANT": backend.variant(),
           "PYTHONPATH": os.pathsep.join([ROOT] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                   if p and p != ROOT])}
    if os.environ.get("SLC_CACHE"):
        env["SLC_CACHE"] = os.environ["SLC_CACHE"]
    return env


def start_ray(cpus: int, address: str | None = None) -> bool:
    """Connect to the Ray cluster at ``address``, or start a local instance of ``cpus`` CPUs
    (never another process's instance on this machine; workers at nice 0,
    :data:`slc.core.backend.RAY_SYSTEM_CONFIG`). Returns whether this call started Ray (the
    caller shuts it down)."""
    if ray.is_initialized():
        return False
    kw = dict(include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": worker_env()})
    if address:
        ray.init(address=address, **kw)
    else:
        ray.init(address="local", num_cpus=cpus, _system_config=backend.RAY_SYSTEM_CONFIG, **kw)
    return True


def node_actors(scene: str, n: int, threads: int | None = None) -> list:
    """``n`` :class:`NodeActor` processes holding ``scene`` (spread over the cluster's machines),
    started and ready."""
    actors = [NodeActor.options(num_cpus=1, scheduling_strategy="SPREAD").remote(scene, threads)
              for _ in range(n)]
    ray.get([a.pid.remote() for a in actors])
    return actors


def render_on_nodes(scene, scene_name: str, method: MethodSpec, viewers: list, n_nodes: int, width: int,
                    height: int, frames: int, threshold: float, lease: int, seed: int = 0,
                    address: str | None = None) -> dict:
    """Render ``frames`` frames of ``viewers`` on ``n_nodes`` :class:`NodeActor` processes (viewer
    v on node v mod K) with sparse owner updates at ``threshold`` and delay 0 (``slc render
    --nodes``): on a local Ray instance, or on the cluster at ``address``. ``method``: the cache
    method's spec checked by the caller (:func:`slc.methods.parse`), shipped to every node, which
    makes the method from it. The frames are walked by the frame loop
    (:class:`slc.methods.frames.FrameLoop`), a frame a :meth:`Cluster.step`. Returns the last
    frame's images (viewer index -> HxWx3, composed as the pipeline composes the method's
    ``output``; ``scene`` is the driver's copy, for the G-buffers), the bytes sent per frame
    (the protocol's count and pickled) and the nodes' pids. Ray is shut down afterwards if this
    call started it."""
    own = start_ray(n_nodes, address)
    try:
        actors = dict(enumerate(node_actors(scene_name, n_nodes, max((os.cpu_count() or 1) // n_nodes, 1))))
        assign = assignment([ViewerPoses.of(v, frames) for v in viewers], n_nodes)
        live = sorted(assign)
        st = Strategy("sparse", 0, float(threshold), int(lease))
        pids = ray.get([actors[n].start.remote(n, live, method, assign[n], width, height, st, seed) for n in live])
        cluster = Cluster(RayNodes(actors), live, 0)
        sent, pickled, images = [], [], {}

        def done(fr: Frame, out: dict) -> None:
            sent.append(out["bytes"])
            pickled.append(out["serialized"])
            if fr.evaluated:          # the last frame's images, composed on the driver's G-buffers
                gbs = gbuf.frame_gbuffers(scene, viewers, fr.number, width, height)
                for r in out["results"].values():
                    for v, img in r["images"].items():
                        images[v] = image_of(method.output, gbs[v], mi.Color3f(img))
        FrameLoop(frames, evaluated=frozenset({frames - 1})).run(
            lambda fr: cluster.step(fr.number, images=fr.evaluated), done)
        return {"images": images, "bytes_per_frame": sent, "serialized_bytes_per_frame": pickled,
                "processes": len(set(pids))}
    finally:
        if own:
            ray.shutdown()
