"""Scenes: built-in procedural scenes, Sponza, and any Mitsuba 3 XML file.

Why one long module: Scene, CameraPath (physical speeds) and SceneBuilder are one API for
scene authors (docs/adding-a-scene.md); moving camera paths into a module of their own is the
next split when this grows.

A :class:`Scene` wraps a ``mi.Scene`` with what the experiments need on top:
animation as a function of time (:meth:`Scene.set_time`), camera paths, a
fixed exposure for tone mapping and the scene's unit (scene units per metre).

Time is physical: frame ``f`` is ``f / FPS`` seconds at ``FPS = 60``, and
camera paths move at a walking pace (``WALK_SPEED`` = 1.4 m/s) with view
turns capped at ``TURN_RATE`` = 30 deg/s (:class:`CameraPath`), so a cache
entry stays in view for as many frames as it would in a real-time session.

Built-in scene definitions live in the repository's top-level ``scenes/``
folder, one Python file per scene with a ``build(**options) -> Scene``
function (see ``docs/adding-a-scene.md``). :func:`load` resolves a name from
that folder, a path to a ``.py`` definition or a path to a ``.xml`` scene.

Animation never recompiles kernels: moving things are triangle meshes whose
``vertex_positions`` buffers are rewritten each frame (the kernels read them
from memory), never transforms baked into a kernel.
"""
from __future__ import annotations

import importlib.util
import math
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from slc.core import backend
from slc.core.spec import SpecError, parse_spec

backend.init()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from slc.scene.emitter_sampling import for_scene  # noqa: E402
from slc.scene.lights import forget  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
SCENES_DIR = REPO_ROOT / "scenes"
SHARED_DIR = REPO_ROOT.parent / "shared"
ENVMAPS_DIR = SHARED_DIR / "envmaps"

FPS = 60.0            # frames per second of every camera path and animation (the paper's real-time rate)
WALK_SPEED = 1.4      # m/s: camera speed of the built-in paths (a walking pace)
TURN_RATE = 30.0      # deg/s: fastest turn of a built-in path's view direction
SUPPORTED_EMITTERS = ("area", "point", "spot", "envmap", "constant", "directional")
# Version of what loading makes of a scene definition (today: emitter meshes made flat,
# flatten_emitter_meshes). Part of every cached reference's key (slc.reference.cache.cache_path):
# raised whenever loading changes a scene's lights or geometry, so that no reference
# computed from an older build is served.
LOAD_VERSION = 2


class SceneError(ValueError):
    """A scene cannot be loaded (one-line reason for the user)."""


# -----------------------------------------------------------------------------
# Cameras and camera paths
# -----------------------------------------------------------------------------

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


# -----------------------------------------------------------------------------
# Scene
# -----------------------------------------------------------------------------

@dataclass
class Animated:
    """A triangle mesh moved rigidly: ``transform(t)`` gives a 4x4 matrix
    applied to the rest-pose vertices (and normals) at time ``t`` (seconds)."""
    shape_id: str
    rest_positions: np.ndarray  # (V, 3)
    transform: Callable[[float], np.ndarray]
    rest_normals: np.ndarray | None = None


_WRAPPERS: dict[int, int] = {}   # live Scene objects per mi.Scene address


def _release_tables(scene_id: int) -> None:
    n = _WRAPPERS.get(scene_id, 1) - 1
    if n > 0:
        _WRAPPERS[scene_id] = n
        return
    _WRAPPERS.pop(scene_id, None)
    forget(scene_id)


