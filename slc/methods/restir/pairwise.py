"""Spatial reuse of ReSTIR with pairwise MIS weights (``restir:bias=pairwise``,
the default): the resampling weights and the two neighbour passes."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.structs import drjit_struct
from slc.methods.restir.reservoir import Reservoir, Stream, share
from slc.scene.lights import rng


@drjit_struct
@dataclass
class AcceptLoop:
    """The state of pass 1 (one lane per pixel): ``i`` the neighbours drawn, ``smp`` the
    random numbers of the neighbour sequence, ``K`` the number and ``M_n`` the summed
    confidence of the accepted neighbours, ``used`` their bit mask."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)
    K: mi.Float = field(default_factory=mi.Float)
    M_n: mi.Float = field(default_factory=mi.Float)
    used: mi.UInt32 = field(default_factory=mi.UInt32)


@drjit_struct
@dataclass
class PairwiseLoop:
    """The state of pass 2 (one lane per pixel): ``i`` the neighbours replayed, ``smp`` and
    ``sel`` the random numbers of the neighbour sequence and of the selection, ``st`` the
    reservoir being filled, ``m_c`` the canonical reservoir's MIS weight summed over the pairs."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)
    sel: mi.PCG32 = field(default_factory=mi.PCG32)
    st: Stream = field(default_factory=Stream)
    m_c: mi.Float = field(default_factory=mi.Float)


def spatial_pairwise(reuse, gb, r: Reservoir, p_cur, k, R: float, seed: int):
    """Spatial reuse with pairwise MIS (Bitterli 2022, Lin et al. 2022),
    M-weighted: the current (canonical) reservoir c and each of the K
    accepted neighbours i form a pair that holds the share
    f_i = (M_i + M_c / K) / (M_c + sum_j M_j) of the total M; within the
    pair, the balance heuristic of M_i p_i and (M_c / K) p_c:

        m_i(y) = f_i M_i p_i(y) / (M_i p_i(y) + M_c / K p_c(y)),
        m_c(y) = sum_i f_i (M_c / K) p_c(y) / (M_i p_i(y) + M_c / K p_c(y)),

    which sum to 1 wherever p_c(y) > 0 (m_c = 1 without neighbours).
    Resampling weights w = m(y) p_c(y) W, W = sum w / p_c(y_selected).
    A neighbour's sample that its own target rates low gets a small
    weight even where the current target is large; with the 1/Z weights
    of ``basic`` it is w = p_c(y) W M, unbounded as p_c / p_i grows.

    Pass 1 finds the accepted neighbours (bit mask, count K, sum of M);
    pass 2 replays them and resamples, three target evaluations per
    neighbour: p_c(y_i), p_i(y_i) and p_i(y_c)."""
    n = gb.size
    si, active = gb.si, gb.valid
    bsdf = si.bsdf()

    # ---------------- Pass 1: accepted neighbours ----------------
    def body(s: AcceptLoop):
        _, ok, rq = reuse.accepted_neighbour(s.smp, gb, r, R)
        s.used = s.used | dr.select(ok, mi.UInt32(1) << s.i, 0)
        s.K = s.K + dr.select(ok, 1.0, 0.0)
        s.M_n = s.M_n + dr.select(ok, rq.M, 0.0)
        s.i = s.i + 1
        return (s,)

    s, = dr.while_loop(
        state=(AcceptLoop(mi.UInt32(0), rng(n, seed, stream=13), mi.Float(0.0), mi.Float(0.0), mi.UInt32(0)),),
        cond=lambda s: s.i < k, body=body, labels=("accepted",))
    K, M_n, used = s.K, s.M_n, s.used
    M = r.M + M_n
    Mc_K = r.M / dr.select(K > 0.0, K, 1.0)
    inv_total = dr.select(M > 0.0, dr.rcp(dr.select(M > 0.0, M, 1.0)), 0.0)

    # ---------------- Pass 2: pairwise MIS resampling ----------------
    st = Stream(n)
    k2 = dr.select(active, 32 - dr.lzcnt(used), 0)
    c_ok = active & (r.W > 0.0)

    def body2(s: PairwiseLoop):
        q, _ = reuse.neighbour(s.smp, *reuse.pixel_xy(n, gb.width), R, gb.width, gb.height)
        ok = ((used >> s.i) & 1) != 0
        rq = dr.gather(Reservoir, r, q, ok)
        si_q = dr.gather(mi.SurfaceInteraction3f, si, q, ok)
        bsdf_q = si_q.bsdf()
        has = ok & (rq.W > 0.0)
        _, p_c_i, _, _, _, _ = reuse.target.evaluate(si, bsdf, rq.y, rq.n, rq.light, has)
        _, p_i_i, _, _, _, _ = reuse.target.evaluate(si_q, bsdf_q, rq.y, rq.n, rq.light, has)
        _, p_i_c, _, _, _, _ = reuse.target.evaluate(si_q, bsdf_q, r.y, r.n, r.light, ok & c_ok)
        f = (rq.M + Mc_K) * inv_total
        m_i = f * share(rq.M * p_i_i, Mc_K * p_c_i)
        s.st.update(rq.y, rq.n, rq.light, p_c_i, m_i * p_c_i * rq.W, s.sel.next_float32(), has)
        s.m_c = s.m_c + dr.select(ok, f * share(Mc_K * p_cur, rq.M * p_i_c), 0.0)
        s.i = s.i + 1
        return (s,)

    s, = dr.while_loop(
        state=(PairwiseLoop(mi.UInt32(0), rng(n, seed, stream=13), rng(n, seed, stream=14), st, mi.Float(0.0)),),
        cond=lambda s: s.i < k2, body=body2, labels=("pairwise",))
    sel, st, m_c = s.sel, s.st, s.m_c
    m_c = dr.select(K > 0.0, m_c, 1.0)
    st.update(r.y, r.n, r.light, p_cur, m_c * p_cur * r.W, sel.next_float32(), c_ok)
    return st.finalize(mi.Float(1.0), M, active), st.p_hat
