r"""CONES representation: the Surface Light Cones record of :mod:`slc.methods.cones`
(insertion cases A-D, accumulation count, shrink test, 286-bit packing for 3
cones) in a pool of its own.

:func:`update` is the ``slc`` method's own update cycle
(:func:`slc.methods.cones.cycle.update_cycle`: same light sampler, same per-entry
R2 samples, same ray ramp through the shared ray policy), on records of the
pool, with the :class:`~slc.methods.adaptive.sampling.LightStats` observer that
gathers the cycle's light statistics for the choice rule. Shading is
:class:`slc.methods.cones.shading.ConeShading` on the pool, unchanged.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.cones.packing import pack, unpack
from slc.methods.cones.cycle import CycleEntries, update_cycle
from slc.methods.cones.update import ConeParams, empty_state, end_cycle, frame_u32, insert_sample
from slc.scene.lights import light_inputs
from slc.core.freeze import FrozenFunction
from slc.methods.adaptive.sampling import LightStats, lum
from slc.methods.adaptive.frozen_inputs import light_tables, sampler_inputs

CONVERT_COUNT = 4.0     # C of a record converted from another representation: new samples take over fast


def update(scene: mi.Scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame: int, seed: int,
           p: ConeParams, sph=None, env=None):
    """One update cycle of cone records ``rec`` (packed words, one lane per
    entry): :func:`slc.methods.cones.cycle.update_cycle`, the ``slc`` method's update
    (its light sampler, per-entry R2 samples from ``first_sample`` where not
    ``moving``, C capped for ``moving`` entries), with ``fresh`` records
    restarting empty (no LOD seed) and the choice rule's statistics gathered
    from the same samples. Returns (new words, motion, stats values)."""
    moving = mi.Bool(moving)
    entries = CycleEntries(key, si, rays, unsettled, moving, fresh, first_sample, ~moving)
    words, motion, _, _, st = update_cycle(scene, unpack(rec, p.max_cones), entries, frame, seed, p,
                                           valid=mi.Bool(on) & si.is_valid(), observer=LightStats(scene, si, sph, env))
    return words, motion, st.values()


class ConesUpdate(FrozenFunction):
    """:func:`update` traced once and replayed (``dr.freeze``, as ``slc``'s
    :class:`slc.methods.cones.update_kernel.ConeUpdate` and :class:`~slc.methods.adaptive.vis_frozen.VisUpdate`):
    tracing the cone update cycle (the sample loop, cases A-D, the shrink test,
    packing, the light statistics) cost ~45 ms of Python per frame on the
    atrium whatever the number of entries. Inputs: the scene, the emitter
    tables' arrays (the light sampler's, :func:`slc.scene.lights.light_inputs`,
    and the statistics' :func:`~slc.methods.adaptive.frozen_inputs.sampler_inputs`), the
    sphere and region tables, the entries' records and interactions, and the
    frame as an opaque ``mi.UInt32`` (a new frame is no new recording). The
    cone parameters, ``seed``, ``sph`` and ``env`` are fixed per instance.
    Unfrozen in animated scenes and after more than ``max_recordings``
    recordings. Images are those of the traced update bit for bit."""

    def __init__(self, p: ConeParams, seed: int, sph=None, env=None, freeze: bool = True, max_recordings: int = 4):
        self.sph, self.env = sph, env
        seed = int(seed)

        def kernel(scene, lights, tables, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame):
            # no reference to the method (see vis_frozen.VisShading)
            out, motion, st = update(scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame,
                                     seed, p, sph, env)
            # a statistic the samples never touch (e_delta without delta lights) is a literal zero,
            # which a recording replays at the recorded width: a select makes it a kernel's output
            st = [dr.select(on, x, 0.0) for x in st]
            dr.eval(out, motion, st)
            return out, motion, st
        super().__init__(kernel, freeze, False, max_recordings,
                         lanes=("rec", "si", "key", "rays", "unsettled", "moving", "first_sample", "fresh",
                                "on"))     # per entry (slc.core.freeze)

    def __call__(self, scene, rec, si, key, rays, unsettled, moving, first_sample, fresh, on, frame: int):
        lights = light_inputs(scene)
        if self.sph is not None or self.env is not None:
            lights = lights + sampler_inputs(scene)
        return super().__call__(scene, lights, light_tables(self.sph, self.env), [mi.UInt32(w) for w in rec], si,
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


def irradiance_at_normal(lobes) -> mi.Color3f:
    """Irradiance at the entry's normal (local z) of lobes: sum L (n.d)(1 + cos a)/2."""
    E = mi.Color3f(0.0)
    for d, a, Lr, m in lobes:
        E += dr.select(m, Lr * (dr.maximum(d.z, 0.0) * 0.5 * (1.0 + dr.cos(a))), 0.0)
    return E
