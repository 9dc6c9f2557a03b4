"""Cone update kernels: insertion of light samples (cases A-D), the end of
an update cycle (C reduction, C increment, running mean of the radiance),
and the shrink test for moving / vanished lights.

All functions work on *unpacked* cone state held in registers, vectorized
over entries (one lane per active entry). The state of one lane is

- ``D``: list of ``max_cones`` unit :class:`mi.Vector3f` (local frame of the entry),
- ``A``: list of opening angles (half-angles, radians, :class:`mi.Float`),
- ``L``: list of :class:`mi.Color3f`, the cone's running estimate of
  ``E_c = integral over the cone's solid angle of L_i`` (no cosine),
- ``S``: list of :class:`mi.Color3f`, this cycle's sum of sample weights per cone,
- ``n``: :class:`mi.UInt32` number of cones (cones ``0 .. n-1`` are live, contiguous),
- ``C``: :class:`mi.Float` accumulation count,
- ``beta``: :class:`mi.Float` largest cone turn of this cycle (radians).

Angles between directions are always ``atan2(|a x b|, a . b)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core.keys import STREAM_CONE_UPDATE, keyed_rng, mixed_rng
from slc.core.freeze import FrozenFunction
from slc.osc.protocol import entry_start
from slc.scene.lights import light_inputs, sample_light

INF = float("inf")
# A stream of its own for the per-entry shift of the stratified update samples
# (keyed by the entry alone, so it stays the same over the entry's life)
STREAM_CONE_STRATA = STREAM_CONE_UPDATE ^ 0x5BD1E995
# R2 (Roberts' rank-1 lattice on the plastic constant g): alpha = (1/g, 1/g^2)
# as 32-bit fractions; u_k = frac(shift + k alpha) is computed in integers
# (wrapping mod 2^32), exact for any sample index k
_G2 = 1.32471795724474602596
R2_STEP = (int((1.0 / _G2) * 2 ** 32) & 0xFFFFFFFF, int((1.0 / _G2 ** 2) * 2 ** 32) & 0xFFFFFFFF)


@dataclass
class ConeParams:
    """Tunable constants of the update (defaults are the documented decisions)."""
    max_cones: int = 3
    inside_tol: float = 2e-3        # rad; case A tolerance (covers fp16 direction quantization)
    beta_min_deg: float = 1.0       # C is reduced only when a cone turned by more than this (degrees)
    c_min: float = 2.0              # ... and C is above this
    epsilon: float = 0.1            # shrink test at (1 - epsilon) * alpha from the axis
    alpha_delta: float = 1e-3       # rad; cones narrower than this are never shrink-tested (delta lights)
    alpha_small: float = math.radians(2.0)   # rad; cones below are tested on their axis and dropped on a miss
    shrink_period: int = 4          # settled entries run the shrink test every k-th frame
    seed_c_max: float = 4.0         # C given to an entry seeded from a coarser one
    c_max: float = 255.0            # 8-bit encoding
    multi_cycles: float = 8.0       # cycles of moving entries cap C at this many cycles
    stratified: bool = True         # light samples from a per-entry R2 sequence (False: independent PCG32)
    shrink_keeps: str = "energy"    # a shrunk cone keeps its L_c ("energy", the paper) or its density L_c / Omega_c
    gone_test: bool = False         # a missed rim test is followed by one on the axis; both missed: the light left
    gone_turn: float = math.radians(40.0)   # rad; the turn a left light counts as (40 deg: the largest C reduction, /3)



# ----------------------------------------------------------------------------- frame keys

def frame_u32(frame) -> mi.UInt32:
    """The frame number as an opaque :class:`mi.UInt32` (a Python int is made
    opaque, so that a new frame never recompiles a kernel; a ``mi.UInt32`` is
    kept, so that a frozen update takes the frame as an input, not a key)."""
    return dr.opaque(mi.UInt32, int(frame) & 0xFFFFFFFF) if isinstance(frame, int) else mi.UInt32(frame)


def frame_rng(keys: mi.UInt32, seed: int, frame: mi.UInt32, stream: int) -> mi.PCG32:
    """:func:`slc.core.keys.keyed_rng` for a frame held in a ``mi.UInt32``: the same
    (seed, frame, stream) mix as :func:`slc.core.keys.stream_key`, wrapped modulo
    2^32 in the kernel instead of in Python, so the same streams bit for bit."""
    return mixed_rng(keys, frame * 0x85EBCA77 + ((int(seed) * 0x9E3779B1 + int(stream)) & 0xFFFFFFFF))


# ----------------------------------------------------------------------------- geometry

def angle_between(a, b):
    """Angle between two unit vectors, robust for (anti)parallel inputs."""
    return dr.atan2(dr.norm(dr.cross(a, b)), dr.dot(a, b))


def perpendicular(d):
    return mi.Frame3f(d).s


def rotate_towards(d, s, ang):
    """Rotate unit ``d`` by ``ang`` radians towards ``s`` (away when negative),
    in the plane of ``d`` and ``s``; any plane when they are (anti)parallel."""
    t = s - d * dr.dot(d, s)
    tn = dr.norm(t)
    t = dr.select(tn > 1e-7, t / dr.maximum(tn, 1e-30), perpendicular(d))
    sn, cs = dr.sincos(ang)
    return dr.normalize(d * cs + t * sn)


def cone_direction(d, theta, phi):
    """Direction at angle ``theta`` from the axis ``d``, azimuth ``phi``."""
    fr = mi.Frame3f(d)
    st, ct = dr.sincos(theta)
    sp, cp = dr.sincos(phi)
    return dr.normalize(fr.to_world(mi.Vector3f(st * cp, st * sp, ct)))


def merge_cones(Da, Aa, Db, Ab):
    """Smallest cone containing both cones: (D, alpha, turn of a, turn of b)."""
    th = angle_between(Da, Db)
    a_has_b = th + Ab <= Aa
    b_has_a = th + Aa <= Ab
    Am = dr.minimum(0.5 * (th + Aa + Ab), math.pi)
    Dm = rotate_towards(Da, Db, dr.maximum(Am - Aa, 0.0))
    Dm = dr.select(a_has_b, Da, dr.select(b_has_a, Db, Dm))
    Am = dr.select(a_has_b, Aa, dr.select(b_has_a, Ab, Am))
    return Dm, Am, angle_between(Da, Dm), angle_between(Db, Dm)


def widen_cone(D, A, s):
    """Smallest cone containing cone (D, A) and direction ``s``: (D', A', turn)."""
    th = angle_between(D, s)
    grow = dr.maximum(th - A, 0.0)
    turn = 0.5 * grow
    return rotate_towards(D, s, turn), dr.minimum(A + turn, math.pi), turn


def shrink_cone(D, A, s):
    """The paper's shrink away from a test direction ``s`` inside the cone:
    ``delta = alpha - angle(D, s)``; alpha -= delta; D turns away from s by delta/2.
    Returns (D', A', delta)."""
    delta = dr.maximum(A - angle_between(D, s), 0.0)
    return rotate_towards(D, s, -0.5 * delta), A - delta, delta


def c_reduction(C, beta, p: ConeParams):
    """``C / min(max(1 + beta_deg * 0.05, 1.01), 3)`` when beta (degrees) and C exceed
    their thresholds; ``beta`` is in radians on input."""
    bd = beta * (180.0 / math.pi)
    div = dr.minimum(dr.maximum(1.0 + bd * 0.05, 1.01), 3.0)
    red = (bd > p.beta_min_deg) & (C > p.c_min)
    return dr.select(red, C / div, C), red


# ----------------------------------------------------------------------------- state

def _pick(lst, idx):
    r = lst[0]
    for i in range(1, len(lst)):
        r = dr.select(idx == i, lst[i], r)
    return r


def empty_state(size: int, K: int):
    D = [mi.Vector3f(0.0, 0.0, 1.0) for _ in range(K)]
    A = [dr.zeros(mi.Float, size) for _ in range(K)]
    L = [dr.zeros(mi.Color3f, size) for _ in range(K)]
    return D, A, L, dr.zeros(mi.Float, size), dr.zeros(mi.UInt32, size)


# ----------------------------------------------------------------------------- insertion

def insert_sample(D, A, L, S, n, beta, s, w, ok, p: ConeParams):
    """Insert one light sample (local direction ``s``, weight ``w`` = L_e G / pdf * V)
    where ``ok``. Returns (D, A, L, S, n, beta, case) with case 0 none, 1 A, 2 B, 3 C, 4 D."""
    K = p.max_cones
    D, A, L, S = list(D), list(A), list(L), list(S)
    th = [angle_between(D[i], s) for i in range(K)]
    live = [n > i for i in range(K)]

    # (A) inside a live cone: the one with the nearest axis
    best, idx_in = mi.Float(INF), mi.UInt32(K)
    for i in range(K):
        better = live[i] & (th[i] <= A[i] + p.inside_tol) & (th[i] < best)
        best = dr.select(better, th[i], best)
        idx_in = dr.select(better, i, idx_in)
    caseA = ok & (idx_in < K)
    caseB = ok & ~caseA & (n < K)
    full = ok & ~caseA & ~caseB

    # (A) and (B): add to the cone / start a new one
    for i in range(K):
        a_i = caseA & (idx_in == i)
        b_i = caseB & (n == i)
        S[i] = dr.select(a_i, S[i] + w, S[i])
        D[i] = dr.select(b_i, s, D[i])
        A[i] = dr.select(b_i, 0.0, A[i])
        L[i] = dr.select(b_i, mi.Color3f(0.0), L[i])
        S[i] = dr.select(b_i, w, S[i])
    n = dr.select(caseB, n + 1, n)

    # (C) and (D), for a full record only: in a symbolic branch, which a SIMD packet
    # without such a lane skips (most samples fall inside a cone: case A)
    def full_fn(full, D, A, L, S, beta):
        return _insert_full(D, A, L, S, n, beta, s, w, th, live, full, p)

    def keep_fn(full, D, A, L, S, beta):
        return D, A, L, S, beta, mi.Bool(False)

    D, A, L, S, beta, caseC = dr.if_stmt(args=(full, D, A, L, S, beta), cond=full, true_fn=full_fn,
                                         false_fn=keep_fn, label="insert_full")
    caseD = full & ~caseC
    case = dr.select(caseA, 1, dr.select(caseB, 2, dr.select(caseC, 3, dr.select(caseD, 4, 0))))
    return D, A, L, S, n, beta, mi.UInt32(case)


def _insert_full(D, A, L, S, n, beta, s, w, th, live, full, p: ConeParams):
    """Cases (C) and (D) of :func:`insert_sample` for the lanes ``full`` (no room,
    the sample inside no cone): widen the nearest cone, or merge the closest pair
    and start a new cone. Returns (D, A, L, S, beta, caseC)."""
    K = p.max_cones
    D, A, L, S = list(D), list(A), list(L), list(S)
    # nearest cone axis and closest pair of axes
    jn, thj = mi.UInt32(0), mi.Float(INF)
    for i in range(K):
        better = live[i] & (th[i] < thj)
        thj = dr.select(better, th[i], thj)
        jn = dr.select(better, i, jn)
    pa, pb, pmin = mi.UInt32(0), mi.UInt32(1 if K > 1 else 0), mi.Float(INF)
    for a in range(K):
        for b in range(a + 1, K):
            ang = angle_between(D[a], D[b])
            better = live[b] & (ang < pmin)
            pmin = dr.select(better, ang, pmin)
            pa = dr.select(better, a, pa)
            pb = dr.select(better, b, pb)
    caseC = full & (thj < pmin)
    caseD = full & ~caseC

    # (C) widen the nearest cone
    Dj, Aj = _pick(D, jn), _pick(A, jn)
    Dw, Aw, turn_c = widen_cone(Dj, Aj, s)
    # (D) merge the closest pair into slot pa, new cone in slot pb
    Dm, Am, ta, tb = merge_cones(_pick(D, pa), _pick(A, pa), _pick(D, pb), _pick(A, pb))
    Lm = _pick(L, pa) + _pick(L, pb)
    Sm = _pick(S, pa) + _pick(S, pb)
    turn_d = dr.minimum(ta, tb)

    for i in range(K):
        c_i = caseC & (jn == i)
        m_i = caseD & (pa == i)
        d_i = caseD & (pb == i)
        S[i] = dr.select(c_i, S[i] + w, S[i])
        D[i] = dr.select(c_i, Dw, D[i])
        A[i] = dr.select(c_i, Aw, A[i])
        D[i] = dr.select(m_i, Dm, D[i])
        A[i] = dr.select(m_i, Am, A[i])
        L[i] = dr.select(m_i, Lm, L[i])
        S[i] = dr.select(m_i, Sm, S[i])
        D[i] = dr.select(d_i, s, D[i])
        A[i] = dr.select(d_i, 0.0, A[i])
        L[i] = dr.select(d_i, mi.Color3f(0.0), L[i])
        S[i] = dr.select(d_i, w, S[i])
    beta = dr.select(caseC, dr.maximum(beta, turn_c), beta)
    beta = dr.select(caseD, dr.maximum(beta, turn_d), beta)
    return D, A, L, S, beta, caseC


def end_cycle(L, S, C, n, beta, n_samples, moving, p: ConeParams):
    """Close an update cycle: reduce C once (if a cone turned), add the cycle's
    sample count to it (the paper: "increasing C with the exact samples in every
    cycle"), and fold the samples into each cone's running mean. With
    ``n_s`` samples and their per-cone weight sum ``S_c`` this is the paper's
    per-sample update ``L <- L (1 - 1/C) + L_s / C`` applied ``n_s`` times
    (a sample outside a cone counts as zero for it):

        C' = min(C + n_s, 255),   L_c <- L_c (1 - n_s / C') + S_c / C'.

    Every sample's weight enters exactly one cone, so the sum over cones is the
    running mean of all samples (energy is kept through inserts and merges).
    ``moving`` (entries after detected motion, the ray policy's state) caps C
    at ``multi_cycles`` cycles of ``n_s`` samples: a moving entry forgets its
    older samples. New entries are not capped: their light did not move, and
    a cap would throw away the samples of their first, larger cycles.
    Returns (L, C, reduced)."""
    K = p.max_cones
    C, red = c_reduction(C, beta, p)
    ns = dr.maximum(mi.Float(n_samples), 1.0)
    # moving entries keep at most ``multi_cycles`` cycles of memory; the others go up to 255
    C = dr.minimum(C + ns, dr.select(moving, dr.minimum(p.multi_cycles * ns, p.c_max), p.c_max))
    inv = 1.0 / dr.maximum(C, 1.0)
    keep = dr.maximum(1.0 - ns * inv, 0.0)
    out = []
    for i in range(K):
        Li = L[i] * keep + S[i] * inv
        out.append(dr.select(n > i, Li, mi.Color3f(0.0)))
    return out, C, red


def compact(D, A, L, S, keep, K):
    """Remove cones where ``keep`` is false, keeping the order; returns (D, A, L, S, n)."""
    rank = []
    r = mi.UInt32(0)
    for i in range(K):
        rank.append(r)
        r = r + dr.select(keep[i], 1, 0)
    nD, nA, nL, nS = [], [], [], []
    for q in range(K):
        d, a, l, s_ = mi.Vector3f(0, 0, 1), mi.Float(0.0), mi.Color3f(0.0), mi.Color3f(0.0)
        for i in range(q, K):
            m = keep[i] & (rank[i] == q)
            d = dr.select(m, D[i], d)
            a = dr.select(m, A[i], a)
            l = dr.select(m, L[i], l)
            s_ = dr.select(m, S[i], s_)
        nD.append(d), nA.append(a), nL.append(l), nS.append(s_)
    return nD, nA, nL, nS, r


def shrink_step(D, A, L, S, n, beta, test_dirs, hit, tested, p: ConeParams):
    """Apply the shrink-test outcome of every cone: ``test_dirs[i]`` the tested local
    direction, ``hit[i]`` whether it found an emitter, ``tested[i]`` whether cone i was
    tested. Small cones (alpha < alpha_small) that miss are dropped, larger ones shrink.
    With ``p.shrink_keeps == "density"`` a shrunk cone keeps its radiance density
    ``L_c / Omega_c`` instead of its integral ``L_c``: the test found no light in
    the part of the cone it gives up, so the integral over that part leaves
    with it. Returns (D, A, L, S, n, beta, dropped_any, shrunk_any)."""
    K = p.max_cones
    D, A, L = list(D), list(A), list(L)
    keep, dropped, shrunk = [], mi.Bool(False), mi.Bool(False)
    for i in range(K):
        miss = tested[i] & ~hit[i] & (n > i)
        small = A[i] < p.alpha_small
        drop = miss & small
        shr = miss & ~small
        Dn, An, delta = shrink_cone(D[i], A[i], test_dirs[i])
        An = dr.maximum(An, 0.0)
        if p.shrink_keeps == "density":
            ratio = (1.0 - dr.cos(An)) / dr.maximum(1.0 - dr.cos(A[i]), 1e-12)
            L[i] = dr.select(shr, L[i] * dr.clip(ratio, 0.0, 1.0), L[i])
        D[i] = dr.select(shr, Dn, D[i])
        A[i] = dr.select(shr, An, A[i])
        beta = dr.select(shr, dr.maximum(beta, 0.5 * delta), beta)
        keep.append((n > i) & ~drop)
        dropped |= drop
        shrunk |= shr
    D, A, L, S, n = compact(D, A, L, S, keep, K)
    return D, A, L, S, n, beta, dropped, shrunk


def shrink_test_dirs(D, A, n, u, p: ConeParams):
    """Per cone: (test direction, tested mask). Cones narrower than alpha_delta are not
    tested; cones below alpha_small are tested on the axis; others at (1 - epsilon) alpha
    with azimuth ``2 pi u[i]``."""
    dirs, tested = [], []
    for i in range(p.max_cones):
        th = dr.select(A[i] < p.alpha_small, 0.0, (1.0 - p.epsilon) * A[i])
        dirs.append(cone_direction(D[i], th, 2.0 * math.pi * u[i]))
        tested.append((n > i) & (A[i] >= p.alpha_delta))
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
    (directions, tested masks, hit-a-light masks) per cone."""
    dirs, tested = shrink_test_plan(D, A, n, key, valid, unsettled, sampler, frame, p)
    hits = []
    for i in range(p.max_cones):
        si2 = scene.ray_intersect(si.spawn_ray(si.sh_frame.to_world(dirs[i])), tested[i])
        if area_only:
            # Mitsuba's area emitter: L_e = radiance where cos(theta) > 0 (its front side), else 0;
            # with constant radiance > 0 that is the hit test, without the virtual call
            hit = (si2.emitter(scene, tested[i]) != None) & (mi.Frame3f.cos_theta(si2.wi) > 0.0)  # noqa: E711
        else:
            Le = mi.Color3f(si2.emitter(scene, tested[i]).eval(si2, tested[i]))
            hit = dr.max(Le) > 0.0
        hits.append(tested[i] & hit)
    return dirs, tested, hits


def constant_area_emitters(scene) -> bool:
    """Whether every emitter of ``scene`` is Mitsuba's ``area`` emitter with a constant,
    positive radiance (and there is no environment): then a ray's hit point
    emits (``L_e > 0``) exactly where its shape has an emitter and the ray arrives
    on the front side, which :func:`shrink_test` checks without the emitter's
    virtual call. Read on the host (:meth:`ConeUpdate.area_only` keeps it per
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
    import numpy as np
    a = np.array(v, dtype=np.float64).ravel()
    return a.size > 0 and bool(np.isfinite(a).all()) and bool(a.max() > 0.0)


# ----------------------------------------------------------------------------- the update kernel

@dataclass
class CycleEntries:
    """The per-entry inputs of one update cycle (one lane per entry): ``key`` (the
    entry's random-number and shrink-schedule key), ``si`` (its surface point and
    frame), ``rays`` (light samples this cycle), ``unsettled`` (the ray policy's
    flag), ``moving`` (C capped, see :func:`end_cycle`), ``fresh`` (the entry
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
class UpdateBatch:
    """The per-lane inputs of :func:`_update_kernel`: the entries' ``slot`` in the
    storage, the ``seed_slot`` of their LOD seed (``INVALID``: none) and their
    :class:`CycleEntries`."""
    slot: mi.UInt32
    seed_slot: mi.UInt32
    entries: CycleEntries


def update_entries(scene: mi.Scene, storage: mi.UInt32, active: mi.UInt32, si: mi.SurfaceInteraction3f,
                   rays: mi.UInt32, unsettled: mi.Bool, is_new: mi.Bool, seed_slot: mi.UInt32, keys: mi.UInt32,
                   frame: int, seed: int, p: ConeParams, stats: dict | None = None,
                   moving: mi.Bool | None = None, first_sample: mi.UInt32 | None = None,
                   strata: mi.Bool | None = None, updater: "ConeUpdate | None" = None):
    """One update cycle of every active entry (one lane per entry, samples processed
    sequentially in a loop so no update is lost). Reads and writes the packed
    ``storage`` (``capacity * words_per_entry`` UInt32). ``rays`` and ``unsettled``
    come from the ray policy; ``keys`` seed each entry's random numbers and
    shrink-test schedule (the OSC's viewer-independent texel keys make an entry's
    history independent of which other viewers exist). ``moving`` (default:
    none) marks the entries whose C is capped (see
    :func:`end_cycle`); ``first_sample`` (default 0) is the index of the cycle's
    first sample in the entry's stratified sequence where ``strata`` (default:
    not ``moving``) holds; elsewhere the cycle's samples continue a second
    per-entry sequence at ``frame x rays``. ``updater`` (a :class:`ConeUpdate`,
    default: none) runs the kernel traced once and replayed; without it the
    kernel is traced on every call. Returns (storage, motion mask per active entry)."""
    if dr.width(active) == 0:
        return storage, mi.Bool()
    N = dr.width(active)
    moving = dr.zeros(mi.Bool, N) if moving is None else mi.Bool(moving)
    first_sample = dr.zeros(mi.UInt32, N) if first_sample is None else mi.UInt32(first_sample)
    strata = ~moving if strata is None else mi.Bool(strata)
    # Entries with 8 samples side by side, so that a SIMD packet's loop does not
    # run 8 iterations for 1-sample lanes (random numbers are keyed by slot, so
    # the order changes nothing in the results). Outside the frozen kernel:
    # dr.argsort bakes the array's length into its kernels.
    order = dr.argsort(mi.UInt32(rays), descending=True)
    kernel = updater if updater is not None else _update_kernel
    batch = UpdateBatch(mi.UInt32(active), mi.UInt32(seed_slot),
                        CycleEntries(mi.UInt32(keys), si, mi.UInt32(rays), mi.Bool(unsettled), moving,
                                     mi.Bool(is_new), first_sample, strata))
    storage, motion_o, shrunk_o, dropped_o = kernel(
        scene, light_inputs(scene), storage, order, batch, frame_u32(frame), int(seed), p,
        updater.area_only(scene) if updater is not None else constant_area_emitters(scene))
    motion = dr.zeros(mi.Bool, N)
    dr.scatter(motion, motion_o, order)
    if stats is not None:
        stats["shrunk"] = shrunk_o
        stats["dropped"] = dropped_o
    return storage, motion


def _update_kernel(scene, lights, storage, order, batch: UpdateBatch, frame, seed, p: ConeParams,
                   area_only: bool = False):
    """The update proper, in the lane order ``order``: gather the inputs,
    :func:`_updated_words`, write the words back into ``storage``. Every
    argument that changes from frame to frame is a Dr.Jit array (``frame``
    an opaque ``mi.UInt32``), and nothing here reads an array's width, so
    that :class:`ConeUpdate` can trace it once and replay it for any number
    of entries. ``lights`` (:func:`light_inputs`) is not read here: it declares
    the emitter table's arrays, which :func:`slc.scene.lights.sample_light` reads, as
    inputs of the frozen function. ``area_only`` (a Python bool, part of the recording's
    key) see :func:`shrink_test`. Returns (storage, motion, shrunk, dropped), the masks in lane order."""
    from slc.methods.cones.packing import scatter_words
    act = dr.gather(mi.UInt32, batch.slot, order)
    e = batch.entries
    entries = CycleEntries(
        dr.gather(mi.UInt32, e.key, order), dr.gather(type(e.si), e.si, order), dr.gather(mi.UInt32, e.rays, order),
        dr.gather(mi.Bool, e.unsettled, order), dr.gather(mi.Bool, e.moving, order),
        dr.gather(mi.Bool, e.fresh, order), dr.gather(mi.UInt32, e.first_sample, order),
        dr.gather(mi.Bool, e.strata, order))
    words, motion_o, shrunk_o, dropped_o = _updated_words(
        scene, storage, act, entries, dr.gather(mi.UInt32, batch.seed_slot, order), frame, seed, p, area_only)
    # Every intermediate that read ``storage`` died with _updated_words' locals, so
    # the scatter below writes in place (a live reader would force a full copy).
    scatter_words(storage, words, act, p.max_cones)
    return storage, motion_o, shrunk_o, dropped_o


def _updated_words(scene, storage, active, entries: CycleEntries, seed_slot, frame, seed, p: ConeParams,
                   area_only: bool = False):
    """The update kernel proper on the packed ``storage``: unpack the active
    entries (and the LOD seeds of new ones), :func:`update_cycle`, pack.
    Returns the evaluated (words, motion, shrunk, dropped)."""
    from slc.methods.cones.packing import gather_words, unpack
    K = p.max_cones
    state = unpack(gather_words(storage, active, K), K)
    start = entry_start(entries.fresh, seed_slot, 0)
    has_seed = start.seeded
    seeds = unpack(gather_words(storage, start.src, K, has_seed), K)
    words, motion, shrunk, dropped, _ = update_cycle(scene, state, entries, frame, seed, p, seeds=seeds,
                                                     has_seed=has_seed, area_only=area_only)
    dr.eval(*words, motion, shrunk, dropped)
    return words, motion, shrunk, dropped


class ConeUpdate(FrozenFunction):
    r"""The cone update kernel (:func:`_update_kernel`) traced once and replayed
    (``dr.freeze``): tracing the update (the sample loop, cases A-D, the shrink
    test, packing) costs tens of milliseconds of Python per frame whatever the
    number of entries; a replay launches the recorded kernels on the frame's
    arrays. Images are those of the traced kernel bit for bit.

    Parameters (defaults): ``freeze=True`` (False: trace on every call),
    ``animated=False`` (the scene's meshes move), ``max_recordings=4``.

    A recording is reused while its inputs keep their layout: the frame number is
    an opaque ``mi.UInt32`` input and the number of active entries, the storage's
    size (it grows with the cache) may change between calls without a new recording;
    what forces one is a change of which inputs share a width (e.g. an input of
    width 1: one active entry, or as many entries as a mesh has vertex
    coordinates: such calls run on a free width, see :mod:`slc.core.freeze`), or a
    change of the scene's traversed state. As
    :class:`slc.methods.cones.shading.ConeShading`: in a static scene a function recorded
    more than ``max_recordings`` times is dropped (traced from then on); in an
    animated one it keeps 2 recordings and is dropped once 8 calls show that almost
    every call records."""

    def __init__(self, freeze: bool = True, animated: bool = False, max_recordings: int = 4):
        # per-lane: the order and the batch (a lane count equal to a scene array's width runs
        # on a free width; the extra lanes repeat the last one: same words, same slot)
        super().__init__(_update_kernel, freeze, animated, max_recordings, lanes=("order", "batch"))
        self._area_only = None      # (id of the scene, constant_area_emitters): one scene per instance

    def area_only(self, scene) -> bool:
        """:func:`constant_area_emitters` of ``scene``, read once (no reference to the scene kept)."""
        key = id(getattr(scene, "mi_scene", scene))
        if self._area_only is None or self._area_only[0] != key:
            self._area_only = (key, constant_area_emitters(scene))
        return self._area_only[1]


def updater_for(owner) -> ConeUpdate:
    """The :class:`ConeUpdate` of ``owner`` (a method instance), made on first use
    (animated when the owner's scene is)."""
    up = getattr(owner, "_cone_update", None)
    if up is None:
        scene = getattr(owner, "scene", None)
        up = ConeUpdate(animated=bool(getattr(scene, "dynamic", False)))
        owner._cone_update = up
    return up


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


def update_cycle(scene, state, entries: CycleEntries, frame, seed, p: ConeParams, seeds=None, has_seed=None,
                 valid=None, observer: SampleObserver | None = None, area_only: bool = False):
    """One update cycle of unpacked cone records ``state = (D, A, L, C, n)``
    (one lane per entry, as :func:`slc.methods.cones.packing.unpack` returns it) with
    the per-entry inputs ``entries`` (:class:`CycleEntries`):
    fresh entries restart empty, or from their LOD seed's unpacked
    record ``seeds`` where ``has_seed``; ``rays`` light samples per entry from
    the stratified sequence (see below), insertion (cases A-D), the shrink test,
    the end of the cycle. ``valid`` (default: the interaction's) masks the lanes
    that sample; ``observer`` (a :class:`SampleObserver`) sees every sample;
    ``area_only`` see :func:`shrink_test`.
    Shared by ``slc`` (through :func:`update_entries`) and the adaptive cache's
    cone pool. Returns (packed words, motion, shrunk, dropped, observer state);
    nothing evaluated."""
    from slc.methods.cones.packing import pack
    key, si, rays, unsettled, moving = entries.key, entries.si, entries.rays, entries.unsettled, entries.moving
    is_new, first_sample, strata = entries.fresh, entries.first_sample, entries.strata
    K = p.max_cones
    N = dr.width(key)
    valid = si.is_valid() if valid is None else mi.Bool(valid)
    D, A, L, C, n = (list(state[0]), list(state[1]), list(state[2]), state[3], state[4])

    # ----------------------------------------------- reset / seed new entries
    eD, eA, eL, eC, en = empty_state(N, K)
    is_new = mi.Bool(is_new)
    if seeds is None:
        for i in range(K):
            D[i] = dr.select(is_new, eD[i], D[i])
            A[i] = dr.select(is_new, eA[i], A[i])
            L[i] = dr.select(is_new, eL[i], L[i])
        C = dr.select(is_new, eC, C)
        n = dr.select(is_new, en, n)
    else:
        sD, sA, sL, sC, sn = seeds
        for i in range(K):
            D[i] = dr.select(has_seed, sD[i], dr.select(is_new, eD[i], D[i]))
            A[i] = dr.select(has_seed, sA[i], dr.select(is_new, eA[i], A[i]))
            L[i] = dr.select(has_seed, sL[i], dr.select(is_new, eL[i], L[i]))
        C = dr.select(has_seed, dr.minimum(sC, p.seed_c_max), dr.select(is_new, eC, C))
        n = dr.select(has_seed, sn, dr.select(is_new, en, n))

    frame_l = si.sh_frame
    frame = frame_u32(frame)
    sampler = frame_rng(key, seed, frame, STREAM_CONE_UPDATE)
    rays = mi.UInt32(rays)
    S = [dr.zeros(mi.Color3f, N) for _ in range(K)]
    beta = dr.zeros(mi.Float, N)
    extra = observer.init(N) if observer is not None else ()

    # ----------------------------------------------- light samples, one at a time per entry
    # Stratified over the entry's life: sample j of the entry is the R2 point
    # frac(shift + j alpha), the shift fixed per entry (uniform, so every sample
    # is uniform and the estimate stays unbiased) and j counting on from the
    # samples of earlier cycles, so that the first cycles together cover the
    # light-sampling domain evenly instead of at random. Where ``strata`` is
    # false (moving entries) the sample count is not a
    # function of the age, and indices repeating those of the previous cycle
    # would correlate the cycles they average: there j = frame x rays, in a
    # sequence of its own (a second shift), consecutive over the cycles of a
    # moving phase while the entry's rays stay the same.
    if p.stratified:
        shift = keyed_rng(key, seed, 0, STREAM_CONE_STRATA)
        s0, s1, m0, m1 = (shift.next_uint32(), shift.next_uint32(), shift.next_uint32(), shift.next_uint32())
        j = dr.select(strata, mi.UInt32(first_sample), (frame & 0xFFFFFF) * rays)
        q0 = dr.select(strata, s0, m0) + j * R2_STEP[0]
        q1 = dr.select(strata, s1, m1) + j * R2_STEP[1]
    else:
        q0 = q1 = dr.zeros(mi.UInt32, N)

    def cond(st: SampleLoop):
        return st.k < rays

    def body(st: SampleLoop):
        if p.stratified:
            # top 24 bits: a float32 in [0, 1)
            u = mi.Point2f(mi.Float(st.q0 >> 8) * (1.0 / 16777216.0), mi.Float(st.q1 >> 8) * (1.0 / 16777216.0))
            st.q0, st.q1 = st.q0 + R2_STEP[0], st.q1 + R2_STEP[1]
        else:
            u = mi.Point2f(st.sampler.next_float32(), st.sampler.next_float32())
        ds, w, ok = sample_light(scene, si, u, valid)
        ok &= dr.all(dr.isfinite(w))
        ok &= ~scene.ray_test(si.spawn_ray_to(ds.p), ok)
        s = dr.normalize(frame_l.to_local(ds.d))
        if observer is not None:
            st.extra = observer.observe(st.extra, ds, w, ok, s)
        st.D, st.A, st.L, st.S, st.n, st.beta, _ = insert_sample(st.D, st.A, st.L, st.S, st.n, st.beta, s, w, ok, p)
        st.k = st.k + 1
        return (st,)

    st, = dr.while_loop(state=(SampleLoop(mi.UInt32(0), D, A, L, S, n, beta, sampler, q0, q1, extra),), cond=cond,
                        body=body, labels=("cycle",))
    D, A, L, S, n, beta, sampler, extra = st.D, st.A, st.L, st.S, st.n, st.beta, st.sampler, st.extra

    # ----------------------------------------------- shrink test: one ray per cone
    dirs, tested, hits = shrink_test(scene, si, D, A, n, key, valid, mi.Bool(unsettled), sampler, frame, p,
                                     area_only)
    # A light that left (switched off, moved away) leaves a cone whose rim tests
    # miss but which only shrinks by epsilon alpha per test, with its L_c and C
    # kept: it would fade as (1 - n/C) per cycle, 255 cycles for a settled entry.
    # So a large cone whose rim test missed and that got no sample this cycle
    # is tested once more on its axis; if that misses too, the cycle counts as a
    # turn of ``gone_turn`` (C divided by 3, motion reported: 8 cycles of memory
    # and rays_moving rays until it stops). A cone that still gets samples holds
    # a light that moves within reach, which widening and shrinking follow.
    gone = mi.Bool(False)
    if p.gone_test:
        for i in range(K):
            m = tested[i] & ~hits[i] & (A[i] >= p.alpha_small) & (dr.max(S[i]) <= 0.0)
            si2 = scene.ray_intersect(si.spawn_ray(frame_l.to_world(D[i])), m)
            Le = mi.Color3f(si2.emitter(scene, m).eval(si2, m))
            gone |= m & ~(dr.max(Le) > 0.0)
        beta = dr.select(gone, dr.maximum(beta, p.gone_turn), beta)
    D, A, L, S, n, beta, dropped, shrunk = shrink_step(D, A, L, S, n, beta, dirs, hits, tested, p)

    # ----------------------------------------------- close the cycle and pack
    L, C, reduced = end_cycle(L, S, C, n, beta, rays, moving, p)
    motion = valid & (reduced | dropped | (beta * (180.0 / math.pi) > p.beta_min_deg))
    return pack(D, A, L, C, n, K), motion, shrunk, dropped, extra
