"""Ground truth: 2048 samples per pixel of direct illumination at the
G-buffer points, with multiple importance sampling of lights and BSDF.

Per sample: one light sample (shadow ray, power-heuristic weight against the
BSDF pdf; delta lights weight 1) plus one BSDF sample (a ray; if it hits an
emitter or escapes to the environment, weighted against the light pdf).
Results are cached on disk (``$SLC_CACHE/gt`` or ``~/.cache/slc/gt``) under
the one key of :func:`slc.reference.cache.cache_path` (scene, frame, viewer,
resolution, sample count, camera, scene time, G-buffer hash), so
experiments never recompute the same reference.
"""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core import check
from slc.scene.gbuffer import GBuffer, compose, to_image
from slc.core.io import cached_array
from slc.scene.lights import mis_weight, rng, visible
from slc.scene.lights import sample_light_reference as sample_light  # Mitsuba's own sampling: an independent check
from slc.reference.cache import cache_path, cache_root

GT_SAMPLES = 2048
_VERSION = "gt-v1"


def cache_dir() -> Path:
    return cache_root() / "gt"


def direct_mis(scene: mi.Scene, gb: GBuffer, spp: int = GT_SAMPLES, seed: int = 7) -> mi.Color3f:
    """Direct illumination at the G-buffer points, ``spp`` MIS samples each."""
    si, active = gb.si, gb.valid
    bsdf = si.bsdf()
    ctx = mi.BSDFContext()
    sampler = rng(gb.size, seed, stream=99)
    n = dr.opaque(mi.UInt32, spp)

    def cond(i, L, sampler):
        return i < n

    def body(i, L, sampler):
        # --------------------------- Light sampling ---------------------------
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        ds, w, ok = sample_light(scene, si, u, active)
        ok = visible(scene, si, ds, ok)
        wo = si.to_local(ds.d)
        f = mi.Color3f(bsdf.eval(ctx, si, wo, ok))
        pdf_b = bsdf.pdf(ctx, si, wo, ok)
        m = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, pdf_b))
        L += dr.select(ok, f * w * m, 0.0)

        # ---------------------------- BSDF sampling ---------------------------
        u1 = sampler.next_float32()
        u2 = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        bs, bw = bsdf.sample(ctx, si, u1, u2, active)
        ok_b = active & (bs.pdf > 0.0) & (dr.max(mi.Color3f(bw)) > 0.0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        si2 = scene.ray_intersect(ray, ok_b)
        em = si2.emitter(scene, ok_b)
        ok_b &= em != None  # noqa: E711 (EmitterPtr comparison)
        Le = mi.Color3f(em.eval(si2, ok_b))
        ds2 = mi.DirectionSample3f(scene, si2, si)
        pdf_l = scene.pdf_emitter_direction(si, ds2, ok_b)
        m2 = mis_weight(bs.pdf, pdf_l)
        L += dr.select(ok_b, mi.Color3f(bw) * Le * m2, 0.0)
        return i + 1, L, sampler

    _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                            labels=("i", "L", "sampler"))
    return L / float(max(spp, 1))


def ground_truth(scene, gb: GBuffer, frame: int, viewer: str = "", spp: int = GT_SAMPLES,
                 use_cache: bool = True) -> np.ndarray:
    """Composed ground-truth image (H, W, 3) at the G-buffer's points, cached."""
    path = cache_path("gt", _VERSION, scene, gb, frame, viewer, spp)

    def compute():
        return to_image(gb, compose(gb, direct_mis(scene.mi_scene, gb, spp)))

    img = cached_array(path, compute, use_cache)
    if check.enabled():                      # check mode: the reference is raw too
        with check.scope("gt", frame, [gb]):
            check.images([img], [gb], stage="ground truth")
    return img