class Scene:
    """A Mitsuba scene plus animation, camera paths and display settings.

    Parameters
    ----------
    name: registry name.
    mi_scene: the loaded ``mi.Scene``.
    camera_paths: at least three uncorrelated paths for built-in scenes.
    animated: rigidly moving meshes (lights or objects).
    exposure: multiplier applied before the tone map (fixed per scene so that
        every method and the ground truth are mapped alike).
    unit: scene units per metre (1.0: one scene unit is one metre; every
        built-in scene is modelled in metres). Camera paths walk at
        ``WALK_SPEED * unit`` scene units per second; stereo eyes are
        ``0.064 * unit`` apart. Paths given in other units are re-timed.
    """

    def __init__(self, name: str, mi_scene: mi.Scene, camera_paths: list[CameraPath],
                 animated: list[Animated] | None = None, exposure: float = 1.0,
                 unit: float = 1.0, description: str = "", meeting_center=None):
        self.name = name
        self.mi_scene = mi_scene
        if len(mi_scene.shapes()) == 0:
            raise SceneError(f"scene '{name}' has no shapes (only emitters): nothing to shade")
        self.camera_paths = [p if p._legacy or p.unit == unit else
                             CameraPath(p.keys, fov=p.fov, name=p.name, speed=p.speed,
                                        turn_rate=p.turn_rate, unit=unit) for p in camera_paths]
        self.animated = animated or []
        self.exposure = exposure
        self.unit = unit
        self.description = description
        self._update_bbox()
        self.meeting_center = (np.asarray(meeting_center, float) if meeting_center is not None
                               else 0.5 * (self.bbox_min + self.bbox_max))
        self.time = None
        self._params = mi.traverse(mi_scene) if self.animated else None
        check_emitters(mi_scene, name)
        check_values(mi_scene, name)
        flat = flatten_emitter_meshes(mi_scene)
        for a in self.animated:
            if a.shape_id in flat:
                a.rest_normals = None       # posed flat: set_time writes no normals back
        for_scene(mi_scene)   # the emitter table, built here: never inside a symbolic loop
        # per-scene tables (emitter table, BSDF flags) hold the scene's emitters and
        # shapes: dropped with the last Scene of this mi.Scene, so that a freed scene
        # leaves Mitsuba's registry (which every frozen function traverses)
        _WRAPPERS[id(mi_scene)] = _WRAPPERS.get(id(mi_scene), 0) + 1
        weakref.finalize(self, _release_tables, id(mi_scene))

    def _update_bbox(self) -> None:
        """Bounding box of the non-emissive geometry (far lights such as a
        moon would otherwise make the box useless for placing viewers)."""
        boxes = [sh.bbox() for sh in self.mi_scene.shapes() if not sh.is_emitter()]
        if not boxes:
            boxes = [self.mi_scene.bbox()]
        self.bbox_min = np.min([np.array(b.min, float).ravel() for b in boxes], axis=0)
        self.bbox_max = np.max([np.array(b.max, float).ravel() for b in boxes], axis=0)

    @property
    def dynamic(self) -> bool:
        return bool(self.animated)

    def shape_ids(self) -> list[str]:
        return [s.id() for s in self.mi_scene.shapes()]

    def set_time(self, t: float) -> None:
        """Pose every animated mesh at time ``t`` (seconds). Kernels are not
        recompiled: only vertex buffers change (the BVH is rebuilt)."""
        if not self.animated or self.time == t:
            self.time = t
            return
        for a in self.animated:
            M = np.asarray(a.transform(t), float)
            P = a.rest_positions @ M[:3, :3].T + M[:3, 3]
            self._params[f"{a.shape_id}.vertex_positions"] = mi.Float(P.astype(np.float32).ravel())
            if a.rest_normals is not None and f"{a.shape_id}.vertex_normals" in self._params:
                N = a.rest_normals @ np.linalg.inv(M[:3, :3]).T
                N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
                self._params[f"{a.shape_id}.vertex_normals"] = mi.Float(N.astype(np.float32).ravel())
        self._params.update()
        for_scene(self.mi_scene)   # re-read moved emissive meshes outside kernels
        self.time = t

    def set_frame(self, frame: int) -> None:
        """Pose the scene at frame ``frame`` (time ``frame / FPS``, 60 Hz)."""
        self.set_time(frame / FPS)

    def path(self, i: int) -> CameraPath:
        """Camera path ``i``; beyond the scene's own paths, a deterministic
        random path through the scene's box (seeded by ``i``)."""
        if i < len(self.camera_paths):
            return self.camera_paths[i]
        lo, hi = self.bbox_min, self.bbox_max
        ext = hi - lo
        rng = np.random.default_rng(1000 + i)
        base = self.camera_paths[0] if self.camera_paths else None
        fov = base.fov if base else 60.0
        return random_path(rng, lo + 0.2 * ext, hi - 0.2 * ext, lo + 0.3 * ext, hi - 0.3 * ext,
                           fov=fov, name=f"random{i}", unit=self.unit)


