"""Scenes: built-in procedural scenes, Sponza, and any Mitsuba 3 XML file.

A :class:`Scene` wraps a ``mi.Scene`` with what the experiments need on top:
animation as a function of time (:meth:`Scene.set_time`), camera paths
(:mod:`slc.scene.camera`), a fixed exposure for tone mapping and the scene's
unit (scene units per metre).

Built-in scene definitions live in the repository's top-level ``scenes/``
folder, one Python file per scene with a ``build(**options) -> Scene``
function (see ``docs/adding-a-scene.md``; :mod:`slc.scene.builder` builds
them). :func:`load` resolves a name from that folder, a path to a ``.py``
definition or a path to a ``.xml`` scene.

Animation never recompiles kernels: moving things are triangle meshes whose
``vertex_positions`` buffers are rewritten each frame (the kernels read them
from memory), never transforms baked into a kernel.
"""
from __future__ import annotations

import importlib.util
import inspect
import math
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from slc.core import backend
from slc.core.spec import parse_spec

backend.init()
import mitsuba as mi  # noqa: E402

from slc.core.freeze import device_array  # noqa: E402

from slc.scene import instances  # noqa: E402
from slc.scene.camera import FPS, CameraPath, random_path  # noqa: E402
from slc.scene.checks import SceneError, check_emitters, check_values  # noqa: E402
from slc.scene.emitter_sampling import for_scene  # noqa: E402
from slc.scene.lights import forget  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
SCENES_DIR = REPO_ROOT / "scenes"
SHARED_DIR = REPO_ROOT.parent / "shared"
ENVMAPS_DIR = SHARED_DIR / "envmaps"

# Version of what loading makes of a scene definition (today: emitter meshes made flat,
# flatten_emitter_meshes). Part of every cached reference's key (slc.reference.cache.cache_path):
# raised whenever loading changes a scene's lights or geometry, so that no reference
# computed from an older build is served.
LOAD_VERSION = 2


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
            # in memory Dr.Jit allocates: frozen functions replay on the new buffer
            # (slc.core.freeze, "Host data that changes between calls")
            self._params[f"{a.shape_id}.vertex_positions"] = device_array(mi.Float, P.astype(np.float32).ravel())
            if a.rest_normals is not None and f"{a.shape_id}.vertex_normals" in self._params:
                N = a.rest_normals @ np.linalg.inv(M[:3, :3]).T
                N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
                self._params[f"{a.shape_id}.vertex_normals"] = device_array(mi.Float, N.astype(np.float32).ravel())
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


def scene_options(definition) -> tuple:
    """The options a built-in scene's name may carry: its ``build``'s named parameters and its
    module's ``OPTIONS`` (the options its ``build`` reads from ``**options``)."""
    params = inspect.signature(definition.build).parameters.values()
    named = tuple(p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY))
    return named + tuple(o for o in getattr(definition, "OPTIONS", ()) if o not in named)


def load(name_or_path: str, **options) -> Scene:
    """Load a built-in scene by name, a ``.py`` definition or a ``.xml`` file.
    Built-in scenes take options in the name, like methods take settings:
    ``hangar:lights=24`` (the scene's name keeps them, so ground-truth caches
    of two variants never mix).

    Raises :class:`SceneError` with a one-line message on any problem."""
    with backend.exr_pool():     # EXR textures and environment maps (and files a builder writes)
        return _load(name_or_path, **options)


def _load(name_or_path: str, **options) -> Scene:
    if ":" in str(name_or_path) and Path(str(name_or_path)).suffix not in (".xml", ".py"):
        name, opts = parse_spec(name_or_path, "scene option", SceneError)  # values stay strings
        if name not in builtin_names():
            raise SceneError(f"unknown scene '{name}' (built-in scenes: {', '.join(builtin_names())})")
        definition = _import_definition(SCENES_DIR / f"{name}.py")
        known = scene_options(definition)
        unknown = [k for k in opts if k not in known]
        if unknown:
            raise SceneError(f"unknown option '{unknown[0]}' for scene '{name}' "
                             f"(its options: {', '.join(known) if known else 'none'})")
        try:
            scene = definition.build(**{**opts, **options})
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


def load_xml_text(name: str, text: str, camera_paths: list[CameraPath], files: dict | None = None,
                  exposure: float = 1.0, unit: float = 1.0, description: str = "") -> Scene:
    """A built-in scene written as Mitsuba 3 XML, the way exporters write scenes (shapes and
    lights placed by 4x4 matrices, two-sided materials, ...): ``text`` is loaded as a file
    (mesh merging off, as :func:`load_xml`) beside ``files`` (file name -> function that
    writes it to the path it is given: an environment map's image), all in a temporary
    folder removed once loaded."""
    tmp = Path(tempfile.mkdtemp(prefix=f"slc-{name}-"))
    try:
        for fname, write in (files or {}).items():
            write(tmp / fname)
        (tmp / f"{name}.xml").write_text(instances.expand(text))
        sc = mi.load_file(str(tmp / f"{name}.xml"), optimize=False)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return Scene(name, sc, camera_paths, exposure=exposure, unit=unit, description=description)


def xml_matrix(M) -> str:
    """A 4x4 matrix as the ``value`` of an XML ``<matrix>`` (row-major)."""
    return " ".join(f"{float(v):.9g}" for v in np.asarray(M, float).reshape(16))


def _load_file(path: Path) -> mi.Scene:
    """``path`` loaded by Mitsuba, its instances expanded (:mod:`slc.scene.instances`; the
    expanded text is loaded with relative file names resolved from the file's folder)."""
    text = path.read_text(errors="replace")
    if not instances.has_instances(text):
        return mi.load_file(str(path), optimize=False)
    with instances.resolving_from(path.parent.resolve()):
        return mi.load_string(instances.expand(text), optimize=False)


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
        sc = _load_file(path)
    except instances.InstanceError as e:
        raise SceneError(f"cannot expand the instances of scene {path}: {e}") from None
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
