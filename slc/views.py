"""Viewers and viewer rigs.

A :class:`Viewer` maps a frame index to a :class:`~slc.scenes.Camera`. Rigs
build lists of viewers:

- :func:`single`: one viewer on one of the scene's camera paths;
- :func:`independent`: N viewers on N uncorrelated paths;
- :func:`overlap_rig`: N viewers sharing one position (path 0), fanned out by
  yaw offsets chosen so that adjacent views overlap by a target fraction of
  the screen (the measured overlap is reported by the experiments);
- :func:`stereo`: pairs of viewers 6.4 cm apart (in scene units);
- :func:`meeting`: N viewers on a circle looking at a common centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .scenes import Camera, Scene

INTEROCULAR_M = 0.064
RIGS = ("single", "random", "overlap", "stereo", "meeting")


@dataclass
class Viewer:
    name: str
    pose: Callable[[float], Camera]
    rig: str = "single"

    def camera(self, frame: float) -> Camera:
        return self.pose(frame)


def single(scene: Scene, path: int = 0) -> list[Viewer]:
    p = scene.path(path)
    return [Viewer(f"{p.name}", p.at, "single")]


def independent(scene: Scene, n: int, first_path: int = 0) -> list[Viewer]:
    """N viewers on uncorrelated paths (the scene's own, then random ones)."""
    out = []
    for i in range(n):
        p = scene.path(first_path + i)
        out.append(Viewer(f"v{i:02d}-{p.name}", p.at, "random"))
    return out


def random_viewers(scene: Scene, n: int, frames: int = 64, seed: int = 0) -> list[Viewer]:
    """N viewers on uncorrelated random paths through the scene's box that
    all start looking at ``scene.meeting_center`` (the paper's Fig. 12 set-up)."""
    from .scenes import CameraPath
    lo, hi = scene.bbox_min, scene.bbox_max
    ext = hi - lo
    c = np.asarray(scene.meeting_center, float)
    out = []
    for i in range(n):
        rng = np.random.default_rng(10_000 + 97 * seed + i)
        keys = []
        for k in range(5):
            o = rng.uniform(lo + 0.15 * ext, hi - 0.15 * ext)
            o[1] = rng.uniform(lo[1] + 0.08 * ext[1], lo[1] + 0.35 * ext[1])
            t = c if k == 0 else rng.uniform(lo + 0.25 * ext, hi - 0.25 * ext)
            keys.append((o, t))
        p = CameraPath(keys, frames=frames, fov=scene.path(0).fov, name=f"rnd{i}")
        out.append(Viewer(f"r{i:02d}", p.at, "random"))
    return out


def measure_overlap(gbuffers) -> float:
    """Percent of surface cells seen by more than one viewer, among all cells
    seen by anyone. A cell is the hit position quantised to the median pixel
    footprint, so the figure is comparable across methods (cache methods also
    report the overlap of their own entries)."""
    if len(gbuffers) < 2:
        return 0.0
    keys, foot = [], []
    for gb in gbuffers:
        v = np.array(gb.valid, bool)
        f = np.array(gb.footprint, np.float64)[v]
        if f.size:
            foot.append(np.median(f))
    cell = max(float(np.median(foot)) if foot else 1.0, 1e-6)
    for gb in gbuffers:
        v = np.array(gb.valid, bool)
        p = np.array(gb.si.p, np.float64)
        p = (p.T if p.shape[0] == 3 else p)[v]
        q = np.floor(p / cell).astype(np.int64)
        k = (q[:, 0] * 73856093) ^ (q[:, 1] * 19349663) ^ (q[:, 2] * 83492791)
        keys.append(np.unique(k))
    allk = np.concatenate(keys)
    _, counts = np.unique(allk, return_counts=True)
    return 100.0 * float(np.mean(counts > 1)) if counts.size else 0.0


def horizontal_fov(vfov_deg: float, aspect: float) -> float:
    return math.degrees(2 * math.atan(math.tan(math.radians(vfov_deg) / 2) * aspect))


def overlap_rig(scene: Scene, n: int, overlap: float, aspect: float = 16 / 9,
                path: int = 0) -> list[Viewer]:
    """N viewers at one position; viewer i is turned by ``i * (1 - overlap) * hfov``
    about the up axis (alternating left/right), so neighbouring views share
    about ``overlap`` (0..1) of the screen. Overlap 1 gives N identical views."""
    p = scene.path(path)
    hfov = horizontal_fov(p.fov, aspect)
    step = (1.0 - overlap) * hfov
    out = []
    for i in range(n):
        k = (i + 1) // 2 * (1 if i % 2 else -1)  # 0, +1, -1, +2, -2, ...
        out.append(Viewer(f"o{i:02d}", (lambda f, k=k: p.at(f).yawed(k * step)), "overlap"))
    return out


def stereo(scene: Scene, pairs: int, first_path: int = 0, ipd_m: float = INTEROCULAR_M) -> list[Viewer]:
    """``pairs`` stereo pairs (2 * pairs viewers), pair k on path k; the eyes
    sit +-ipd/2 along the camera's right vector."""
    half = 0.5 * ipd_m * scene.unit
    out = []
    for k in range(pairs):
        p = scene.path(first_path + k)
        for side, s in (("L", -1.0), ("R", 1.0)):
            def pose(f, p=p, s=s):
                c = p.at(f)
                _, r, _ = c.basis()
                off = s * half * r
                return Camera(c.origin + off, c.target + off, c.up, c.fov)
            out.append(Viewer(f"s{k:02d}{side}", pose, "stereo"))
    return out


def meeting(scene: Scene, n: int, radius: float | None = None, height: float | None = None,
            fov: float = 50.0) -> list[Viewer]:
    """N viewers evenly on a horizontal circle around ``scene.meeting_center``,
    all looking at it (the abstract's shared-cloud case)."""
    c = np.asarray(scene.meeting_center, float)
    ext = scene.bbox_max - scene.bbox_min
    r = radius if radius is not None else 0.2 * float(min(ext[0], ext[2]))
    h = height if height is not None else 0.1 * float(ext[1])
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        o = c + np.array([r * math.cos(a), h, r * math.sin(a)])
        out.append(Viewer(f"m{i:02d}", (lambda f, o=o: Camera(o.copy(), c.copy(), fov=fov)), "meeting"))
    return out


def make_rig(scene: Scene, rig: str, viewers: int, overlap: float = 1.0) -> list[Viewer]:
    """Dispatch by rig name; ``viewers`` counts images (stereo: 2 per pair)."""
    if rig == "single":
        return single(scene) if viewers == 1 else independent(scene, viewers)
    if rig == "random":
        return random_viewers(scene, viewers)
    if rig == "overlap":
        return overlap_rig(scene, viewers, overlap)
    if rig == "stereo":
        return stereo(scene, max(viewers // 2, 1))
    if rig == "meeting":
        return meeting(scene, viewers)
    raise ValueError(f"unknown rig '{rig}' (choose one of {', '.join(RIGS)})")
