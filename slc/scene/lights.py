"""Light sampling at surface points: the building block shared by RT-N,
ReSTIR, the cache updates and the ground truth.

:func:`sample_light` is the one switch. By default (``table``) it samples
from the scene's :class:`~slc.scene.emitter_sampling.EmitterSampler` (one alias
table over emissive triangles and emitters, no virtual call over emitters;
emitters chosen uniformly as Mitsuba does, or in proportion to power with
``SLC_EMITTER_CHOICE=power``); with ``mitsuba``
(:func:`set_emitter_sampling`, or ``SLC_EMITTER_SAMPLING=mitsuba``) it is
:func:`sample_light_reference`, i.e. ``scene.sample_emitter_direction``
(uniform emitter choice, Mitsuba's per-emitter sampling). The ground
truths always use the reference, so that they stay an independent check.
Either way the weight ``w`` is ``L_e / pdf`` with the emitter choice
already folded in, so ``f * w * V`` is an unbiased one-sample estimate of
direct illumination, and :func:`light_pdf` / :func:`light_pdf_hit` give the
density of the sampler in use (for MIS). :class:`SurfaceBSDF` evaluates the
BSDFs of fixed shading points for many directions (RT-N), diffuse ones
without the virtual call.
"""
from __future__ import annotations

import contextlib
import os

import drjit as dr
import mitsuba as mi

from slc.scene import bsdf_table, emitter_sampling

MODES = ("table", "mitsuba")
_mode = None   # None: read SLC_EMITTER_SAMPLING (default 'table') on first use


def emitter_sampling_mode() -> str:
    """'table' or 'mitsuba' (see the module docstring)."""
    global _mode
    if _mode is None:
        m = os.environ.get("SLC_EMITTER_SAMPLING", "table")
        if m not in MODES:
            raise ValueError(f"SLC_EMITTER_SAMPLING must be one of {', '.join(MODES)}, not '{m}'")
        _mode = m
    return _mode


def set_emitter_sampling(mode: str) -> None:
    """Select the light sampler used by every method from now on. Kernels
    traced before keep the sampler they were traced with."""
    global _mode
    if mode not in MODES:
        raise ValueError(f"emitter sampling must be one of {', '.join(MODES)}, not '{mode}'")
    _mode = mode


@contextlib.contextmanager
def emitter_sampling_as(mode: str):
    """``with emitter_sampling_as('mitsuba'): ...`` (benchmarks, tests)."""
    old = emitter_sampling_mode()
    set_emitter_sampling(mode)
    try:
        yield
    finally:
        set_emitter_sampling(old)


def sampler(scene: mi.Scene, subset=None):
    """The scene's emitter table when the table is in use and models at
    least one of the scene's emitters, else None (Mitsuba's sampling)."""
    if emitter_sampling_mode() != "table":
        return None
    s = emitter_sampling.for_scene(scene, subset=subset)
    return s if s.tabled else None


def stream_state(seed: int, stream: int) -> mi.UInt64:
    """The PCG32 init state of :func:`rng` for (seed, stream), as an opaque array: an input of a
    frozen kernel (a Python int inside it would be baked into the recording)."""
    return dr.opaque(mi.UInt64, (int(seed) * 0x9E3779B97F4A7C15 + int(stream) * 0xBF58476D1CE4E5B9)
                     & 0xFFFFFFFFFFFFFFFF)


def rng(n: int, seed: int, stream: int = 0) -> mi.PCG32:
    """``n`` independent PCG32 streams for one (seed, stream) pair. The seed
    is opaque so that a new frame or seed never recompiles a kernel."""
    return mi.PCG32(size=n, initstate=stream_state(seed, stream), initseq=dr.arange(mi.UInt64, n))


