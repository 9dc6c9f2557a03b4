"""The cone update's operations on unpacked cone state: insertion of light samples (cases
A-D), the end of an update cycle (C reduction, C increment, running mean of the radiance), and
the shrink of cones whose shrink test missed (moving / vanished lights); with the update's
parameters (:class:`ConeParams`), per-frame random numbers and cone geometry. One update cycle
built from them is :mod:`slc.lib.cones.cycle`; the kernel on the packed storage, traced once
and replayed, :mod:`slc.methods.cones.update_kernel`.

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

from slc.core.keys import mixed_rng
from slc.lib.cones.conestate import above_mean_cosine

INF = float("inf")


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
    gone_test: bool = False         # a missed axis test after a missed rim test: the light left (else a dark hit only)
    gone_turn: float = math.radians(40.0)   # rad; the turn a left light counts as (40 deg: the largest C reduction, /3)
    front_only: bool = False        # only light above an entry's horizon reaches its pixels (every BSDF reflects on
                                    # its front side only): samples below it are dropped, shrink tests below it skipped
    cosine_weights: bool = True     # with front_only: a cycle's samples enter S_c weighted by their cosine, divided by
                                    # the cap's mean cosine above the horizon at the end of the cycle (cosine_sums)

    @property
    def cosine_sums(self) -> bool:
        """Whether a cycle's sums are cosine-weighted (:func:`normalize_cosine_sums`)."""
        return self.front_only and self.cosine_weights



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


def normalize_cosine_sums(S, D, A, K: int):
    r"""The cycle's cosine-weighted sums ``S_c`` (:attr:`ConeParams.cosine_sums`: each sample
    entered its cone's sum weighted by its cosine to the entry's normal) divided by the mean
    cosine :math:`\bar\mu_c` of the part of cone ``c`` above the horizon
    (:func:`slc.lib.cones.conestate.above_mean_cosine`; ``D``, ``A`` the cones' axes in the
    local frame and half-angles as the cycle leaves them). The cone's irradiance at the entry,
    :math:`L_c \bar\mu_c`, is then the samples' own estimate :math:`\sum w \cos\theta / n_s`
    however the caps overlap, where unweighted a cone spreads what the samples near its axis
    brought over its whole cap (docs/cones.md)."""
    return [S[i] * dr.rcp(dr.maximum(above_mean_cosine(D[i].z, A[i]), 1e-6)) for i in range(K)]


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
