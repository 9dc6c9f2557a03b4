"""Light sampling at surface points: the building block shared by RT-N,
ReSTIR, the cache updates and the ground truth.

All emitter kinds of Mitsuba go through ``scene.sample_emitter_direction``:
area lights on shapes and emissive meshes (sampled by area or solid angle),
point and spot lights (``ds.delta``), directional lights and environment
maps. The returned weight ``w`` is ``L_e / pdf`` with the uniform choice of
emitter already folded in, so ``f * w * V`` is an unbiased one-sample
estimate of direct illumination.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def rng(n: int, seed: int, stream: int = 0) -> mi.PCG32:
    """``n`` independent PCG32 streams for one (seed, stream) pair. The seed
    is opaque so that a new frame or seed never recompiles a kernel."""
    idx = dr.arange(mi.UInt64, n)
    s = dr.opaque(mi.UInt64, (int(seed) * 0x9E3779B97F4A7C15 + int(stream) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF)
    return mi.PCG32(size=n, initstate=s, initseq=idx)


def finite(c: mi.Color3f) -> mi.Color3f:
    """Replace NaN/Inf by 0."""
    ok = dr.isfinite(c[0]) & dr.isfinite(c[1]) & dr.isfinite(c[2])
    return dr.select(ok, c, 0.0)


def sample_light(scene: mi.Scene, si: mi.SurfaceInteraction3f, u: mi.Point2f, active: mi.Bool):
    """One light sample from ``si``: (DirectionSample3f, L_e/pdf as Color3f, mask).

    The mask is false where no sample exists (pdf 0, or the light is behind
    the geometric surface)."""
    ds, w = scene.sample_emitter_direction(si, u, False, active)
    ok = active & (ds.pdf > 0.0) & (dr.max(mi.Color3f(w)) > 0.0)
    return ds, mi.Color3f(w), ok


def visible(scene: mi.Scene, si: mi.SurfaceInteraction3f, ds: mi.DirectionSample3f, active: mi.Bool) -> mi.Bool:
    """Shadow ray towards the sampled emitter point."""
    return active & ~scene.ray_test(si.spawn_ray_to(ds.p), active)


def direct_sample(scene: mi.Scene, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, u: mi.Point2f,
                  active: mi.Bool, ctx: mi.BSDFContext | None = None) -> mi.Color3f:
    """One light sample + shadow ray + BSDF evaluation (cosine included)."""
    ctx = ctx if ctx is not None else mi.BSDFContext()
    ds, w, ok = sample_light(scene, si, u, active)
    ok = visible(scene, si, ds, ok)
    f = bsdf.eval(ctx, si, si.to_local(ds.d), ok)
    return dr.select(ok, mi.Color3f(f) * w, 0.0)


def mis_weight(a, b):
    """Power heuristic a^2 / (a^2 + b^2), 0 where both pdfs are 0."""
    a2, b2 = dr.square(a), dr.square(b)
    return dr.select(a2 > 0.0, a2 / (a2 + b2), 0.0)
