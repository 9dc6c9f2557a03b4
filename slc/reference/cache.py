"""The one key under which every reference is cached on disk (``$SLC_CACHE`` or ``~/.cache/slc``).

The key holds everything a reference depends on: the estimator's version, the source code of
the reference and scene layers (:data:`CODE_HASH`), the scene's content (every parameter
Mitsuba exposes: geometry, emitters, BSDFs and textures), its time, the camera, the
resolution, the sample count, the bounces and the G-buffer's points. Two scenes that share a
name and a G-buffer but differ in a light, a material or an unseen occluder get two entries."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.gbuffer import GBuffer
from slc.scene.scenes import LOAD_VERSION


def cache_root() -> Path:
    return Path(os.environ.get("SLC_CACHE", Path.home() / ".cache" / "slc"))


def _code_hash() -> str:
    """Hash of the source of the modules that compute references and the scenes they
    are computed on (``slc/reference``, ``slc/scene``): a change there never reuses a
    reference cached before it."""
    h = hashlib.sha1()
    root = Path(__file__).resolve().parents[1]
    for p in sorted([*root.joinpath("reference").glob("*.py"), *root.joinpath("scene").glob("*.py")]):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


CODE_HASH = _code_hash()


def scene_hash(mi_scene: mi.Scene) -> str:
    """Hash of every parameter of the Mitsuba scene (``mi.traverse``: vertex positions,
    transforms, emitter radiances, BSDF values, textures), in key order."""
    params = mi.traverse(mi_scene)
    h = hashlib.sha1()
    for k in sorted(params.keys()):
        v = params[k]
        h.update(k.encode())
        try:
            # a copy: converting a literal (an emitter's scale) evaluates it in place, and a
            # kernel that baked the literal would be compiled again in the next frame
            a = np.asarray(dr.copy(v.matrix if hasattr(v, "matrix") else v))
        except (TypeError, ValueError):
            h.update(repr(v).encode())
            continue
        h.update(str(a.dtype).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def gbuffer_hash(gb: GBuffer) -> str:
    """Hash of the G-buffer's points, normals and valid mask (what every
    reference is evaluated at)."""
    h = hashlib.sha1()
    for v in (gb.si.p, gb.si.sh_frame.n, gb.valid):
        h.update(np.ascontiguousarray(np.array(v)).tobytes())
    return h.hexdigest()[:16]


def cache_path(folder: str, version: str, scene, gb: GBuffer, frame: int, viewer: str, spp: int,
               bounces: int | None = None, seed: int | None = None) -> Path:
    """``$SLC_CACHE/<folder>/<scene>_f<frame>_<viewer>_<W>x<H>_s<spp>[_b<bounces>]_<hash>.npy``."""
    cam, t = gb.camera, scene.time
    ident = [version, LOAD_VERSION, CODE_HASH, scene_hash(scene.mi_scene), scene.name, int(frame), viewer, gb.width, gb.height, int(spp),
             bounces, seed, np.round(cam.origin, 6).tolist(), np.round(cam.target, 6).tolist(), float(cam.fov),
             None if t is None else round(float(t), 6), gbuffer_hash(gb)]
    h = hashlib.sha1(json.dumps(ident).encode()).hexdigest()[:16]
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{scene.name}_f{frame}_{viewer}")
    b = "" if bounces is None else f"_b{bounces}"
    return cache_root() / folder / f"{safe}_{gb.width}x{gb.height}_s{spp}{b}_{h}.npy"
