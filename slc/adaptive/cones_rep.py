r"""CONES representation: the Surface Light Cones record of :mod:`slc.cones`
(insertion cases A-D, accumulation count, shrink test, 286-bit packing for 3
cones) in a pool of its own.

:func:`update` is :func:`slc.cones.update._updated_words` (copied, because
that module is not ours to change) with two differences: samples come from
the emitter table with their emitter (:mod:`slc.adaptive.sampling`), and
the cycle's light statistics are returned for the choice rule. Shading is
:class:`slc.cones.shading.ConeShading` on the pool, unchanged.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..cones.packing import pack, unpack
from ..cones.update import ConeParams, empty_state, end_cycle, insert_sample, shrink_step, shrink_test
from ..keys import STREAM_CONE_UPDATE, keyed_rng
from .sampling import lum, sampler_of

CONVERT_COUNT = 4.0     # C of a record converted from another representation: new samples take over fast


def update(scene: mi.Scene, rec, si, key, rays, unsettled, fresh, on, frame: int, seed: int, p: ConeParams):
    """One update cycle of cone records ``rec`` (packed words, one lane per entry).
    Returns (new words, motion, stats values)."""
    K = p.max_cones
    N = dr.width(key)
    samp = sampler_of(scene)
    valid = mi.Bool(on) & si.is_valid()

    # ----------------------------------------------- unpack (fresh records start empty)
    D, A, L, C, n = unpack(rec, K)
    eD, eA, eL, eC, en0 = empty_state(N, K)
    fresh = mi.Bool(fresh)
    D = [dr.select(fresh, eD[i], D[i]) for i in range(K)]
    A = [dr.select(fresh, eA[i], A[i]) for i in range(K)]
    L = [dr.select(fresh, eL[i], L[i]) for i in range(K)]
    C, n = dr.select(fresh, eC, C), dr.select(fresh, en0, n)

    frame_l = si.sh_frame
    sampler = keyed_rng(key, seed, frame, STREAM_CONE_UPDATE)
    rays = mi.UInt32(rays)
    S = [dr.zeros(mi.Color3f, N) for _ in range(K)]
    beta = dr.zeros(mi.Float, N)
    z = dr.zeros(mi.Float, N)

    # ----------------------------------------------- light samples, one at a time per entry
    def cond(k, *state):
        return k < rays

    def body(k, D, A, L, S, n, beta, ed, enn, m, sampler):
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        ds, w, ok, _ = samp.sample(si, u, valid & (k < rays))
        ok &= dr.all(dr.isfinite(w))
        ok &= ~scene.ray_test(si.spawn_ray_to(ds.p), ok)
        s = dr.normalize(frame_l.to_local(ds.d))
        c = dr.select(ok, lum(w) * dr.maximum(s.z, 0.0), 0.0)
        ed = ed + dr.select(ds.delta, c, 0.0)
        cn = dr.select(ds.delta, 0.0, c)
        enn, m = enn + cn, m + s * cn
        D, A, L, S, n, beta, _ = insert_sample(D, A, L, S, n, beta, s, w, ok, p)
        return k + 1, D, A, L, S, n, beta, ed, enn, m, sampler

    _, D, A, L, S, n, beta, ed, enn, m, sampler = dr.while_loop(
        state=(mi.UInt32(0), D, A, L, S, n, beta, z, mi.Float(z), mi.Vector3f(z, z, z), sampler),
        cond=cond, body=body)

    # ----------------------------------------------- shrink test: one ray per cone
    dirs, tested, hits = shrink_test(scene, si, D, A, n, key, valid, mi.Bool(unsettled), sampler, frame, p)
    D, A, L, S, n, beta, dropped, shrunk = shrink_step(D, A, L, S, n, beta, dirs, hits, tested, p)

    # ----------------------------------------------- close the cycle and pack
    L, C, reduced = end_cycle(L, S, C, n, beta, rays, mi.Bool(unsettled), p)
    motion = valid & (reduced | dropped | (beta * (180.0 / math.pi) > p.beta_min_deg))
    return pack(D, A, L, C, n, K), motion, [ed, enn, m]


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
