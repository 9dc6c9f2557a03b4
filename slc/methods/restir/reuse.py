"""The reuse stages of ReSTIR (:class:`Reuse`, held by :class:`slc.methods.restir.method.ReSTIR`
as ``reuse``): temporal reuse of the previous frame's reservoir
through the motion vectors, spatial reuse of neighbouring pixels' reservoirs with the ``basic`` and
``off`` weights (``pairwise``: :func:`slc.methods.restir.pairwise.spatial_pairwise`), and the
neighbour sequence and similarity test both stages share."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.structs import drjit_struct
from slc.scene.lights import rng
from slc.methods.restir.pairwise import spatial_pairwise
from slc.methods.restir.reservoir import Reservoir, Stream, share
from slc.methods.restir.target import AREA


@drjit_struct
@dataclass
class NeighbourLoop:
    """The state of the spatial resampling loop (one lane per pixel): ``i`` the neighbours
    drawn, ``smp`` and ``sel`` the random numbers of the neighbour sequence and of the
    selection, ``st`` the reservoir being filled, ``M`` the sum of the reused confidences and
    ``used`` the bit mask of the accepted neighbours."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    smp: mi.PCG32 = field(default_factory=mi.PCG32)
    sel: mi.PCG32 = field(default_factory=mi.PCG32)
    st: Stream = field(default_factory=Stream)
    M: mi.Float = field(default_factory=mi.Float)
    used: mi.UInt32 = field(default_factory=mi.UInt32)


