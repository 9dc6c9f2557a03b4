r"""Disk-cached references, and which one a method is compared with.

A method's ``output`` (:data:`slc.methods.OUTPUTS`) selects its reference
(:func:`reference_for`), always at the method's own G-buffer points:

``direct``
    :func:`slc.reference.groundtruth.ground_truth`: direct light by MIS (light and
    BSDF sampling), composed with the emission seen directly.
``indirect``
    :func:`indirect_light` below: light that reached the G-buffer point
    after 1..``bounces`` reflections, emission seen directly excluded.
``full``
    the sum of the two (direct composed with emission + indirect).

The indirect estimator (one definition for every indirect method: CRC and
the MegaViews VPL methods) follows a path from the G-buffer point x_0 with
the surfaces' own BSDFs (``bsdf.sample``; diffuse surfaces give cosine
sampling) and adds next-event estimation of direct light at every vertex
after the first:

.. math:: L_{ind}(x_0) \approx \frac{1}{n}\sum_{s=1}^{n}\sum_{b=1}^{B}
          \beta_b\, \frac{f(x_b, \omega_{b}, \omega_{\ell}) L_e(y_\ell) G V}{p(y_\ell)},
          \qquad \beta_b = \prod_{i<b} \frac{f(x_i)\cos\theta_i}{p(\omega_i)}

Emitters hit by the bounce rays are not counted (that light is direct light
of the vertex before, which next-event estimation already counts), so the
sum of the direct and the indirect reference counts every path of up to
``bounces + 1`` segments exactly once. ``bounces`` is the method's own
(:func:`reference_bounces`).

Every reference is cached on disk (``$SLC_CACHE`` or ``~/.cache/slc``), in
one folder per kind, under one key (:func:`slc.reference.cache.cache_path`): scene, frame,
viewer, resolution, sample count, bounces, estimator version, the version
of scene loading (:data:`slc.scene.scenes.LOAD_VERSION`), the source of the
reference and scene layers, the scene's content (every Mitsuba parameter),
camera, scene time and a hash of the G-buffer points themselves, so a changed
scene, light, material, loader, estimator or G-buffer never reuses a stale reference.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.io import cached_array
from slc.reference.cache import cache_path
from slc.reference.groundtruth import GT_SAMPLES, ground_truth
from slc.scene.gbuffer import GBuffer, compose, to_image
from slc.scene.lights import rng, visible
from slc.scene.lights import sample_light_reference as sample_light  # Mitsuba's own sampling: an independent check

INDIRECT_SAMPLES = 256      # default paths per pixel of the indirect reference
INDIRECT_SEED = 5
_INDIRECT_VERSION = "ind-v2"
STREAM_INDIRECT = 31


# -----------------------------------------------------------------------------
# Indirect light
# -----------------------------------------------------------------------------

def indirect_light(mi_scene: mi.Scene, gb: GBuffer, spp: int = INDIRECT_SAMPLES, bounces: int = 1,
                   seed: int = INDIRECT_SEED) -> mi.Color3f:
    """Indirect radiance (1..``bounces`` reflections) leaving each G-buffer
    point towards its camera, ``spp`` paths per pixel (see the module text)."""
    sampler = rng(gb.size, seed, stream=STREAM_INDIRECT + int(bounces))
    return indirect_paths(mi_scene, gb.si, mi.Bool(gb.valid), sampler, spp, bounces)


def indirect_paths(mi_scene: mi.Scene, si0, active0: mi.Bool, sampler: mi.PCG32, spp: int,
                   bounces: int) -> mi.Color3f:
    """The estimator of :func:`indirect_light` at the points ``si0`` with the random
    numbers of ``sampler`` (one PCG32 lane per point): ``spp`` paths of ``bounces``
    BSDF-sampled reflections, next-event estimation (Mitsuba's light sampling) after
    each; the mean over the paths (``spp`` is opaque: no recompilation per count).
    Shared with the ``pt`` baseline, which passes its own streams."""
    ctx = mi.BSDFContext()
    n = dr.opaque(mi.UInt32, spp)

    def cond(i, L, sampler):
        return i < n

    def body(i, L, sampler):
        si, beta, active = si0, mi.Color3f(1.0), mi.Bool(active0)
        for _ in range(int(bounces)):
            # ---------------------- BSDF-sampled bounce ----------------------
            bs, bw = si.bsdf().sample(ctx, si, sampler.next_float32(),
                                      mi.Point2f(sampler.next_float32(), sampler.next_float32()), active)
            active &= bs.pdf > 0.0
            beta = dr.select(active, beta * mi.Color3f(bw), 0.0)
            si = mi_scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active)
            active &= si.is_valid() & (dr.max(beta) > 0.0)
            # ---------------- next-event estimation at the hit ----------------
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            ds, w, ok = sample_light(mi_scene, si, u, active)
            ok = visible(mi_scene, si, ds, ok)
            f = mi.Color3f(si.bsdf().eval(ctx, si, si.to_local(ds.d), ok))
            L += dr.select(ok, beta * f * w, 0.0)
        return i + 1, L, sampler

    _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                            labels=("i", "L", "sampler"))
    return dr.select(active0, L / float(max(spp, 1)), 0.0)


def indirect_reference(scene, gb: GBuffer, frame: int, viewer: str = "", spp: int = INDIRECT_SAMPLES,
                       bounces: int = 1, use_cache: bool = True) -> np.ndarray:
    """(H, W, 3) :func:`indirect_light` at the G-buffer points, cached on disk."""
    path = cache_path("indirect", _INDIRECT_VERSION, scene, gb, frame, viewer, spp, bounces, INDIRECT_SEED)
    return cached_array(path, lambda: to_image(gb, indirect_light(scene.mi_scene, gb, spp, bounces)),
                        use_cache)


# -----------------------------------------------------------------------------
# Selection by output kind
# -----------------------------------------------------------------------------

def reference_bounces(method) -> int:
    """Indirect bounces a method computes (its ``bounces`` setting, else 1)."""
    return int(getattr(method, "bounces", 1) or 1)


def reference_for(method_output: str, scene, gb: GBuffer, frame: int, viewer: str = "", spp: int | None = None,
                  bounces: int = 1, use_cache: bool = True) -> np.ndarray:
    """(H, W, 3) reference of the kind a method's ``output`` names. ``spp``
    (None: 2048 for direct light, :data:`INDIRECT_SAMPLES` for indirect) is
    used for every part of a ``full`` reference."""
    if method_output == "direct":
        return ground_truth(scene, gb, frame, viewer, spp=spp or GT_SAMPLES, use_cache=use_cache)
    if method_output == "indirect":
        return indirect_reference(scene, gb, frame, viewer, spp or INDIRECT_SAMPLES, bounces, use_cache)
    if method_output == "full":
        return (ground_truth(scene, gb, frame, viewer, spp=spp or GT_SAMPLES, use_cache=use_cache)
                + indirect_reference(scene, gb, frame, viewer, spp or INDIRECT_SAMPLES, bounces, use_cache))
    raise ValueError(f"unknown method output '{method_output}' (direct, indirect or full)")


def image_of(method_output: str, gb: GBuffer, value: mi.Color3f) -> np.ndarray:
    """(H, W, 3) image of a method's output, comparable with
    :func:`reference_for` of the same kind: direct and full light are
    composed with the emission seen directly (:func:`slc.scene.gbuffer.compose`),
    indirect light is shown alone (zero where no surface was hit)."""
    if method_output == "indirect":
        return to_image(gb, dr.select(gb.valid, value, 0.0))
    return to_image(gb, compose(gb, value))


def exposure_for(method_output: str, scene, reference: np.ndarray) -> float:
    """Exposure of the metrics: the scene's for direct and full light; for
    indirect light alone (much darker) ``0.8 / p99`` of the reference's
    luminance, so that FLIP/PSNR/SSIM see its range."""
    if method_output != "indirect":
        return scene.exposure
    return 0.8 / max(float(np.percentile(np.asarray(reference).mean(-1), 99)), 1e-6)
