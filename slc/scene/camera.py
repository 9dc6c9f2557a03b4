"""Cameras, camera paths and viewers.

A :class:`Camera` is a pinhole camera, a :class:`CameraPath` a keyframed path
of cameras and a :class:`Viewer` a named camera over time (the rigs of
:mod:`slc.scene.views` build lists of them).

Time is physical: frame ``f`` is ``f / FPS`` seconds at ``FPS = 60``, and
camera paths move at a walking pace (``WALK_SPEED`` = 1.4 m/s) with view
turns capped at ``TURN_RATE`` = 30 deg/s (:class:`CameraPath`), so a cache
entry stays in view for as many frames as it would in a real-time session.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slc.scene.checks import SceneError

FPS = 60.0            # frames per second of every camera path and animation (the paper's real-time rate)
WALK_SPEED = 1.4      # m/s: camera speed of the built-in paths (a walking pace)
TURN_RATE = 30.0      # deg/s: fastest turn of a built-in path's view direction


@dataclass
class Camera:
    """A pinhole camera: position, look-at target, up vector, vertical fov."""
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov: float = 60.0  # vertical field of view in degrees

    def basis(self):
        """(forward, right, up) unit vectors. A camera whose target is its
        origin (or not finite) has no view direction: :class:`SceneError`."""
        f = np.asarray(self.target, float) - np.asarray(self.origin, float)
        n = np.linalg.norm(f)
        if not (np.isfinite(n) and n > 1e-12 * max(1.0, float(np.max(np.abs(self.origin))))):
            raise SceneError(f"degenerate camera: target {_fmt(self.target)} is its origin {_fmt(self.origin)} "
                             "(no view direction)")
        f /= n
        r = np.cross(f, self.up)
        if np.linalg.norm(r) < 1e-8:  # looking along up: pick any right vector
            r = np.cross(f, [1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        return f, r, u

    def yawed(self, degrees: float) -> "Camera":
        """The same camera turned about the world up axis by ``degrees``."""
        d = np.asarray(self.target, float) - np.asarray(self.origin, float)
        return Camera(np.array(self.origin, float), np.asarray(self.origin, float) + _yaw(degrees) @ d,
                      np.array(self.up, float), self.fov)

    def orbited(self, degrees: float) -> "Camera":
        """The camera moved by ``degrees`` on a circle about the world up axis
        through its target, still looking at it."""
        t = np.asarray(self.target, float)
        return Camera(t + _yaw(degrees) @ (np.asarray(self.origin, float) - t), t.copy(),
                      np.array(self.up, float), self.fov)


def _yaw(degrees: float) -> np.ndarray:
    """Rotation about the world up axis (+y) by ``degrees``."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(x):g}" for x in np.ravel(v)) + ")"


def check_camera(keys, fov: float, name: str = "path") -> None:
    """Raise :class:`SceneError` (one line) for a camera that cannot render:
    no keys, a field of view outside (0, 180) degrees, a non-finite key, or a
    key whose target is its origin. (The up vector is fixed to +y; a view
    along it gets another right vector in :meth:`Camera.basis`, not NaN.)"""
    if not keys:
        raise SceneError(f"degenerate camera '{name}': no keys")
    if not (np.isfinite(fov) and 0.0 < float(fov) < 180.0):
        raise SceneError(f"degenerate camera '{name}': field of view {fov} deg (expected 0 < fov < 180)")
    for i, (o, t) in enumerate(keys):
        if o.shape != (3,) or t.shape != (3,) or not (np.all(np.isfinite(o)) and np.all(np.isfinite(t))):
            raise SceneError(f"degenerate camera '{name}': key {i} is not two finite 3D points")
        if np.linalg.norm(t - o) <= 1e-12 * max(1.0, float(np.max(np.abs(o)))):
            raise SceneError(f"degenerate camera '{name}': key {i} looks at its own origin {_fmt(o)}")


def _catmull_rom(p0, p1, p2, p3, t):
    t = np.asarray(t, float)[..., None] if np.ndim(t) else t
    t2, t3 = t * t, t * t * t
    return 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * t3)


