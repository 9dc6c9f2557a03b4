"""Viewer rigs.

A :class:`~slc.scene.camera.Viewer` maps a frame index to a
:class:`~slc.scene.camera.Camera`. Rigs build lists of viewers:

- :func:`single`: one viewer on one of the scene's camera paths;
- :func:`independent`: N viewers on N uncorrelated paths;
- :func:`~slc.scene.random_walks.random_viewers`: N viewers on uncorrelated random walks from
  different start points, all first looking towards the scene's centre;
- :func:`overlap_rig`: N viewers sharing one position (path 0), fanned out by
  yaw offsets chosen so that the share of the visible surface seen by more
  than one viewer is a target (narrowing the views when the fan would wrap
  around the circle);
- :func:`stereo`: pairs of viewers 6.4 cm apart (in scene units);
- :func:`meeting`: N viewers on a circle looking at a common centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.camera import Camera, Viewer
from slc.scene.checks import SceneError
from slc.scene.gbuffer import render_gbuffer
from slc.scene.random_walks import random_viewers
from slc.scene.scenes import Scene

INTEROCULAR_M = 0.064
RIGS = ("single", "random", "overlap", "stereo", "meeting")


def at_speed(viewers: list[Viewer], speed: float) -> list[Viewer]:
    """The same viewers moving ``speed`` times as fast along their paths
    (0.25-4 in the camera-speed experiment)."""
    if not speed > 0:
        raise ValueError(f"camera speed must be positive, got {speed}")
    return [replace(v, speed=v.speed * float(speed)) for v in viewers]


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


CALIBRATION_RES = (64, 36)          # G-buffer size used to calibrate the overlap rig
CALIBRATION_FRAMES = (0, 60, 120)   # frames (0, 1 and 2 s into the path) averaged by the calibration
_CALIBRATED: dict = {}


def vertical_fov(hfov_deg: float, aspect: float) -> float:
    return math.degrees(2 * math.atan(math.tan(math.radians(hfov_deg) / 2) / aspect))


def _fan(p, n: int, step: float, aspect: float, pivot: str = "eye"):
    """Viewers of a fan turned by ``step`` screen widths each (viewer 0 on
    the path's heading, then alternately right and left); fields of view
    narrowed when the fan would span more than 360 degrees. ``pivot="eye"``
    turns each view about its own position; ``"target"`` moves the eye on a
    circle about the up axis through the path's look-at point, every viewer
    looking at it (the views beyond 90 degrees see the box from behind);
    ``"tile"``: see :func:`_tiles`."""
    hfov = horizontal_fov(p.fov, aspect)
    span = 1.0 + (n - 1) * step
    fov = p.fov
    if hfov * span > 360.0:
        hfov = 360.0 / span
        fov = vertical_fov(hfov, aspect)
    yaw = step * hfov
    turn = Camera.orbited if pivot == "target" else Camera.yawed
    out = []
    for i in range(n):
        k = (i + 1) // 2 * (1 if i % 2 else -1)  # 0, +1, -1, +2, -2, ...
        out.append(Viewer(f"o{i:02d}", (lambda f, k=k, turn=turn: _with_fov(turn(p.at(f), k * yaw), fov)),
                          "overlap"))
    return out


@dataclass(frozen=True)
class Window:
    """A rectangle of a camera's view in tangent units of its basis (x right, y up):
    ``x0 <= x <= x1``, ``y0 <= y <= y1``."""
    x0: float
    x1: float
    y0: float
    y1: float


def _scene_window(scene: Scene, p) -> Window:
    """The part of the path's first view that shows the front of a surface
    (:class:`Window`), from a G-buffer at ``CALIBRATION_RES``."""
    cam = p.at(0)
    w, h = CALIBRATION_RES
    gb = render_gbuffer(scene, cam, w, h, None, "window")
    front = np.array(gb.valid) & (np.array(mi.Frame3f.cos_theta(gb.si.wi)) > 0.0)
    if not np.any(front):
        raise SceneError(f"scene {scene.name!r}: its first camera sees no surface from the front")
    f, r, u = cam.basis()
    d = np.array(gb.si.p).T[front] - np.asarray(cam.origin, float)
    z = d @ f
    x, y = (d @ r) / z, (d @ u) / z
    return Window(float(x.min()), float(x.max()), float(y.min()), float(y.max()))


def _tiles(p, n: int, step: float, aspect: float, window: Window):
    """Viewers at the path's position, each aimed at a tile of ``window``, what
    its camera sees of the scene (:func:`_scene_window`): a grid of ceil(sqrt(n)) columns,
    tiles of the render's aspect as large as fit ``1 + (k - 1) step`` tiles
    across the window on both axes, centres ``step`` tiles apart (step 0: n
    identical views of the whole window; 1: adjacent tiles). For a camera
    outside the scene (the cornell box seen through its open side) every view
    looks into the box at the front of its walls. Viewer 0 holds the tile
    nearest the window's centre."""
    x0, x1, y0, y1 = window.x0, window.x1, window.y0, window.y1
    cols = int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / cols))
    tw = min((x1 - x0) / (1.0 + (cols - 1) * step), (y1 - y0) * aspect / (1.0 + (rows - 1) * step))
    th = tw / aspect
    mx, my = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    cells = [(mx + (c - 0.5 * (cols - 1)) * step * tw, my + (r - 0.5 * (rows - 1)) * step * th)
             for r in range(rows) for c in range(cols)]
    cells.sort(key=lambda q: (q[0] - mx) ** 2 + (q[1] - my) ** 2)
    fov = math.degrees(2.0 * math.atan(0.5 * th))

    def aimed(f, cx, cy):
        cam = p.at(f)
        fw, r, u = cam.basis()
        o = np.asarray(cam.origin, float)
        return Camera(o.copy(), o + fw + cx * r + cy * u, np.array(cam.up, float), fov)

    return [Viewer(f"o{i:02d}", (lambda f, cx=cx, cy=cy: aimed(f, cx, cy)), "overlap")
            for i, (cx, cy) in enumerate(cells[:n])]