class Reuse:
    """Temporal and spatial reuse of :class:`~slc.methods.restir.method.ReSTIR` reservoirs.

    Parameters: ``target`` (:class:`~slc.methods.restir.target.LightTarget`: the target function
    p_hat and the emitter kinds), ``temporal`` (temporal reuse on/off), ``mcap`` (temporal M cap),
    ``depth_thr`` (relative depth threshold), ``normal_thr`` (normal threshold, a cosine),
    ``spatial`` (spatial neighbours), ``radius`` (spatial radius in pixels at 1080p, scaled by
    height / 1080, at least 2 px), ``boost`` (spatial neighbours where history was rejected) and
    ``bias`` (reuse weights: ``pairwise``, ``basic`` or ``off``), as ReSTIR's settings."""

    def __init__(self, target, *, temporal: int, mcap: float, depth_thr: float, normal_thr: float,
                 spatial: int, radius: float, boost: int, bias: str):
        self.target = target
        self.temporal, self.mcap = temporal, mcap
        self.depth_thr, self.normal_thr = depth_thr, normal_thr
        self.spatial, self.radius, self.boost, self.bias = spatial, radius, boost, bias

    # ------------------------------ Stage 2: temporal ------------------------------

    def similar(self, n_a, n_b, depth_a, depth_b):
        """RTXDI's neighbour test: relative depth and normal thresholds."""
        depth_ok = dr.abs(depth_b - depth_a) <= self.depth_thr * dr.maximum(depth_a, 1e-6)
        return depth_ok & (dr.dot(n_a, n_b) >= self.normal_thr)

    def temporal_reuse(self, gb, r: Reservoir, p_cur, prev, moved, seed: int):
        """Merge the previous frame's reservoir; returns (reservoir, reused mask)."""
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        if prev is None:
            return r, dr.zeros(mi.Bool, n), p_cur
        r_prev_all, gb_prev = prev
        W_, H_ = gb.width, gb.height
        sampler = rng(n, seed, stream=12)

        # ---------------- Reprojection (nearest pixel) ----------------
        idx = dr.arange(mi.UInt32, n)
        px = mi.Float(idx % W_) + 0.5 + gb.motion.x
        py = mi.Float(idx // W_) + 0.5 + gb.motion.y
        qx, qy = mi.Int32(dr.floor(px)), mi.Int32(dr.floor(py))
        inb = (qx >= 0) & (qy >= 0) & (qx < W_) & (qy < H_)
        q = mi.UInt32(dr.select(inb, qy * W_ + qx, 0))
        ok = active & inb & dr.gather(mi.Bool, gb_prev.valid, q, active & inb)
        si_p = dr.gather(mi.SurfaceInteraction3f, gb_prev.si, q, ok)
        cam_o = mi.Point3f(*[dr.opaque(mi.Float, float(c)) for c in gb_prev.camera.origin])
        expected = dr.norm(si.p - cam_o)
        ok &= self.similar(si.sh_frame.n, si_p.sh_frame.n, expected, dr.gather(mi.Float, gb_prev.depth, q, ok))
        rp = dr.gather(Reservoir, r_prev_all, q, ok)
        ok &= ~(dr.gather(mi.Bool, moved, rp.light, ok)
                & (dr.gather(mi.UInt32, self.target.kinds, rp.light, ok) == AREA))
        ok &= rp.M > 0.0
        M_p = dr.select(ok, dr.minimum(rp.M, self.mcap), 0.0)

        # ---------------- Resampling: current + history ----------------
        st = Stream(n)
        M = r.M + M_p
        _, p_here, _, _, _, _ = self.target.evaluate(si, bsdf, rp.y, rp.n, rp.light, ok & (rp.W > 0.0))
        if self.bias == "pairwise":
            # balance heuristic over the two reservoirs' targets, weighted by their M:
            # m_c(y) = M_c p_c(y) / (M_c p_c(y) + M_p p_p(y)), m_p(y) = 1 - m_c(y)
            bsdf_p = si_p.bsdf()
            _, p_pp, _, _, _, _ = self.target.evaluate(si_p, bsdf_p, rp.y, rp.n, rp.light, ok & (rp.W > 0.0))
            _, p_pc, _, _, _, _ = self.target.evaluate(si_p, bsdf_p, r.y, r.n, r.light, ok & (r.W > 0.0))
            m_c = share(r.M * p_cur, dr.select(ok, M_p * p_pc, 0.0))
            m_p = share(M_p * p_pp, r.M * p_here)
            st.update(r.y, r.n, r.light, p_cur, m_c * p_cur * r.W, sampler.next_float32(), active)
            st.update(rp.y, rp.n, rp.light, p_here, m_p * p_here * rp.W, sampler.next_float32(), ok)
            return st.finalize(mi.Float(1.0), M, active), ok, st.p_hat
        st.update(r.y, r.n, r.light, p_cur, p_cur * r.W * r.M, sampler.next_float32(), active)
        st.update(rp.y, rp.n, rp.light, p_here, p_here * rp.W * M_p, sampler.next_float32(), ok)

        # ---------------- Bias correction ----------------
        if self.bias == "off":
            Z = M
        else:
            Z = dr.select(st.p_hat > 0.0, r.M, 0.0)
            bsdf_p = si_p.bsdf()
            # only where a sample was selected (W = 0 otherwise, whatever Z)
            sel = ok & (st.p_hat > 0.0) & (st.w_sum > 0.0)
            _, p_prev, _, _, _, _ = self.target.evaluate(si_p, bsdf_p, st.y, st.n, st.light, sel)
            Z += dr.select(sel & (p_prev > 0.0), M_p, 0.0)
        return st.finalize(Z, M, active), ok, st.p_hat

    # ------------------------------ Stage 3: spatial ------------------------------

    def neighbour(self, smp, x0, y0, R: float, W_: int, H_: int):
        """Next neighbour of the sequence ``smp``: a pixel uniform in the disk
        of radius ``R`` around (x0, y0), rounded; (index, in-bounds mask).
        The pixel itself does not count as a neighbour."""
        u1, u2 = smp.next_float32(), smp.next_float32()
        rad = R * dr.sqrt(u1)
        phi = 2.0 * math.pi * u2
        qx = x0 + mi.Int32(dr.round(rad * dr.cos(phi)))
        qy = y0 + mi.Int32(dr.round(rad * dr.sin(phi)))
        inb = (qx >= 0) & (qy >= 0) & (qx < W_) & (qy < H_) & ((qx != x0) | (qy != y0))
        return mi.UInt32(dr.select(inb, qy * W_ + qx, 0)), inb

    def spatial_reuse(self, gb, r: Reservoir, p_cur, reused, seed: int):
        """Merge neighbours' reservoirs (read from the temporal output ``r``).

        Two symbolic loops over a per-pixel neighbour count ``k``. With
        ``bias=pairwise`` see :func:`slc.methods.restir.pairwise.spatial_pairwise`. Otherwise the first
        resamples and records the accepted neighbours in a bit mask, the
        second (``bias=basic``) replays the same neighbour sequence up to
        the last accepted one and sums Z over the accepted neighbours whose
        surface has p_hat(y) > 0 for the selected y."""
        n = gb.size
        si, active = gb.si, gb.valid
        bsdf = si.bsdf()
        W_, H_ = gb.width, gb.height
        R = max(self.radius * H_ / 1080.0, 2.0)
        x0, y0 = self.pixel_xy(n, W_)

        # ---------------- Per-pixel neighbour count ----------------
        # spatial everywhere; max(spatial, boost) where temporal history was
        # rejected (disocclusion boost); none on invalid pixels.
        k = dr.full(mi.UInt32, self.spatial, n)
        if self.temporal and self.boost > self.spatial:
            k = dr.select(reused, k, self.boost)
        k = dr.select(active, k, 0)
        if self.bias == "pairwise":
            return spatial_pairwise(self, gb, r, p_cur, k, R, seed)

        # ---------------- Pass 1: resampling self + neighbours ----------------
        sel = rng(n, seed, stream=14)
        st = Stream(n)
        st.update(r.y, r.n, r.light, p_cur, p_cur * r.W * r.M, sel.next_float32(), active)
        M = mi.Float(r.M)

        def body(s: NeighbourLoop):
            q, ok, rq = self.accepted_neighbour(s.smp, gb, r, R)
            # the target is only needed for a non-zero resampling weight; M counts regardless
            _, p_here, _, _, _, _ = self.target.evaluate(si, bsdf, rq.y, rq.n, rq.light, ok & (rq.W > 0.0))
            s.st.update(rq.y, rq.n, rq.light, p_here, p_here * rq.W * rq.M, s.sel.next_float32(), ok)
            s.M = s.M + dr.select(ok, rq.M, 0.0)
            s.used = s.used | dr.select(ok, mi.UInt32(1) << s.i, 0)
            s.i = s.i + 1
            return (s,)

        s, = dr.while_loop(state=(NeighbourLoop(mi.UInt32(0), rng(n, seed, stream=13), sel, st, M, mi.UInt32(0)),),
                           cond=lambda s: s.i < k, body=body, labels=("neighbours",))
        st, M, used = s.st, s.M, s.used

        # ---------------- Pass 2: bias correction (replay the neighbours) ----------------
        if self.bias == "off":
            Z = M
        else:
            Z = dr.select(st.p_hat > 0.0, r.M, 0.0)
            # Only up to the last accepted neighbour, only where a sample was selected
            k2 = dr.select(active & (st.p_hat > 0.0) & (st.w_sum > 0.0), 32 - dr.lzcnt(used), 0)
            y_s, n_s, l_s = mi.Point3f(st.y), mi.Vector3f(st.n), mi.UInt32(st.light)

            def body_z(i, smp, Z):
                q, _ = self.neighbour(smp, x0, y0, R, W_, H_)
                ok = ((used >> i) & 1) != 0
                Mq = dr.gather(mi.Float, r.M, q, ok)
                si_q = dr.gather(mi.SurfaceInteraction3f, si, q, ok)
                _, p_q, _, _, _, _ = self.target.evaluate(si_q, si_q.bsdf(), y_s, n_s, l_s, ok)
                return i + 1, smp, Z + dr.select(ok & (p_q > 0.0), Mq, 0.0)

            _, _, Z = dr.while_loop(state=(mi.UInt32(0), rng(n, seed, stream=13), Z),
                                    cond=lambda i, *_: i < k2, body=body_z, labels=("i", "smp", "Z"))
        return st.finalize(Z, M, active), st.p_hat

    def accepted_neighbour(self, smp, gb, r: Reservoir, R: float):
        """Next neighbour of the sequence ``smp`` (see :meth:`neighbour`) and
        whether it is reused: valid, similar depth and normal, M > 0; (index,
        mask, its reservoir)."""
        W_, H_ = gb.width, gb.height
        n0 = mi.Vector3f(gb.si.sh_frame.n)
        q, ok = self.neighbour(smp, *self.pixel_xy(gb.size, W_), R, W_, H_)
        ok &= dr.gather(mi.Bool, gb.valid, q, ok)
        ok &= self.similar(n0, dr.gather(mi.Vector3f, n0, q, ok), gb.depth, dr.gather(mi.Float, gb.depth, q, ok))
        rq = dr.gather(Reservoir, r, q, ok)
        return q, ok & (rq.M > 0.0), rq

    @staticmethod
    def pixel_xy(n: int, width: int):
        """Pixel coordinates (x, y) of the ``n`` pixels of a ``width``-wide image."""
        idx = dr.arange(mi.UInt32, n)
        return mi.Int32(idx % width), mi.Int32(idx // width)