@dataclass
class CameraPath:
    """Keyframed camera path, interpolated by a Catmull-Rom spline, moving
    at a physical speed.

    ``keys`` are (origin, target) pairs. The camera runs along the spline of
    the origins at ``speed`` m/s (``unit`` scene units per metre) and its
    view direction (towards the spline of the targets) turns at most
    ``turn_rate`` deg/s: each short piece of the path takes
    ``max(distance / speed, angle / turn_rate)`` seconds, so the camera walks
    at ``speed`` and slows down only where the view swings faster than the
    turn rate. Frame ``f`` is time ``f / FPS`` (60 Hz). Past its end the
    path runs back (and forth again), so every frame keeps the stated speed
    and any frame index is valid. ``duration`` is the one-way time in
    seconds, ``n_frames`` the same in frames. A viewer's camera-speed
    multiplier (:func:`slc.scene.views.at_speed`) scales the time, not the path.

    Legacy mode: with ``frames`` given, the keys are spread evenly over that
    many frames (no physical speed) and frames past the end hold the last
    pose; hand-made test paths use it.
    """
    keys: list
    frames: int | None = None
    fov: float = 60.0
    name: str = "path"
    speed: float = WALK_SPEED          # m/s
    turn_rate: float = TURN_RATE       # deg/s
    unit: float = 1.0                  # scene units per metre

    def __post_init__(self):
        self._k = [(np.asarray(o, float), np.asarray(t, float)) for o, t in self.keys]
        check_camera(self._k, self.fov, self.name)
        self._legacy = self.frames is not None
        self._table = None
        if not self._legacy:
            self._table = self._time_table()

    @property
    def n_frames(self) -> int:
        """Frames from the first key to the last (one way) at 1x speed."""
        return self.frames if self._legacy else int(math.ceil(self.duration * FPS)) + 1

    # ------------------------------------------------------------------ spline
    def _spline(self, s):
        """(origin, target) at spline parameter(s) ``s`` in [0, len(keys) - 1]."""
        k = self._k
        n = len(k)
        s = np.clip(np.asarray(s, float), 0.0, n - 1)
        i = np.minimum(s.astype(int), n - 2)
        t = s - i
        idx = [np.maximum(i - 1, 0), i, i + 1, np.minimum(i + 2, n - 1)]
        O = np.stack([o for o, _ in k])
        G = np.stack([g for _, g in k])
        o = _catmull_rom(*[O[j] for j in idx], t)
        g = _catmull_rom(*[G[j] for j in idx], t)
        return o, g

    def _time_table(self, samples_per_key: int = 256):
        """Spline parameter -> time (s) at walking speed with the turn cap."""
        if len(self._k) == 1:
            return np.array([0.0]), np.array([0.0])
        s = np.linspace(0.0, len(self._k) - 1, samples_per_key * (len(self._k) - 1) + 1)
        o, g = self._spline(s)
        d = g - o
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        ds = np.linalg.norm(np.diff(o, axis=0), axis=1) / (self.speed * self.unit)
        cr = np.linalg.norm(np.cross(d[:-1], d[1:]), axis=1)
        ang = np.arctan2(cr, np.sum(d[:-1] * d[1:], axis=1))  # robust for tiny angles
        dth = ang / math.radians(self.turn_rate)
        t = np.concatenate([[0.0], np.cumsum(np.maximum(ds, dth))])
        return t, s

    @property
    def duration(self) -> float:
        """Seconds from the first key to the last (one way)."""
        if self._legacy:
            return (self.frames - 1) / FPS
        return float(self._table[0][-1])

    def length(self) -> float:
        """Length of the camera's route in metres (one way)."""
        if len(self._k) == 1:
            return 0.0
        s = np.linspace(0.0, len(self._k) - 1, 256 * (len(self._k) - 1) + 1)
        o, _ = self._spline(s)
        return float(np.sum(np.linalg.norm(np.diff(o, axis=0), axis=1))) / self.unit

    # ------------------------------------------------------------------ poses
    def at(self, frame: float) -> Camera:
        """The camera at frame ``frame`` (time ``frame / FPS``)."""
        if len(self._k) == 1:
            return Camera(self._k[0][0].copy(), self._k[0][1].copy(), fov=self.fov)
        if self._legacy:
            s = min(max(frame, 0.0), self.frames - 1) / max(self.frames - 1, 1) * (len(self._k) - 1)
        else:
            T, S = self._table
            t = max(float(frame), 0.0) / FPS
            if T[-1] > 0:
                t = t % (2 * T[-1])
                t = t if t <= T[-1] else 2 * T[-1] - t      # back and forth
            s = float(np.interp(t, T, S))
        o, g = self._spline(s)
        return Camera(np.asarray(o, float).ravel(), np.asarray(g, float).ravel(), fov=self.fov)


def random_path(rng: np.random.Generator, lo, hi, look_lo, look_hi, n_keys=5,
                fov=60.0, name="random", unit=1.0) -> CameraPath:
    """A smooth path at walking speed through ``n_keys`` random points of the
    box [lo, hi], looking at random points of [look_lo, look_hi]."""
    lo, hi, look_lo, look_hi = map(lambda a: np.asarray(a, float), (lo, hi, look_lo, look_hi))
    keys = [(rng.uniform(lo, hi), rng.uniform(look_lo, look_hi)) for _ in range(n_keys)]
    return CameraPath(keys, fov=fov, name=name, unit=unit)


@dataclass
class Viewer:
    """A named camera over time. ``speed`` is the camera-speed multiplier:
    frame ``f`` shows the pose the path has at ``f * speed`` (1.0: the
    path's own walking speed at 60 Hz). The scene's own animation (lights,
    objects) is not affected."""
    name: str
    pose: Callable[[float], Camera]
    rig: str = "single"
    speed: float = 1.0

    def camera(self, frame: float) -> Camera:
        return self.pose(frame * self.speed)