_SIGNED_BSDFS = ("BumpMap",)    # a height map and its scale are signed: finiteness only


def check_values(mi_scene: mi.Scene, name: str) -> None:
    """Raise :class:`SceneError` (one line) at the first non-finite or negative
    value of an emitter (radiance, intensity, irradiance, scale, environment
    map) or of a BSDF, textures included (a bitmap with a NaN texel). Positions
    and transforms are not values of light or reflectance and are not checked."""
    for e in mi_scene.emitters():
        if e.get_shape() is None:
            _check_params(e, name, f"emitter {_label(e, None)}", signed=False)
    seen = []
    for i, sh in enumerate(mi_scene.shapes()):
        if sh.is_emitter():
            _check_params(sh.emitter(), name, f"area light of shape {_label(sh, i)}", signed=False)
        b = sh.bsdf()
        if b is None or any(b is x for x in seen):
            continue
        seen.append(b)
        _check_params(b, name, f"BSDF {_label(b, None)} of shape {_label(sh, i)}",
                      signed=b.class_name() in _SIGNED_BSDFS)


def _label(obj, index) -> str:
    """'id' (Class), or #index (Class) for objects without an id."""
    ident = f"'{obj.id()}'" if obj.id() else (f"#{index}" if index is not None else "")
    return f"{ident} ({obj.class_name()})".strip()


def _check_params(obj, scene_name: str, what: str, signed: bool) -> None:
    params = mi.traverse(obj)
    for key in params.keys():
        v = params[key]
        if isinstance(v, float):
            a = np.array([v])
        elif isinstance(v, (mi.Float, mi.Color3f, mi.TensorXf)):
            flat = v.array if isinstance(v, mi.TensorXf) else v
            finite = bool(dr.all(dr.isfinite(flat), axis=None))
            if finite and (signed or bool(dr.all(flat >= 0.0, axis=None))):
                continue                                   # the usual case: no read-back of the data
            a = np.asarray(flat, dtype=np.float64).ravel()
        else:
            continue                                       # positions, transforms, integers
        bad = ~np.isfinite(a) if signed else ~(np.isfinite(a) & (a >= 0.0))
        if bad.any():
            x = float(a[np.argmax(bad)])
            kind = "NaN" if np.isnan(x) else ("Inf" if np.isinf(x) else f"negative value {x:g}")
            raise SceneError(f"scene '{scene_name}': {what} has {kind} in '{key}' "
                             f"(emitter, BSDF and texture values must be finite"
                             f"{'' if signed else ' and >= 0'})")


def flatten_emitter_meshes(mi_scene: mi.Scene) -> set[str]:
    """Drop the vertex normals of every triangle mesh that carries an area light,
    so that it is shaded and sampled flat; returns the ids of the meshes changed.

    Mitsuba samples a mesh emitter uniformly by area but reports the density of
    a sample, and decides which side emits, with the *interpolated* normal of a
    smooth mesh, which is not the density its samples follow: light sampling
    (and the ground truth built on it) is then biased, and the MIS weights of
    BSDF samples that hit the emitter use the same wrong density. With the
    geometric normal both are exact (docs/emitter-sampling.md)."""
    flat = set()
    for sh in mi_scene.shapes():
        if sh.is_emitter() and sh.is_mesh() and sh.has_vertex_normals():
            p = mi.traverse(sh)
            if "vertex_normals" not in p:
                continue        # a Rectangle: a Mesh to Mitsuba, flat, with no normals to drop
            p["vertex_normals"] = mi.Float()
            p.update()
            flat.add(sh.id())
    return flat


def check_emitters(mi_scene: mi.Scene, name: str) -> None:
    """Raise SceneError when the scene has no emitter or an unsupported one."""
    ems = mi_scene.emitters()
    if len(ems) == 0:
        raise SceneError(f"scene '{name}' has no emitters (direct illumination needs at least one light)")
    for e in ems:
        cls = e.class_name()
        plugin = {"AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
                  "EnvironmentMapEmitter": "envmap", "ConstantBackgroundEmitter": "constant",
                  "DirectionalEmitter": "directional"}.get(cls)
        if plugin is None:
            raise SceneError(f"scene '{name}': emitter type '{cls}' is not supported "
                             f"(supported: {', '.join(SUPPORTED_EMITTERS)})")


