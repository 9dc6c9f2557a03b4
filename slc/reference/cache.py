"""The one key under which every reference is cached on disk (``$SLC_CACHE`` or ``~/.cache/slc``)."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from slc.scene.gbuffer import GBuffer


def cache_root() -> Path:
    return Path(os.environ.get("SLC_CACHE", Path.home() / ".cache" / "slc"))


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
    ident = [version, scene.name, int(frame), viewer, gb.width, gb.height, int(spp), bounces, seed,
             np.round(cam.origin, 6).tolist(), np.round(cam.target, 6).tolist(), float(cam.fov),
             None if t is None else round(float(t), 6), gbuffer_hash(gb)]
    h = hashlib.sha1(json.dumps(ident).encode()).hexdigest()[:16]
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{scene.name}_f{frame}_{viewer}")
    b = "" if bounces is None else f"_b{bounces}"
    return cache_root() / folder / f"{safe}_{gb.width}x{gb.height}_s{spp}{b}_{h}.npy"