def fan_pivot(scene: Scene, path: int = 0) -> str:
    """``"tile"`` when the path's first camera is outside the scene's
    bounding box (it looks at the scene from outside: turning it about its eye
    would look away from everything, and orbiting it about the look-at point
    (``"target"``) shows the box's walls from behind in more than half of 16
    views), else ``"eye"``."""
    o = np.asarray(scene.path(path).at(0).origin, float)
    inside = bool(np.all(o >= scene.bbox_min) and np.all(o <= scene.bbox_max))
    return "eye" if inside else "tile"


def _rig(p, n: int, step: float, aspect: float, pivot: str, window: Window | None = None):
    """The views of a fan (:func:`_fan`) or, with ``pivot="tile"``, of tiles of ``window``
    (:func:`_tiles`)."""
    return _tiles(p, n, step, aspect, window) if pivot == "tile" else _fan(p, n, step, aspect, pivot)


def _fan_overlap(scene: Scene, p, n: int, step: float, aspect: float, pivot: str = "eye",
                 window: Window | None = None) -> float:
    """Mean measured overlap of a fan over ``CALIBRATION_FRAMES``."""
    w, h = CALIBRATION_RES
    w = max(int(round(h * aspect)), 1)
    vs = _rig(p, n, step, aspect, pivot, window)
    m = []
    for f in CALIBRATION_FRAMES:
        scene.set_frame(f)
        m.append(measure_overlap([render_gbuffer(scene, v.camera(f), w, h, None, v.name) for v in vs]))
    return float(np.mean(m))


def calibrated_step(scene: Scene, n: int, overlap: float, aspect: float = 16 / 9, path: int = 0,
                    iterations: int = 8, pivot: str = "eye") -> tuple[float, float]:
    """(step, measured overlap %) of a fan of ``n`` views whose measured
    overlap is closest to ``overlap`` (0..1): bisection over the step in
    screen widths (0: identical views, 1: adjacent screens), measured with
    :func:`measure_overlap` at ``CALIBRATION_RES`` on ``CALIBRATION_FRAMES``.
    Cached per (scene, path, n, overlap, aspect)."""
    if n < 2 or overlap >= 1.0:
        return 0.0, 100.0 if n >= 2 else 0.0
    key = (scene.name, path, n, round(float(overlap), 4), round(float(aspect), 4), pivot)
    if key in _CALIBRATED:
        return _CALIBRATED[key]
    p = scene.path(path)
    target = 100.0 * max(float(overlap), 0.0)
    window = _scene_window(scene, p) if pivot == "tile" else None      # rendered once per calibration
    best = (1.0, _fan_overlap(scene, p, n, 1.0, aspect, pivot, window))
    if target > best[1]:
        a, b = 0.0, 1.0      # measured overlap falls as the step grows
        for _ in range(iterations):
            m = 0.5 * (a + b)
            got = _fan_overlap(scene, p, n, m, aspect, pivot, window)
            if abs(got - target) < abs(best[1] - target):
                best = (m, got)
            if got > target:
                a = m
            else:
                b = m
    _CALIBRATED[key] = best
    return best


