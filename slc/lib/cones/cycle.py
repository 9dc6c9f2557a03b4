"""One update cycle of unpacked cone records, one lane per entry: the per-entry inputs
(:class:`CycleEntries`), the cycle's light samples from a per-entry stratified R2 sequence
inserted one at a time (:func:`update_cycle`, with an optional :class:`SampleObserver` that reads
them), the shrink-test rays (:func:`shrink_test`, with the shortcut for constant area emitters,
:func:`constant_area_emitters`) and the close of the cycle, packed. Built from the operations of
:mod:`slc.lib.cones.update`; shared by ``slc`` (through
:func:`slc.methods.cones.update_kernel.update_entries`) and the adaptive cache's cone pool."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import STREAM_CONE_UPDATE, keyed_rng
from slc.lib.cones.packing import pack
from slc.lib.cones.update import (ConeParams, cone_direction, empty_state, end_cycle, frame_rng, frame_u32,
                                      insert_sample, normalize_cosine_sums, shrink_step)
from slc.scene.lights import sample_light

# A stream of its own for the per-entry shift of the stratified update samples
# (keyed by the entry alone, so it stays the same over the entry's life)
STREAM_CONE_STRATA = STREAM_CONE_UPDATE ^ 0x5BD1E995
# R2 (Roberts' rank-1 lattice on the plastic constant g): alpha = (1/g, 1/g^2)
# as 32-bit fractions; u_k = frac(shift + k alpha) is computed in integers
# (wrapping mod 2^32), exact for any sample index k
_G2 = 1.32471795724474602596
R2_STEP = (int((1.0 / _G2) * 2 ** 32) & 0xFFFFFFFF, int((1.0 / _G2 ** 2) * 2 ** 32) & 0xFFFFFFFF)


def shrink_test_dirs(D, A, n, u, p: ConeParams):
    """Per cone: (test direction, tested mask). Cones narrower than alpha_delta are not
    tested; cones below alpha_small are tested on the axis; others at (1 - epsilon) alpha
    with azimuth ``2 pi u[i]``. With ``p.front_only`` a direction below the horizon is not
    tested (a cone holds no light there)."""
    dirs, tested = [], []
    for i in range(p.max_cones):
        th = dr.select(A[i] < p.alpha_small, 0.0, (1.0 - p.epsilon) * A[i])
        dirs.append(cone_direction(D[i], th, 2.0 * math.pi * u[i]))
        tested.append((n > i) & (A[i] >= p.alpha_delta))
        if p.front_only:
            tested[i] &= dirs[i].z > 0.0
    return dirs, tested


def shrink_test_plan(D, A, n, key: mi.UInt32, valid: mi.Bool, unsettled: mi.Bool, sampler, frame, p: ConeParams):
    """Per cone: (test direction, tested mask) of this update, on the schedule of
    :func:`shrink_test`: every update of an ``unsettled`` entry, else every
    ``shrink_period``-th frame (staggered by ``key``); draws one number per cone from ``sampler``."""
    period = max(int(p.shrink_period), 1)
    phase = frame_u32(frame) % period  # opaque: no recompilation per frame
    do_shrink = valid & (unsettled | (((key + phase) % period) == 0))
    us = [sampler.next_float32() for _ in range(p.max_cones)]
    dirs, tested = shrink_test_dirs(D, A, n, us, p)
    return dirs, [t & do_shrink for t in tested]


def shrink_test(scene: mi.Scene, si: mi.SurfaceInteraction3f, D, A, n, key: mi.UInt32, valid: mi.Bool,
                unsettled: mi.Bool, sampler, frame: int, p: ConeParams, area_only: bool = False):
    """Trace one shrink-test ray per cone (paper Sec. 3.3) of the ``valid``
    entries: at every update of an ``unsettled`` entry, else every
    ``shrink_period``-th frame (staggered by ``key``). ``area_only``
    (:func:`constant_area_emitters`, read by the caller outside any frozen
    function) tests a hit without the emitter's virtual call. Returns
    (directions, tested masks, hit-a-light masks, dark masks) per cone: a dark
    ray hit the front side of an emitter's shape that emits nothing there (a
    light switched off, its shape in place); ``dark`` is None with ``area_only``,
    where every emitter emits."""
    dirs, tested = shrink_test_plan(D, A, n, key, valid, unsettled, sampler, frame, p)
    hits, dark = [], None if area_only else []
    for i in range(p.max_cones):
        si2 = scene.ray_intersect(si.spawn_ray(si.sh_frame.to_world(dirs[i])), tested[i])
        if area_only:
            # Mitsuba's area emitter: L_e = radiance where cos(theta) > 0 (its front side), else 0;
            # with constant radiance > 0 that is the hit test, without the virtual call
            hit = (si2.emitter(scene, tested[i]) != None) & (mi.Frame3f.cos_theta(si2.wi) > 0.0)  # noqa: E711
        else:
            hit, off = emitter_hit(scene, si2, tested[i])
            dark.append(tested[i] & off)
        hits.append(tested[i] & hit)
    return dirs, tested, hits, dark


def emitter_hit(scene: mi.Scene, si2: mi.SurfaceInteraction3f, active: mi.Bool):
    """(lit, dark) of a shrink-test ray's intersection ``si2``: lit where the hit
    emits towards the ray (``L_e > 0``, the environment on a miss), dark where it
    is the front side of an emitter's shape that emits nothing there (a light
    switched off; a light that moved away is not hit at all)."""
    em = si2.emitter(scene, active)
    Le = mi.Color3f(em.eval(si2, active))
    lit = dr.max(Le) > 0.0
    front = si2.is_valid() & (em != None) & (mi.Frame3f.cos_theta(si2.wi) > 0.0)  # noqa: E711
    return lit, front & ~lit


def constant_area_emitters(scene) -> bool:
    """Whether every emitter of ``scene`` is Mitsuba's ``area`` emitter with a constant,
    positive radiance (and there is no environment): then a ray's hit point
    emits (``L_e > 0``) exactly where its shape has an emitter and the ray arrives
    on the front side, which :func:`shrink_test` checks without the emitter's
    virtual call. Read on the host (:meth:`slc.methods.cones.update_kernel.ConeUpdate.area_only` keeps it per
    instance: a module-level cache holding the scene kept a released scene's
    objects in Mitsuba's registry, which every frozen function traverses)."""
    ms = getattr(scene, "mi_scene", scene)
    ok = ms.environment() is None and len(ms.emitters()) > 0
    for e in ms.emitters():
        if not ok:
            break
        params = mi.traverse(e)
        own = [k for k in params.keys() if k == "radiance" or k.startswith("radiance.")]
        ok = e.class_name() == "AreaLight" and own == ["radiance.value"] and _positive(params["radiance.value"])
    return ok


def _positive(v) -> bool:
    a = np.array(v, dtype=np.float64).ravel()
    return a.size > 0 and bool(np.isfinite(a).all()) and bool(a.max() > 0.0)


@dataclass
class CycleEntries:
    """The per-entry inputs of one update cycle (one lane per entry): ``key`` (the
    entry's random-number and shrink-schedule key), ``si`` (its surface point and
    frame), ``rays`` (light samples this cycle), ``unsettled`` (the ray policy's
    flag), ``moving`` (C capped, see :func:`slc.lib.cones.update.end_cycle`), ``fresh`` (the entry
    restarts: new, or a record converted from elsewhere), ``first_sample`` (the
    index of the cycle's first sample in the entry's stratified sequence) and
    ``strata`` (the samples continue that sequence; false: a per-frame one)."""
    key: mi.UInt32
    si: mi.SurfaceInteraction3f
    rays: mi.UInt32
    unsettled: mi.Bool
    moving: mi.Bool
    fresh: mi.Bool
    first_sample: mi.UInt32
    strata: mi.Bool


@dataclass
class SampleLoop:
    """The state of an update cycle's sample loop (one lane per entry): ``k`` the
    samples drawn, the cones (``D`` axes, ``A`` half-angles, ``L`` integrated
    radiance: lists of ``K``) and ``n`` their number, ``S`` the cycle's sample sums
    per cone, ``beta`` the cycle's largest cone turn [rad], ``sampler`` the
    unstratified random numbers, ``q0``, ``q1`` the R2 sequence's next point (32-bit
    fixed point) and ``extra`` the observer's state (:class:`SampleObserver`)."""
    k: mi.UInt32
    D: list
    A: list
    L: list
    S: list
    n: mi.UInt32
    beta: mi.Float
    sampler: mi.PCG32
    q0: mi.UInt32
    q1: mi.UInt32
    extra: tuple


class SampleObserver:
    """Hook of :func:`update_cycle` for callers that need more than the cones
    from the cycle's light samples (the adaptive cache's light statistics):
    :meth:`init` gives extra loop state (a tuple of Dr.Jit arrays, one lane
    per entry), :meth:`observe` folds one sample into it. The observer only
    reads the samples: the cones are the same with or without one."""

    def init(self, n: int) -> tuple:
        return ()

    def observe(self, extra: tuple, ds: mi.DirectionSample3f, w: mi.Color3f, ok: mi.Bool,
                s: mi.Vector3f) -> tuple:
        """``ds`` the light sample, ``w`` its weight L_e G / pdf, ``ok`` valid and
        visible, ``s`` its direction in the entry's local frame."""
        return extra


def update_cycle(scene, state, entries: CycleEntries, frame, seed, p: ConeParams, seeded=None,
                 valid=None, observer: SampleObserver | None = None, area_only: bool = False):
    """One update cycle of unpacked cone records ``state = (D, A, L, C, n)``
    (one lane per entry, as :func:`slc.lib.cones.packing.unpack` returns it) with
    the per-entry inputs ``entries`` (:class:`CycleEntries`), in stages that share the cone
    state: fresh entries restart empty, or where ``seeded`` from ``state``, which holds their
    LOD seed's record there (its C capped at ``seed_c_max``; :func:`_reset`); ``rays`` light
    samples per entry from the stratified sequence (:func:`_sequence_start`), insertion (cases
    A-D; :func:`_light_samples`), the shrink test (and :func:`_gone_turn`), the end of the cycle.
    ``valid`` (default: the interaction's) masks the lanes
    that sample; ``observer`` (a :class:`SampleObserver`) sees every sample;
    ``area_only`` see :func:`shrink_test`.
    Shared by ``slc`` (through :func:`slc.methods.cones.update_kernel.update_entries`) and the adaptive cache's
    cone pool. Returns (packed words, motion, shrunk, dropped, observer state);
    nothing evaluated."""
    key, si, rays, unsettled, moving = entries.key, entries.si, entries.rays, entries.unsettled, entries.moving
    K = p.max_cones
    N = dr.width(key)
    valid = si.is_valid() if valid is None else mi.Bool(valid)

    # ----------------------------------------------- reset / seed new entries
    D, A, L, C, n = _reset(state, entries.fresh, seeded, N, p)

    frame_l = si.sh_frame
    frame = frame_u32(frame)
    sampler = frame_rng(key, seed, frame, STREAM_CONE_UPDATE)
    rays = mi.UInt32(rays)
    S = [dr.zeros(mi.Color3f, N) for _ in range(K)]
    beta = dr.zeros(mi.Float, N)
    extra = observer.init(N) if observer is not None else ()

    # ----------------------------------------------- light samples, one at a time per entry
    q0, q1 = _sequence_start(entries, seed, frame, rays, N, p)
    st = _light_samples(scene, si, valid, rays, observer, p,
                        SampleLoop(mi.UInt32(0), D, A, L, S, n, beta, sampler, q0, q1, extra))
    D, A, L, S, n, beta, sampler, extra = st.D, st.A, st.L, st.S, st.n, st.beta, st.sampler, st.extra

    # ----------------------------------------------- shrink test: one ray per cone
    dirs, tested, hits, dark = shrink_test(scene, si, D, A, n, key, valid, mi.Bool(unsettled), sampler, frame, p,
                                           area_only)
    beta = _gone_turn(scene, si, D, A, S, beta, tested, hits, dark, p)
    D, A, L, S, n, beta, dropped, shrunk = shrink_step(D, A, L, S, n, beta, dirs, hits, tested, p)

    # ----------------------------------------------- close the cycle and pack
    if p.cosine_sums:
        S = normalize_cosine_sums(S, D, A, K)
    L, C, reduced = end_cycle(L, S, C, n, beta, rays, moving, p)
    motion = valid & (reduced | dropped | (beta * (180.0 / math.pi) > p.beta_min_deg))
    return pack(D, A, L, C, n, K), motion, shrunk, dropped, extra


def _reset(state, is_new, seeded, N: int, p: ConeParams):
    """The cone records ``(D, A, L, C, n)`` at the start of the cycle: ``state``'s, where
    ``is_new`` empty, except where ``seeded`` (``state`` holds the seed's record there, one
    gather and decode per entry: the entry's own record or its seed's, not both), C capped at
    ``seed_c_max``."""
    K = p.max_cones
    D, A, L, C, n = (list(state[0]), list(state[1]), list(state[2]), state[3], state[4])
    eD, eA, eL, eC, en = empty_state(N, K)
    is_new = mi.Bool(is_new)
    if seeded is None:
        for i in range(K):
            D[i] = dr.select(is_new, eD[i], D[i])
            A[i] = dr.select(is_new, eA[i], A[i])
            L[i] = dr.select(is_new, eL[i], L[i])
        C = dr.select(is_new, eC, C)
        n = dr.select(is_new, en, n)
    else:
        for i in range(K):
            D[i] = dr.select(seeded, D[i], dr.select(is_new, eD[i], D[i]))
            A[i] = dr.select(seeded, A[i], dr.select(is_new, eA[i], A[i]))
            L[i] = dr.select(seeded, L[i], dr.select(is_new, eL[i], L[i]))
        C = dr.select(seeded, dr.minimum(C, p.seed_c_max), dr.select(is_new, eC, C))
        n = dr.select(seeded, n, dr.select(is_new, en, n))
    return D, A, L, C, n


def _sequence_start(entries: CycleEntries, seed, frame: mi.UInt32, rays: mi.UInt32, N: int, p: ConeParams):
    """The R2 point ``(q0, q1)`` (32-bit fixed point) of the cycle's first light sample.

    Stratified over the entry's life: sample j of the entry is the R2 point
    frac(shift + j alpha), the shift fixed per entry (uniform, so every sample
    is uniform and the estimate stays unbiased) and j counting on from the
    samples of earlier cycles, so that the first cycles together cover the
    light-sampling domain evenly instead of at random. Where ``strata`` is
    false (moving entries) the sample count is not a
    function of the age, and indices repeating those of the previous cycle
    would correlate the cycles they average: there j = frame x rays, in a
    sequence of its own (a second shift), consecutive over the cycles of a
    moving phase while the entry's rays stay the same."""
    if not p.stratified:
        q0 = q1 = dr.zeros(mi.UInt32, N)
        return q0, q1
    strata = entries.strata
    shift = keyed_rng(entries.key, seed, 0, STREAM_CONE_STRATA)
    s0, s1, m0, m1 = (shift.next_uint32(), shift.next_uint32(), shift.next_uint32(), shift.next_uint32())
    j = dr.select(strata, mi.UInt32(entries.first_sample), (frame & 0xFFFFFF) * rays)
    q0 = dr.select(strata, s0, m0) + j * R2_STEP[0]
    q1 = dr.select(strata, s1, m1) + j * R2_STEP[1]
    return q0, q1


def _light_samples(scene, si, valid: mi.Bool, rays: mi.UInt32, observer: SampleObserver | None, p: ConeParams,
                   st: SampleLoop) -> SampleLoop:
    """The cycle's ``rays`` light samples inserted one at a time into the cones of ``st``
    (a symbolic loop over the samples, one lane per entry)."""
    frame_l = si.sh_frame

    def cond(st: SampleLoop):
        return st.k < rays

    def body(st: SampleLoop):
        if p.stratified:
            # top 24 bits: a float32 in [0, 1)
            u = mi.Point2f(mi.Float(st.q0 >> 8) * (1.0 / 16777216.0), mi.Float(st.q1 >> 8) * (1.0 / 16777216.0))
            st.q0, st.q1 = st.q0 + R2_STEP[0], st.q1 + R2_STEP[1]
        else:
            u = mi.Point2f(st.sampler.next_float32(), st.sampler.next_float32())
        # mesh triangles in the solid angle they subtend: no d^2/cos factor in w (a large or close light
        # sampled by area has a per-sample variance of up to 150x the squared mean)
        ds, w, ok = sample_light(scene, si, u, valid, solid_angle=True)
        ok &= dr.all(dr.isfinite(w))
        s = dr.normalize(frame_l.to_local(ds.d))
        if p.front_only:
            # below the horizon: no light reaches the entry's pixels; a zero of the cycle
            ok &= s.z > 0.0
        ok &= ~scene.ray_test(si.spawn_ray_to(ds.p), ok)
        if observer is not None:
            st.extra = observer.observe(st.extra, ds, w, ok, s)
        # the cycle's sums S_c: cosine-weighted where the end of the cycle divides by the cap's mean cosine
        w_s = w * s.z if p.cosine_sums else w
        st.D, st.A, st.L, st.S, st.n, st.beta, _ = insert_sample(st.D, st.A, st.L, st.S, st.n, st.beta, s, w_s, ok, p)
        st.k = st.k + 1
        return (st,)

    st, = dr.while_loop(state=(st,), cond=cond, body=body, labels=("cycle",))
    return st


def _gone_turn(scene, si, D, A, S, beta: mi.Float, tested, hits, dark, p: ConeParams) -> mi.Float:
    """The cycle's largest cone turn ``beta``, at least ``gone_turn`` where a light left.

    A light that left (switched off, moved away) leaves a cone whose rim tests
    miss but which only shrinks by epsilon alpha per test, with its L_c and C
    kept: it would fade as (1 - n/C) per cycle, 255 cycles for a settled entry.
    A light switched off shows itself: a shrink-test ray that hits the front
    side of an emitter's shape emitting nothing there (a light that moved is
    not hit at all). A large cone whose rim test missed (a rim ray falls off a
    square light most of the time) and that got no sample this cycle is tested
    once more on its axis; a dark rim or axis hit counts the cycle as a turn of
    ``gone_turn`` (C divided by 3, motion reported: 8 cycles of memory and
    rays_moving rays until it stops). With ``gone_test`` any axis miss counts
    so (a light that moved away too). A cone that still gets samples holds a
    light that moves within reach, which widening and shrinking follow. With
    ``area_only`` no emitter is dark (``dark`` None): no test."""
    frame_l = si.sh_frame
    gone = mi.Bool(False)
    for d in dark or []:
        gone |= d
    if p.gone_test or dark is not None:
        for i in range(p.max_cones):
            m = tested[i] & ~hits[i] & (A[i] >= p.alpha_small) & (dr.max(S[i]) <= 0.0)
            if dark is not None:
                m &= ~dark[i]
            si2 = scene.ray_intersect(si.spawn_ray(frame_l.to_world(D[i])), m)
            lit, off = emitter_hit(scene, si2, m)
            gone |= m & (~lit if p.gone_test else off)
        beta = dr.select(gone, dr.maximum(beta, p.gone_turn), beta)
    return beta