def sample_light(scene: mi.Scene, si: mi.SurfaceInteraction3f, u: mi.Point2f, active: mi.Bool,
                 solid_angle: bool = False):
    """One light sample from ``si``: (DirectionSample3f, L_e/pdf as Color3f, mask),
    from the sampler in use (see the module docstring).

    The mask is false where no sample exists (pdf 0, or the light is behind
    the geometric surface). ``solid_angle``: the table samples mesh triangles
    in the solid angle they subtend (``EmitterSampler.sample``; no
    :func:`light_pdf` for such samples, so not for MIS); Mitsuba's sampler
    ignores it."""
    s = sampler(scene)
    if s is None:
        return sample_light_reference(scene, si, u, active)
    ds, w, ok, _ = s.sample(si, u, active, solid_angle=solid_angle)
    return ds, w, ok


def sample_light_reference(scene: mi.Scene, si: mi.SurfaceInteraction3f, u: mi.Point2f, active: mi.Bool):
    """:func:`sample_light` through Mitsuba's ``scene.sample_emitter_direction``
    (uniform emitter choice); used by the ground truths."""
    ds, w = scene.sample_emitter_direction(si, u, False, active)
    ok = active & (ds.pdf > 0.0) & (dr.max(mi.Color3f(w)) > 0.0)
    return ds, mi.Color3f(w), ok


def light_pdf(scene: mi.Scene, si: mi.SurfaceInteraction3f, ds: mi.DirectionSample3f, active: mi.Bool) -> mi.Float:
    """Solid-angle density with which :func:`sample_light` produces ``ds``
    (emitter choice included; ``ds.n`` the geometric normal for the table)."""
    s = sampler(scene)
    if s is None:
        return scene.pdf_emitter_direction(si, ds, active)
    return s.pdf(si, ds, active)


def light_pdf_hit(scene: mi.Scene, si: mi.SurfaceInteraction3f, si2: mi.SurfaceInteraction3f,
                  active: mi.Bool) -> mi.Float:
    """:func:`light_pdf` of the emitter point ``si2`` hit by a ray from ``si``
    (a BSDF sample; an escaped ray gives the environment's density)."""
    s = sampler(scene)
    if s is None:
        return scene.pdf_emitter_direction(si, mi.DirectionSample3f(scene, si2, si), active)
    return s.pdf_hit(scene, si, si2, active)


def visible(scene: mi.Scene, si: mi.SurfaceInteraction3f, ds: mi.DirectionSample3f, active: mi.Bool) -> mi.Bool:
    """Shadow ray towards the sampled emitter point."""
    return active & ~scene.ray_test(si.spawn_ray_to(ds.p), active)


class SurfaceBSDF:
    r"""The BSDFs of a fixed set of shading points ``si``, evaluated for many
    directions (RT-N's N light samples per pixel).

    Smooth diffuse BSDFs (Mitsuba's ``diffuse``) are evaluated without the
    virtual call over BSDFs: their value is
    :math:`f(\omega_i, \omega_o)\cos\theta_o = k_d \max(\cos\theta_o, 0)`
    with :math:`k_d = \rho(x)/\pi` (0 where :math:`\cos\theta_i \le 0`),
    and :math:`k_d` is read once per point through the BSDF itself (its
    ``eval`` at :math:`\omega_o = (0, 0, 1)`), so a textured albedo is
    looked up at each point's own ``uv``, once instead of once per sample.
    The product is Mitsuba's own, in the same order (bit-identical). Every
    other BSDF goes through ``bsdf.eval`` for its lanes only, and in a scene
    whose shapes all have diffuse BSDFs that call is not traced at all.

    Parameters: ``scene`` (``mi.Scene``), ``si`` (shading points),
    ``active`` (mask), ``ctx`` (``mi.BSDFContext()``; a context that
    disables diffuse reflection or asks for the adjoint transport keeps the
    virtual call for every lane). Build it outside symbolic loops (it reads
    the scene's BSDFs on the host the first time)."""

    def __init__(self, scene: mi.Scene, si: mi.SurfaceInteraction3f, active: mi.Bool,
                 ctx: mi.BSDFContext | None = None):
        self.si, self.ctx = si, ctx if ctx is not None else mi.BSDFContext()
        self.bsdf = si.bsdf()
        table = bsdf_table.for_scene(scene)
        plain = (self.ctx.mode == mi.TransportMode.Radiance and self.ctx.component == 0xFFFFFFFF
                 and self.ctx.type_mask == int(mi.BSDFFlags.All))
        if table is None or not plain:
            self.diffuse, self.others, self.kd = mi.Bool(False), True, None
            return
        rid = dr.reinterpret_array(mi.UInt32, self.bsdf)
        ok = mi.Bool(active) & (self.bsdf != None) & (rid < table.n)  # noqa: E711 (BSDFPtr comparison)
        self.diffuse = dr.gather(mi.Bool, table.diffuse, rid, ok) & ok
        self.others = not table.all_diffuse
        # k_d = rho / pi: Mitsuba's own eval at wo = +z (cos theta_o = 1, an exact product)
        self.kd = mi.Color3f(self.bsdf.eval(self.ctx, si, mi.Vector3f(0.0, 0.0, 1.0), self.diffuse))

    def eval(self, wo: mi.Vector3f, active: mi.Bool) -> mi.Color3f:
        """BSDF value times cosine for the local direction ``wo``."""
        if self.kd is None:
            return mi.Color3f(self.bsdf.eval(self.ctx, self.si, wo, active))
        f = dr.select(self.diffuse & (wo.z > 0.0), self.kd * wo.z, 0.0)
        if self.others:
            g = self.bsdf.eval(self.ctx, self.si, wo, mi.Bool(active) & ~self.diffuse)
            f = dr.select(self.diffuse, f, mi.Color3f(g))
        return dr.select(active, f, 0.0)