def overlap_rig(scene: Scene, n: int, overlap: float, aspect: float = 16 / 9,
                path: int = 0, pivot: str = "eye") -> list[Viewer]:
    """N viewers at one position on path ``path``, fanned out about the up
    axis so that the share of the visible surface seen by more than one of
    them (:func:`measure_overlap`) is ``overlap`` (0..1).

    Viewer 0 looks along the path, the others are turned by ``k * step *
    hfov`` (k = +1, -1, +2, -2, ...). The step is calibrated
    (:func:`calibrated_step`): screen overlap is not surface overlap (a
    turned view samples a shared far wall at other points, near and far
    surfaces hold different numbers of cells), so a fixed formula missed
    the targets by 10-40 points; the bisection on the measured figure at a
    small resolution hits them within a few. Overlap 0 is a fan of
    adjacent screens, overlap 1 N identical views. A fan must not wrap
    around the circle (16 views of 92 degrees side by side would cover it
    four times and measure 75% at target 0%), so when ``hfov * (1 + (n - 1)
    step)`` exceeds 360 degrees every view's field of view is narrowed to
    fit (16 viewers at 0%: 22.5 degrees wide). The resolution, and with it
    the pixels and cache requests per viewer, is unchanged.

    ``pivot`` (see :func:`_fan`): ``"eye"`` (default), ``"target"`` or
    ``"tile"``; ``"auto"`` picks by :func:`fan_pivot` (the cornell box's camera
    is outside the box: a fan about its eye left 11 of 16 views empty, one
    about the look-at point showed 9 of 16 views only the back of the walls)."""
    if pivot == "auto":
        pivot = fan_pivot(scene, path)
    step, _ = calibrated_step(scene, n, overlap, aspect, path, pivot=pivot)
    p = scene.path(path)
    return _rig(p, n, step, aspect, pivot, _scene_window(scene, p) if pivot == "tile" else None)


def _with_fov(c: Camera, fov: float) -> Camera:
    c.fov = fov
    return c


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
    all looking at it (the abstract's shared-cloud case). A position inside
    geometry (:func:`inside_geometry`: the atrium's columns held 2 of 16) is
    moved along the circle, by up to half the spacing, to the nearest free one."""
    c = np.asarray(scene.meeting_center, float)
    ext = scene.bbox_max - scene.bbox_min
    r = radius if radius is not None else 0.2 * float(min(ext[0], ext[2]))
    h = height if height is not None else 0.1 * float(ext[1])
    spacing = 2 * math.pi / max(n, 1)

    def at(a):
        return c + np.array([r * math.cos(a), h, r * math.sin(a)])

    shifts = [0.0] + [s * k * spacing / 16 for k in range(1, 9) for s in (1, -1)]
    out = []
    for i in range(n):
        ring = [at(spacing * i + d) for d in shifts]
        o = next((p for p in ring if not inside_geometry(scene, p)), ring[0])
        out.append(Viewer(f"m{i:02d}", (lambda f, o=o: Camera(o.copy(), c.copy(), fov=fov)), "meeting"))
    return out


def inside_geometry(scene: Scene, p, n_dirs: int = 64) -> bool:
    """Whether point ``p`` is enclosed by geometry: more than half of
    ``n_dirs`` fixed directions hit a surface from its back side."""
    d = np.random.default_rng(7).normal(size=(n_dirs, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(np.asarray(p, float), d.shape)
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k]) for k in range(3)]))
    si = scene.mi_scene.ray_intersect(ray)
    back = si.is_valid() & (dr.dot(si.n, ray.d) > 0)
    return int(np.count_nonzero(np.array(back))) > n_dirs // 2


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