# -----------------------------------------------------------------------------
# Building procedural scenes
# -----------------------------------------------------------------------------

def diffuse(rgb):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(map(float, rgb))}}


def rough_conductor(roughness=0.15, material="Al", rgb=None):
    d = {"type": "roughconductor", "distribution": "ggx", "alpha": float(roughness)}
    if rgb is None:
        d["material"] = material
    else:
        d["material"] = "none"
        d["specular_reflectance"] = {"type": "rgb", "value": list(map(float, rgb))}
    return d


def principled(rgb, roughness=0.2, metallic=0.0, specular=0.5):
    return {"type": "principled", "base_color": {"type": "rgb", "value": list(map(float, rgb))},
            "roughness": float(roughness), "metallic": float(metallic), "specular": float(specular)}


class SceneBuilder:
    """Collects triangle meshes (numpy or trimesh) and lights into a scene.

    Every shape is a ``mi.Mesh`` so that it can be moved without recompiling
    kernels and re-parameterised by the on-surface cache."""

    def __init__(self, name: str):
        self.name = name
        self.shapes: dict[str, dict | mi.Mesh] = {}
        self.animated: list[Animated] = []
        self.extra: dict[str, dict] = {}
        self._n = 0

    def _id(self, prefix):
        self._n += 1
        return f"{prefix}_{self._n:03d}"

    def add_mesh(self, vertices, faces, bsdf=None, emission=None, name="mesh",
                 smooth=False, transform: Callable[[float], np.ndarray] | None = None) -> str:
        """Add a triangle mesh. ``emission`` (RGB radiance) makes it an area
        light; ``transform(t)`` animates it rigidly. Returns its shape id."""
        V = np.ascontiguousarray(vertices, dtype=np.float32)
        F = np.ascontiguousarray(faces, dtype=np.uint32)
        sid = self._id(name)
        normals = None
        if smooth:
            normals = _vertex_normals(V, F)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(bsdf if bsdf is not None else diffuse([0.5, 0.5, 0.5]))
        if emission is not None:
            props["emitter"] = mi.load_dict({"type": "area", "radiance": {
                "type": "rgb", "value": list(map(float, emission))}})
        mesh = mi.Mesh(sid, len(V), len(F), props, has_vertex_normals=smooth, has_vertex_texcoords=False)
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(V.ravel())
        p["faces"] = mi.UInt32(F.ravel())
        if smooth:
            p["vertex_normals"] = mi.Float(normals.ravel())
        p.update()
        self.shapes[sid] = mesh
        if transform is not None:
            self.animated.append(Animated(sid, V.astype(np.float64), transform,
                                          normals.astype(np.float64) if normals is not None else None))
        return sid

    def add_trimesh(self, tm, **kw) -> str:
        return self.add_mesh(np.asarray(tm.vertices), np.asarray(tm.faces), **kw)

    def add_box(self, lo, hi, **kw) -> str:
        return self.add_trimesh(box_mesh(lo, hi), **kw)

    def add_quad(self, center, u, v, **kw) -> str:
        """A rectangle ``center +- u +- v`` facing ``cross(u, v)``."""
        c, u, v = (np.asarray(a, float) for a in (center, u, v))
        V = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
        return self.add_mesh(V, np.array([[0, 1, 2], [0, 2, 3]]), **kw)

    def add_sphere(self, center, radius, subdivisions=2, **kw) -> str:
        import trimesh
        tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
        tm.apply_translation(np.asarray(center, float))
        kw.setdefault("smooth", True)
        return self.add_trimesh(tm, **kw)

    def add_cylinder(self, p0, p1, radius, sections=12, **kw) -> str:
        import trimesh
        tm = trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], float), sections=sections)
        return self.add_trimesh(tm, **kw)

    def add_point_light(self, position, intensity, name="point"):
        self.extra[self._id(name)] = {"type": "point", "position": list(map(float, position)),
                                      "intensity": {"type": "rgb", "value": list(map(float, intensity))}}

    def add_spot_light(self, position, target, intensity, cutoff_deg=30.0, name="spot"):
        T = mi.ScalarTransform4f().look_at(origin=list(map(float, position)), target=list(map(float, target)),
                                           up=[0, 1, 0] if abs(np.subtract(target, position)[1]) < 0.99 *
                                           np.linalg.norm(np.subtract(target, position)) else [1, 0, 0])
        self.extra[self._id(name)] = {"type": "spot", "to_world": T, "cutoff_angle": float(cutoff_deg),
                                      "beam_width": 0.75 * float(cutoff_deg),
                                      "intensity": {"type": "rgb", "value": list(map(float, intensity))}}

    def add_envmap(self, filename=None, scale=1.0, rgb=None, to_world=None, bitmap=None):
        if bitmap is not None:
            d = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(bitmap, np.float32)),
                 "scale": float(scale)}
            if to_world is not None:
                d["to_world"] = to_world
        elif filename is not None:
            d = {"type": "envmap", "filename": str(filename), "scale": float(scale)}
            if to_world is not None:
                d["to_world"] = to_world
        else:
            d = {"type": "constant", "radiance": {"type": "rgb", "value": list(map(float, rgb))}}
        self.extra["envmap"] = d

    def build(self, camera_paths, exposure=1.0, unit=1.0, description="", meeting_center=None) -> Scene:
        d = {"type": "scene", "integrator": {"type": "direct"}}
        d.update(self.shapes)
        d.update(self.extra)
        sc = mi.load_dict(d)
        scene = Scene(self.name, sc, camera_paths, self.animated, exposure=exposure, unit=unit,
                      description=description, meeting_center=meeting_center)
        scene.set_time(0.0)
        scene._update_bbox()  # animated meshes are now in their t = 0 pose
        return scene


