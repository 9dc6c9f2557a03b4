"""What a run of render nodes is given (:class:`slc.distributed.node.Node`): the sharing
strategy, the viewers as their cameras per frame and their nodes, the node's cache method; and
a camera extrapolated from its last motion (latency hiding's requests ahead of the camera)."""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass

import drjit as dr
import numpy as np

from slc import methods
from slc.methods import MethodError, MethodSpec
from slc.osc.cache import OnSurfaceCache
from slc.methods.cache_method import PayloadMethod
from slc.scene.camera import Camera

INITIAL_BLOCKS = 1024      # a node's cache pool starts at 64K entries (8x8 blocks) and doubles on demand


@dataclass(frozen=True)
class Strategy:
    """How nodes share the cache: ``single`` (one node), ``independent`` (no sharing), ``full``
    (every updated record to every node) or ``sparse`` (see the module), messages ``delay``
    frames late; ``threshold``, ``lease`` (frames a subscription outlives the need),
    ``predict`` (request entries ahead of each camera), ``bootstrap`` (rays per frame a node
    spends on an entry it waits for; 0: none), ``region_level`` (the level ``T`` of the regions
    entries are owned by, :class:`slc.distributed.owners.Regions`), ``delegate`` (sparse: a new
    region is owned by a node that needs it, :mod:`slc.distributed.directory`), ``seeds`` (a new
    entry's LOD seed: ``exact``, the finest coarser entry that exists anywhere, asked of its owner
    in the frame; ``held``, the finest one its owner holds, no message; default: exact at
    threshold 0, where the records are exact too, else held)."""
    kind: str
    delay: int = 0
    threshold: float = 0.0
    lease: int = 0
    predict: bool = False
    bootstrap: int = 0
    region_level: int = 0
    delegate: bool = True
    seeds: str = ""

    def __post_init__(self):
        if not self.seeds:       # exact where the records are (threshold 0), else what the owner holds
            object.__setattr__(self, "seeds", "exact" if self.threshold <= 0 else "held")

    @property
    def sharing(self) -> bool:
        return self.kind in ("full", "sparse")

    @property
    def hiding(self) -> str:
        """Which latency hiding is on: none, predict, bootstrap or predict+bootstrap."""
        parts = [p for p, on in (("predict", self.predict), ("bootstrap", self.bootstrap > 0)) if on]
        return "+".join(parts) or "none"

    @property
    def label(self) -> str:
        s = f"{self.kind}-d{self.delay}"
        if self.kind == "sparse":
            s += f"-t{self.threshold:g}-l{self.lease}-{self.seeds}" + ("" if self.delegate else "-hashed")
        return s + ("" if self.hiding == "none" else f"-{self.hiding}")


class ViewerPoses:
    """A viewer as its camera at each frame of a run (picklable: a node in another process
    rebuilds exactly the driver's cameras). A node reads the frames up to the current one."""

    def __init__(self, name: str, cameras: dict):
        self.name, self.cameras = name, cameras

    @classmethod
    def of(cls, viewer, frames: int) -> "ViewerPoses":
        return cls(viewer.name, {f: viewer.camera(f) for f in range(frames)})

    def camera(self, frame: int) -> Camera:
        return self.cameras[int(frame)]


def extrapolated(prev: Camera, cur: Camera, ahead: float) -> Camera:
    """The camera ``ahead`` frames after ``cur`` if it keeps the motion from ``prev`` to ``cur``:
    its origin moved on along a line, its view direction turned on about the same axis."""
    o0, o1 = np.asarray(prev.origin, float), np.asarray(cur.origin, float)
    d0, d1 = np.asarray(prev.target, float) - o0, np.asarray(cur.target, float) - o1
    dist = np.linalg.norm(d1)
    a, b = d0 / max(np.linalg.norm(d0), 1e-12), d1 / max(dist, 1e-12)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    d = b
    if s > 1e-9:
        k = axis / s
        ang = ahead * np.arctan2(s, c)
        d = b * np.cos(ang) + np.cross(k, b) * np.sin(ang) + k * np.dot(k, b) * (1 - np.cos(ang))
    o = o1 + ahead * (o1 - o0)
    return Camera(o, o + d * dist, np.asarray(cur.up, float), cur.fov)


class Clock:
    """Wall and CPU time (ms) of a node's work in one frame, by part (``wall``, ``cpu``)."""

    def __init__(self):
        self.wall, self.cpu = {}, {}

    @contextmanager
    def part(self, name: str):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            dr.sync_thread()
            self.wall[name] = self.wall.get(name, 0.0) + 1e3 * (time.perf_counter() - t0)
            self.cpu[name] = self.cpu.get(name, 0.0) + 1e3 * (time.process_time() - c0)


def make_method(method: str | MethodSpec, scene, seed: int = 0) -> tuple:
    """(the cache method of a node, its cache): ``method`` (a spec, or the
    :class:`~slc.methods.MethodSpec` the driver checked and shipped: the method made from its data)
    with a pool of :data:`INITIAL_BLOCKS` that doubles on demand (the same slots as the default
    pool: blocks are mapped lowest free first). The method is made once; its cache, built from its
    settings, is given to it before its first frame."""
    if isinstance(method, MethodSpec):
        m, spec = method.create(scene, seed), method.spec
    else:
        m, spec = methods.create(method, scene, seed=seed), method
    if not isinstance(m, PayloadMethod):
        raise MethodError(f"'{spec}' keeps no cache entries to share between nodes (slc, sh, adaptive do)")
    if type(m).make_cache is PayloadMethod.make_cache:
        cache = OnSurfaceCache(scene, block_size=m.block, bias=m.bias, evict_after=m.evict_after,
                               max_blocks=INITIAL_BLOCKS)
    else:
        cache = m.make_cache()
    if cache.layout.n_vblocks * cache.layout.block_texels >= 2 ** 32:
        raise MethodError(f"'{spec}': the cache's {cache.layout.n_vblocks} blocks do not fit 32-bit entry addresses")
    m.use_cache(cache)
    return m, cache



def assignment(poses: list, n_nodes: int) -> dict:
    """Viewer ``v`` on node ``v mod n_nodes``: {node: {v: poses[v]}}."""
    return {n: {v: p for v, p in enumerate(poses) if v % n_nodes == n} for n in range(n_nodes)}