def forget(scene_id: int) -> None:
    """Drop the per-scene tables of the scene at address ``scene_id`` (its
    :class:`slc.scene.scenes.Scene` was freed; see :func:`slc.scene.emitter_sampling.forget`)."""
    bsdf_table.forget(scene_id)
    emitter_sampling.forget(scene_id)


def diffuse_flags(scene: mi.Scene):
    """The Bool per BSDF registry id: smooth diffuse (:mod:`slc.scene.bsdf_table`), None for
    scenes without a table."""
    t = bsdf_table.for_scene(scene)
    return None if t is None else t.diffuse


def direct_sample(scene: mi.Scene, si: mi.SurfaceInteraction3f, bsdf, u: mi.Point2f,
                  active: mi.Bool, ctx: mi.BSDFContext | None = None) -> mi.Color3f:
    """One light sample + shadow ray + BSDF evaluation (cosine included).
    ``bsdf`` is ``si.bsdf()`` or a :class:`SurfaceBSDF` of ``si`` (faster
    when the same points take many samples)."""
    ctx = ctx if ctx is not None else mi.BSDFContext()
    ds, w, ok = sample_light(scene, si, u, active)
    ok = visible(scene, si, ds, ok)
    if isinstance(bsdf, SurfaceBSDF):
        f = bsdf.eval(si.to_local(ds.d), ok)
    else:
        f = bsdf.eval(ctx, si, si.to_local(ds.d), ok)
    return dr.select(ok, mi.Color3f(f) * w, 0.0)


def mis_weight(a, b):
    """Power heuristic a^2 / (a^2 + b^2), 0 where both pdfs are 0."""
    a2, b2 = dr.square(a), dr.square(b)
    return dr.select(a2 > 0.0, a2 / (a2 + b2), 0.0)


def light_inputs(scene) -> list:
    """The Dr.Jit arrays of the scene's emitter table (:mod:`slc.scene.emitter_sampling`;
    empty with Mitsuba's sampling), refreshed for moved emissive meshes. A frozen
    function may read only arrays reachable from its inputs: passing these makes
    the table an input (read at each replay, so a refreshed table is followed)."""
    s = sampler(scene)
    if s is None:
        return []

    def arrays(v):
        if isinstance(v, dr.ArrayBase):
            return [v]
        if isinstance(v, (list, tuple)):
            return [a for x in v for a in arrays(x)]
        return []
    return [a for k in sorted(vars(s)) for a in arrays(vars(s)[k])]