def box_mesh(lo, hi):
    """A trimesh box spanning the corners ``lo`` and ``hi``."""
    import trimesh
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    tm = trimesh.creation.box(extents=hi - lo)
    tm.apply_translation(0.5 * (lo + hi))
    return tm


def merge_meshes(parts):
    """One trimesh from several (fewer shapes make a faster scene)."""
    import trimesh
    return trimesh.util.concatenate(parts)


def _vertex_normals(V, F):
    n = np.zeros_like(V, dtype=np.float64)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def translate(t):
    M = np.eye(4)
    M[:3, 3] = t
    return M


def rotate(axis, degrees):
    a = np.asarray(axis, float)
    a /= np.linalg.norm(a)
    th = math.radians(degrees)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    M = np.eye(4)
    M[:3, :3] = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
    return M


def about(center, M):
    """The transform ``M`` applied about the point ``center``."""
    return translate(center) @ M @ translate(-np.asarray(center, float))


# -----------------------------------------------------------------------------
# Registry and loading
# -----------------------------------------------------------------------------

def builtin_names() -> list[str]:
    if not SCENES_DIR.is_dir():
        return []
    return sorted(p.stem for p in SCENES_DIR.glob("*.py") if not p.stem.startswith("_"))


def describe_builtins() -> list[tuple[str, str]]:
    out = []
    for n in builtin_names():
        mod = _import_definition(SCENES_DIR / f"{n}.py")
        first = (mod.__doc__ or "").strip().splitlines()[0] if mod.__doc__ else ""
        out.append((n, first.split(":", 1)[1].strip() if first.startswith(f"{n}:") else first))
    return out


