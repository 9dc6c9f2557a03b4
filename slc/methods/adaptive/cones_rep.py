r"""CONES representation: the Surface Light Cones record of :mod:`slc.methods.cones`
(insertion cases A-D, accumulation count, shrink test, 286-bit packing for 3
cones) in a pool of its own.

:func:`update` is the ``slc`` method's own update cycle
(:func:`slc.lib.cones.cycle.update_cycle`: same light sampler, same per-entry
R2 samples, same ray ramp through the shared ray policy), on records of the
pool, with the :class:`~slc.methods.adaptive.sampling.LightStats` observer that
gathers the cycle's light statistics for the choice rule. Shading is
:class:`slc.lib.cones.shading.ConeShading` on the pool, unchanged.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.lib.cones.packing import pack, unpack, words_per_entry
from slc.lib.cones.cycle import CycleEntries, update_cycle
from slc.lib.cones.shading import shade_key, shader_for
from slc.lib.cones.update import ConeParams, empty_state, end_cycle, frame_u32, insert_sample
from slc.scene.lights import light_inputs
from slc.core.freeze import FrozenFunction
from slc.methods.adaptive.choice import CONES
from slc.methods.adaptive.representation import Entries, Pixels, Representation, Updated, lobe_irradiance
from slc.methods.adaptive.sampling import LightStats, SampleStats, lum
from slc.methods.adaptive.frozen_inputs import light_tables, sampler_inputs
from slc.scene.bsdf_table import side_inputs, two_sided

CONVERT_COUNT = 4.0     # C of a record converted from another representation: new samples take over fast


def update(scene: mi.Scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame: int, seed: int,
           p: ConeParams, sph=None, env=None):
    """One update cycle of cone records ``rec`` (packed words, one lane per
    entry): :func:`slc.lib.cones.cycle.update_cycle`, the ``slc`` method's update
    (its light sampler, per-entry R2 samples from ``first_sample`` where not
    ``moving``, C capped for ``moving`` entries), with ``fresh`` records
    restarting empty (no LOD seed) and the choice rule's statistics gathered
    from the same samples. Returns (new words, motion, stats values)."""
    moving = mi.Bool(moving)
    valid = mi.Bool(on) & si.is_valid()
    entries = CycleEntries(key, si, rays, unsettled, moving, fresh, first_sample, ~moving)
    observer = LightStats(scene, si, sph, env, two_sided(scene, si.bsdf(), valid))
    words, motion, _, _, st = update_cycle(scene, unpack(rec, p.max_cones), entries, frame, seed, p,
                                           valid=valid, observer=observer)
    return words, motion, st.values()


class ConesUpdate(FrozenFunction):
    """:func:`update` traced once and replayed (``dr.freeze``, as ``slc``'s
    :class:`slc.methods.cones.update_kernel.ConeUpdate` and :class:`~slc.methods.adaptive.visibility.frozen.VisUpdate`):
    tracing the cone update cycle (the sample loop, cases A-D, the shrink test,
    packing, the light statistics) cost ~45 ms of Python per frame on the
    atrium whatever the number of entries. Inputs: the scene, the emitter
    tables' arrays (the light sampler's, :func:`slc.scene.lights.light_inputs`,
    and the statistics' :func:`~slc.methods.adaptive.frozen_inputs.sampler_inputs`), the
    sphere and region tables, the entries' records and interactions, and the
    frame as an opaque ``mi.UInt32`` (a new frame is no new recording). The
    cone parameters, ``seed``, ``sph`` and ``env`` are fixed per instance.
    Unfrozen after more than ``max_recordings`` recordings. Images are those of
    the traced update bit for bit."""

    def __init__(self, p: ConeParams, seed: int, sph=None, env=None, freeze: bool = True, max_recordings: int = 4):
        self.sph, self.env = sph, env
        seed = int(seed)

        def kernel(scene, lights, tables, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame):
            # no reference to the method (see visibility.frozen.VisShading)
            out, motion, st = update(scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame,
                                     seed, p, sph, env)
            # a statistic the samples never touch (e_delta without delta lights) is a literal zero,
            # which a recording replays at the recorded width: a select makes it a kernel's output
            st = [dr.select(on, x, 0.0) for x in st]
            dr.eval(out, motion, st)
            return out, motion, st
        super().__init__(kernel, freeze, max_recordings=max_recordings,
                         lanes=("rec", "si", "key", "rays", "unsettled", "moving", "first_sample", "fresh",
                                "on"))     # per entry (slc.core.freeze)

    def __call__(self, scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame: int):
        lights = light_inputs(scene)
        if self.sph is not None or self.env is not None:
            lights = lights + sampler_inputs(scene)
        return super().__call__(scene, lights, light_tables(self.sph, self.env) + side_inputs(scene),
                                [mi.UInt32(w) for w in rec], si,
                                mi.UInt32(key), mi.UInt32(rays), mi.Bool(unsettled), mi.Bool(moving),
                                mi.UInt32(first_sample), mi.Bool(fresh), mi.Bool(on), frame_u32(frame))


def lobes(rec, active, K: int):
    """The cones as lobes (local axis, half-angle, integrated radiance, mask)."""
    D, A, L, C, n = unpack(rec, K)
    return [(D[i], A[i], L[i], mi.Bool(active) & (n > i)) for i in range(K)]


def from_lobes(lobes, n_lanes: int, p: ConeParams):
    """Cones holding the lobes' energy: each lobe inserted as a sample of weight
    its integrated radiance (cases A-D merge what does not fit, the sum over
    cones is kept), the first lobe keeping its own half-angle; C is set to
    ``CONVERT_COUNT`` so that new samples take over within a few updates."""
    K = p.max_cones
    D, A, L, C, n = empty_state(n_lanes, K)
    S = [dr.zeros(mi.Color3f, n_lanes) for _ in range(K)]
    beta = dr.zeros(mi.Float, n_lanes)
    first_alpha = dr.zeros(mi.Float, n_lanes)
    first_set = dr.zeros(mi.Bool, n_lanes)
    for d, a, Lr, m in lobes:
        m = mi.Bool(m) & (lum(Lr) > 0.0) & dr.all(dr.isfinite(Lr))
        placed_first = m & ~first_set
        D, A, L, S, n, beta, _ = insert_sample(D, A, L, S, n, beta, dr.normalize(mi.Vector3f(d)), Lr, m, p)
        first_alpha = dr.select(placed_first, a, first_alpha)
        first_set |= m
    A[0] = dr.maximum(A[0], dr.select(n > 0, first_alpha, 0.0))
    L, _, _ = end_cycle(L, S, C, n, beta, mi.UInt32(1), dr.zeros(mi.Bool, n_lanes), p)
    return pack(D, A, L, dr.full(mi.Float, CONVERT_COUNT, n_lanes), n, K)


irradiance_at_normal = lobe_irradiance     # (the cones' lobes' irradiance at the entry's normal)


class ConesRep(Representation):
    """The CONES representation of the adaptive cache: ``slc``'s record (``cache.max_cones``
    cones), ``slc``'s update (``cache.cone_params``) and ``slc``'s shading
    (:func:`slc.lib.cones.shading.shader_for` with the cache's settings), on a pool of
    its own (see the module)."""

    tag, name = CONES, "cones"
    restarts_stats = False

    def words(self) -> int:
        return words_per_entry(self.cache.max_cones)

    def update(self, e: Entries) -> Updated:
        c = self.cache
        fn = self.frozen("update_fn", lambda fz: ConesUpdate(c.cone_params, c.seed, c.sph, c.env, freeze=fz))
        out, motion, st = fn(c.scene.mi_scene, e.rec, e.si, e.key, e.rays, e.unsettled, e.moving, e.first_sample,
                             e.fresh, e.on, e.frame)
        return Updated(out, motion, SampleStats.of(st))

    def shade(self, px: Pixels) -> mi.Color3f:
        c = self.cache
        return shader_for(c, c.max_cones)(self.pool.data, dr.select(px.active, px.slot, 0), px.active, px.si, px.tf,
                                          c.shade_samples, shade_key(px.frame, c.seed), px.pid)

    def lobes(self, rec, si, active) -> list:
        return lobes(rec, active, self.cache.max_cones)

    def convert(self, src, rec, lobes, n: int) -> list:
        return from_lobes(lobes, n, self.cache.cone_params)
