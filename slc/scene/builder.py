"""Building procedural scenes: :class:`SceneBuilder` collects triangle meshes
and lights into a :class:`slc.scene.scenes.Scene`.

With it come the pieces the scene definitions of ``scenes/`` are made of
(``docs/adding-a-scene.md``): material dictionaries (:func:`diffuse`,
:func:`rough_conductor`, :func:`principled`), meshes (:func:`box_mesh`,
:func:`merge_meshes`) and rigid transforms for animation (:func:`translate`,
:func:`rotate`, :func:`about`). :func:`diffuse_cornell` builds the built-in
Cornell box with every surface Lambertian.
"""
from __future__ import annotations

import importlib.util
import math
from typing import Callable

import mitsuba as mi
import numpy as np
import trimesh

from slc.scene.camera import CameraPath
from slc.scene.scenes import SCENES_DIR, Animated, Scene


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
        tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
        tm.apply_translation(np.asarray(center, float))
        kw.setdefault("smooth", True)
        return self.add_trimesh(tm, **kw)

    def add_cylinder(self, p0, p1, radius, sections=12, **kw) -> str:
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

    def add_directional_light(self, direction, irradiance, name="sun"):
        """A distant light (a sun): light travels along ``direction``; ``irradiance`` (RGB, W/m^2) on a
        surface facing it."""
        self.extra[self._id(name)] = {"type": "directional", "direction": list(map(float, direction)),
                                      "irradiance": {"type": "rgb", "value": list(map(float, irradiance))}}

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
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    tm = trimesh.creation.box(extents=hi - lo)
    tm.apply_translation(0.5 * (lo + hi))
    return tm


def merge_meshes(parts):
    """One trimesh from several (fewer shapes make a faster scene)."""
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


def diffuse_cornell():
    """The Cornell box with its rough-metal block made diffuse (white 0.73):
    every surface is Lambertian, the case CRC models (it reconstructs
    rho E / pi). Named ``cornell_diffuse``: cached references are keyed by the scene's
    name and the G-buffer's points, which it shares with ``cornell``."""
    spec = importlib.util.spec_from_file_location("cornell_diffuse", SCENES_DIR / "cornell.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.rough_conductor = lambda *a, **k: diffuse([0.73, 0.73, 0.73])
    scene = mod.build()
    scene.name = "cornell_diffuse"
    return scene


def cornell_walls(b: SceneBuilder) -> dict:
    """The walls of a 2 m Cornell box, [-1, 1] x [0, 2] x [-1, 1] open at +z: white floor,
    ceiling and back, red left and green right wall (Lambertian). Returns the white BSDF."""
    white, red, green = diffuse([0.73, 0.73, 0.73]), diffuse([0.65, 0.05, 0.05]), diffuse([0.12, 0.45, 0.15])
    b.add_quad([0, 0, 0], [1, 0, 0], [0, 0, -1], bsdf=white, name="floor")
    b.add_quad([0, 2, 0], [1, 0, 0], [0, 0, 1], bsdf=white, name="ceiling")
    b.add_quad([0, 1, -1], [1, 0, 0], [0, 1, 0], bsdf=white, name="back")
    b.add_quad([-1, 1, 0], [0, 1, 0], [0, 0, 1], bsdf=red, name="left")
    b.add_quad([1, 1, 0], [0, 0, 1], [0, 1, 0], bsdf=green, name="right")
    return white


def classic_cornell():
    """The classic Cornell box, all Lambertian: a 2 m box (white, red and green walls), a
    tall and a short white block turned as in the original, and a small warm light
    (0.47 m x 0.38 m, radiance (17, 12, 4)) 1 cm below the ceiling; seen from 6.8 m with a
    20 degree field of view, the camera drifting slowly (``cornell:variant=classic``)."""
    b = SceneBuilder("cornell_classic")
    white = cornell_walls(b)
    for name, lo, hi, deg in (("tall_block", [-0.62, 0, -0.62], [-0.02, 1.2, -0.02], 17.0),
                              ("short_block", [0.05, 0, -0.05], [0.65, 0.6, 0.55], -17.0)):
        tm = box_mesh(lo, hi)
        tm.apply_transform(about(0.5 * (np.asarray(lo, float) + np.asarray(hi, float)), rotate([0, 1, 0], deg)))
        b.add_trimesh(tm, bsdf=white, name=name)
    b.add_quad([0, 1.99, 0], [0.235, 0, 0], [0, 0, 0.19], bsdf=diffuse([0, 0, 0]), emission=[17.0, 12.0, 4.0],
               name="light")
    path = CameraPath([([0.0, 1.0, 6.8], [0.0, 1.0, 0.0]), ([0.15, 1.05, 6.8], [0.0, 1.0, 0.0]),
                       ([-0.1, 0.95, 6.9], [0.0, 1.0, 0.0])], fov=20, name="far")
    return b.build([path, path, path], exposure=1.0, unit=1.0, meeting_center=[0, 1.0, 0],
                   description="the classic Cornell box, all Lambertian, a small warm light, seen from far")
