"""Path-traced reference of diffuse indirect illumination at the G-buffer
points (the ground truth of the CRC experiment), cached on disk like
:mod:`slc.groundtruth`.

Every surface is treated as Lambertian with its diffuse reflectance
(``bsdf.eval_diffuse_reflectance``), one-sided (front = the side of the
shading normal), as the CRC cache models it. Per sample, at the G-buffer
point x: a cosine-distributed direction (throughput rho(x)), the hit y,
next-event estimation of direct light at y (rho(y)/pi cos L_e/pdf V), and
for 2 bounces one more cosine bounce to z with next-event estimation there.
Emitters hit by bounce rays are not counted (direct light is separate).
"""
from __future__ import annotations

import hashlib
import json
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..io import cached_array

from ..gbuffer import GBuffer
from ..groundtruth import cache_dir
from ..lights import finite, rng, visible
from ..lights import sample_light_reference as sample_light  # Mitsuba's own sampling: an independent check

_VERSION = "crc-ref-v1"


def _lambert(si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Color3f:
    return mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, active))


def _nee(scene: mi.Scene, si: mi.SurfaceInteraction3f, rho: mi.Color3f, u: mi.Point2f, active: mi.Bool):
    """rho/pi * cos * L_e/pdf * V: one light sample at a Lambertian point."""
    ds, w, ok = sample_light(scene, si, u, active)
    cos = si.to_local(ds.d).z
    ok = visible(scene, si, ds, ok & (cos > 0.0))
    return dr.select(ok, rho * w * (cos / math.pi), 0.0)


def indirect_diffuse(scene: mi.Scene, gb: GBuffer, spp: int = 256, bounces: int = 1, seed: int = 5) -> mi.Color3f:
    """Outgoing diffuse indirect radiance (1..``bounces`` bounces) per pixel."""
    si0, active0 = gb.si, gb.valid & (gb.si.wi.z > 0.0)
    rho0 = _lambert(si0, active0)
    sampler = rng(gb.size, seed, stream=31 + bounces)
    n = dr.opaque(mi.UInt32, spp)

    def cond(i, L, sampler):
        return i < n

    def body(i, L, sampler):
        si, beta, active = si0, mi.Color3f(rho0), mi.Bool(active0)
        for b in range(bounces):
            # ---------------------- cosine bounce to the next point ----------------------
            wo = mi.warp.square_to_cosine_hemisphere(mi.Point2f(sampler.next_float32(), sampler.next_float32()))
            si = scene.ray_intersect(si.spawn_ray(si.to_world(wo)), active)
            active &= si.is_valid() & (si.wi.z > 0.0)
            rho = _lambert(si, active)
            # ------------------------ next-event estimation ------------------------
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            L += dr.select(active, beta * _nee(scene, si, rho, u, active), 0.0)
            beta = beta * rho
        return i + 1, L, sampler

    _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                            labels=("i", "L", "sampler"))
    return finite(dr.select(active0, L / float(max(spp, 1)), 0.0))


def _key(scene_name, frame, viewer, gb, spp, bounces, t) -> str:
    cam = gb.camera
    h = hashlib.sha1(json.dumps([_VERSION, scene_name, frame, viewer, gb.width, gb.height, spp, bounces,
                                 np.round(cam.origin, 6).tolist(), np.round(cam.target, 6).tolist(),
                                 float(cam.fov), None if t is None else round(float(t), 6)]).encode()).hexdigest()[:16]
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{scene_name}_f{frame}_{viewer}")
    return f"{safe}_{gb.width}x{gb.height}_s{spp}_b{bounces}_{h}.npy"


def reference_indirect(scene, gb: GBuffer, frame: int, viewer: str = "", spp: int = 256, bounces: int = 1,
                       use_cache: bool = True) -> np.ndarray:
    """(H, W, 3) path-traced indirect diffuse radiance, cached on disk."""
    path = cache_dir().parent / "crc-ref" / _key(scene.name, frame, viewer, gb, spp, bounces, scene.time)

    def compute():
        a = np.array(indirect_diffuse(scene.mi_scene, gb, spp, bounces), dtype=np.float32)
        return (a.T if a.shape[0] == 3 else a).reshape(gb.height, gb.width, 3)

    return cached_array(path, compute, use_cache)