def _import_definition(path: Path):
    spec = importlib.util.spec_from_file_location(f"slc_scene_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    if not hasattr(mod, "build"):
        raise SceneError(f"scene definition {path} has no build() function")
    return mod


def parse_scene_spec(spec: str) -> tuple[str, dict]:
    """``"hangar:lights=24"`` -> ``("hangar", {"lights": "24"})``, the syntax of
    method specs (values stay strings; each scene's ``build`` converts its own)."""
    try:
        return parse_spec(spec, "scene option")
    except SpecError as e:
        raise SceneError(str(e)) from None


def load(name_or_path: str, **options) -> Scene:
    """Load a built-in scene by name, a ``.py`` definition or a ``.xml`` file.
    Built-in scenes take options in the name, like methods take settings:
    ``hangar:lights=24`` (the scene's name keeps them, so ground-truth caches
    of two variants never mix).

    Raises :class:`SceneError` with a one-line message on any problem."""
    if ":" in str(name_or_path) and Path(str(name_or_path)).suffix not in (".xml", ".py"):
        name, opts = parse_scene_spec(name_or_path)
        if name not in builtin_names():
            raise SceneError(f"unknown scene '{name}' (built-in scenes: {', '.join(builtin_names())})")
        try:
            scene = _import_definition(SCENES_DIR / f"{name}.py").build(**{**opts, **options})
        except (TypeError, ValueError) as e:
            raise SceneError(f"bad options for scene '{name_or_path}': {e}") from None
        scene.name = str(name_or_path)
        return scene
    p = Path(str(name_or_path))
    if p.suffix == ".xml":
        return load_xml(p)
    if p.suffix == ".py":
        if not p.exists():
            raise SceneError(f"scene file not found: {p}")
        return _import_definition(p).build(**options)
    if str(name_or_path) not in builtin_names():
        known = ", ".join(builtin_names())
        raise SceneError(f"unknown scene '{name_or_path}' (built-in scenes: {known}; or give a .xml path)")
    return _import_definition(SCENES_DIR / f"{name_or_path}.py").build(**options)


def load_xml(path: Path, exposure: float = 1.0, unit: float = 1.0) -> Scene:
    """Any Mitsuba 3 XML scene. Camera paths: the XML's sensor (held still)
    plus orbits around the scene's bounding box at walking speed, taking
    one scene unit for ``1 / unit`` metres (default: one metre)."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene file not found: {path}")
    try:
        # optimize=False: Mitsuba's loader otherwise merges meshes that share a
        # material and returns the merged meshes in an order that changes from
        # run to run (seen on Sponza); the cache layout, its keys and the
        # emitter table follow the shape order, so two runs with the same seed
        # gave different images. Unmerged, the shapes keep the file's order.
        sc = mi.load_file(str(path), optimize=False)
    except Exception as e:  # Mitsuba raises RuntimeError with a long message
        msg = str(e).strip().splitlines()
        last = msg[-1] if msg else type(e).__name__
        if any(w in last for w in ("lookat", "field of view", "sensor plugin")):
            # Mitsuba rejects a zero fov or a look-at whose target is its origin
            raise SceneError(f"degenerate camera in scene {path}: {last.split(': ', 1)[-1]}") from None
        raise SceneError(f"cannot parse scene {path}: {last}") from None
    check_emitters(sc, path.name)
    if len(sc.shapes()) == 0:   # (Scene checks it too; here before the sensor is read)
        raise SceneError(f"scene '{path.name}' has no shapes (only emitters): nothing to shade")
    paths = []
    bb = sc.bbox()
    lo, hi = np.array(bb.min, float).ravel(), np.array(bb.max, float).ravel()
    c, ext = 0.5 * (lo + hi), hi - lo
    if len(sc.sensors()) > 0:
        s = sc.sensors()[0]
        T = np.array(s.world_transform().matrix, float).reshape(4, 4) if hasattr(s, "world_transform") else None
        if T is not None and T.ndim == 2:
            o = T[:3, 3]
            fwd = T[:3, 2]
            fov = 60.0
            try:
                fov = float(mi.traverse(s).get("x_fov", [60.0])[0]) * 9 / 16
            except Exception:
                pass
            paths.append(CameraPath([(o, o + fwd)], fov=fov, name="sensor"))
    r = 0.6 * float(np.linalg.norm(ext))
    for k in range(3):
        keys = []
        for j in range(6):
            a = 2 * math.pi * (j / 6.0 + k / 3.0)
            keys.append((c + np.array([r * math.cos(a), 0.15 * ext[1] * (k - 1), r * math.sin(a)]), c))
        paths.append(CameraPath(keys, fov=50.0, name=f"orbit{k}", unit=unit))
    return Scene(path.stem, sc, paths, exposure=exposure, unit=unit,
                 description=f"Mitsuba XML scene {path}")
