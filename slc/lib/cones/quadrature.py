r"""The MIS quadrature of the cone shading, for the pixels no closed form covers: cone sampling
(a stratified spherical-Fibonacci pattern in each live cone, rotated per pixel) and BSDF sampling
(a rank-1 R3 sequence, rotated per pixel) combined by the balance heuristic over all samples of a
pixel, with the split of the directions between the two strategies by the lobe's width against
the cones and the per-pixel random numbers. The estimator is derived in the docstring of
:mod:`slc.lib.cones.shading` and in docs/cones.md."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.lib.cones.conestate import ConeState, ShadeOptions

GOLDEN = 0.6180339887498949           # 1 / phi: azimuths of the spherical-Fibonacci pattern
R3 = 1.2207440846057596               # plastic constant of the 3-D Roberts (R3) sequence
B_MAX = 0.75                          # at most this share of the directions are BSDF samples
ROUGH_MIN = 0.25                      # rough lobes keep at least this share of the n_S directions per cone


def cone_samples(Dw, A, s_idx: mi.UInt32, nS: int):
    """Direction ``s_idx`` of ``nS`` of the fixed stratified pattern in cone (Dw, A) (world)."""
    return cone_direction(Dw, A, (mi.Float(s_idx) + 0.5) * (1.0 / nS), mi.Float(s_idx) * GOLDEN)


def cone_direction(Dw, A, u, x):
    """The direction of cone (Dw, A) at ``1 - cos(theta) = u (1 - cos A)`` and azimuth
    ``2 pi frac(x)``: uniform in the cone's solid angle for uniform ``u``."""
    ph = 2.0 * math.pi * (x - dr.floor(x))
    h = 2.0 * dr.square(dr.sin(0.5 * A))            # 1 - cos(alpha), precise for tiny alpha
    x = u * h                                       # 1 - cos(theta)
    ct = 1.0 - x
    st = dr.sqrt(dr.maximum(x * (2.0 - x), 0.0))
    sp, cp = dr.sincos(ph)
    return mi.Frame3f(Dw).to_world(mi.Vector3f(st * cp, st * sp, ct))


def _hash_float(pid: mi.UInt32, key: mi.UInt32, j: int) -> mi.Float:
    """Uniform float in [0, 1) from (pixel, key, stream j)."""
    v0, v1 = mi.sample_tea_32(pid, key ^ mi.UInt32((0x9E3779B9 * (j + 1)) & 0xFFFFFFFF), 4)
    return mi.Float(v0 >> 8) * (1.0 / 16777216.0)


def _frac(x):
    return x - dr.floor(x)


def samples_px(bsdf, n_total, glossy_half):
    """n_S per pixel: ``n_total``, halved for purely glossy BSDFs with ``glossy_half``."""
    n_px = mi.UInt32(n_total)
    if glossy_half:
        flags = mi.UInt32(bsdf.flags())
        glossy_only = mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) & \
            ~mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
            ~mi.has_flag(flags, mi.BSDFFlags.Transmission)
        n_px = dr.select(glossy_only, dr.maximum(n_px >> 1, 1), n_px)
    return n_px


@dataclass
class Allocation:
    """A pixel's directions split between the strategies: ``n_c`` cone directions per live cone
    and ``n_b`` BSDF directions per pixel, ``nc_f``, ``nb_f`` the same as floats and ``nc_rcp``
    the reciprocal of ``max(n_c, 1)``."""
    n_c: mi.UInt32
    n_b: mi.UInt32
    nc_f: mi.Float
    nb_f: mi.Float
    nc_rcp: mi.Float


def quadrature(bsdf, si, ctx, sampled, cones: ConeState, n_total, key, pid, opts: ShadeOptions):
    """The MIS quadrature of the pixels ``sampled`` (the module docstring): returns
    the sum over their cone and BSDF samples. Stages: the allocation of the directions
    (:func:`_allocation`), the per-pixel rotations, the cone samples (:func:`_cone_samples`),
    the BSDF samples (:func:`_bsdf_samples`)."""
    K = cones.K
    al = _allocation(bsdf, si, ctx, sampled, cones, n_total, opts)

    # ------------------- per-pixel rotations of the two patterns -------------------
    if opts.rotate:
        rot = [(_hash_float(pid, key, 2 * i), _hash_float(pid, key, 2 * i + 1)) for i in range(K)]
    else:
        rot = [(mi.Float(0.5), mi.Float(0.0)) for i in range(K)]
    rb = (_hash_float(pid, key, 2 * K), _hash_float(pid, key, 2 * K + 1), _hash_float(pid, key, 2 * K + 2))

    acc = _cone_samples(bsdf, si, ctx, sampled, cones, al, rot)
    return _bsdf_samples(bsdf, si, ctx, sampled, cones, al, rb, acc)


# ------------------- the cones' density at a direction, the balance heuristic -------------------
def _density(cones: ConeState, w, own=None):
    """(sum over cones holding w of L_c/Omega_c, of 1/Omega_c); cone ``own`` holds w."""
    Lt, dt = mi.Color3f(cones.zero), mi.Float(cones.zero)
    for j in range(cones.K):
        inside = cones.dense[j] & ((1.0 - dr.dot(w, cones.axis[j])) <= cones.h[j] * (1.0 + 1e-5) + 1e-7)
        if own == j:
            inside = cones.dense[j]
        Lt += dr.select(inside, cones.L[j] * cones.inv_omega[j], 0.0)
        dt += dr.select(inside, cones.inv_omega[j], 0.0)
    return Lt, dt


def _mis(al: Allocation, pdf_cones, pdf_b):
    """Balance heuristic: a sample's weight over its pdf, 1 / (n_C sum_c 1/Omega_c + n_B p_B)."""
    den = al.nc_f * pdf_cones + al.nb_f * pdf_b
    return dr.select(den > 0.0, dr.rcp(den), 0.0)


def _allocation(bsdf, si, ctx, sampled, cones: ConeState, n_total, opts: ShadeOptions) -> Allocation:
    """How narrow is the lobe against the cones? The split of the pixels' directions.

    q = p_B(r) max_c Omega_c, with r the mirror direction of w_o (the peak of a glossy lobe),
    compares the cone's solid angle with the lobe's (about 1 / p_B(r)). n_S cone directions
    are spaced about Omega / n_S apart: they resolve the lobe while q < n_S. Of the n_S
    directions per cone, n_B = round(n_S min(q / (q + n_S), 3/4)) are BSDF samples: none
    for rough lobes (a diffuse lobe has p_B <= 1/pi), up to three quarters for lobes far
    narrower than the cones; at least a quarter stay cone samples (a glossy coat's diffuse
    base, e.g. plastic, is cheaper by cone sampling). The allocation is fixed before any
    sample is drawn, so the MIS estimator stays unbiased for any q.

    Rough lobes (q < 1: the lobe is wider than the widest cone, so f_r cos varies little
    inside a cone) need fewer directions: n_S' = ceil(n_S clip(q, 1/4, 1)) per cone
    (at least a quarter of n_S). The BSDF directions are drawn per pixel, not per cone:
    their density does not depend on the cones, and a lobe narrower than the cones sees
    a nearly constant L~ whatever the cone count (docs/cones.md, "Per-viewer cost")."""
    ns_f = mi.Float(n_total)
    if opts.adaptive:
        om_max = mi.Float(cones.zero)
        for i in range(cones.K):
            om_max = dr.maximum(om_max, dr.select(cones.dense[i], 2.0 * math.pi * cones.h[i], 0.0))
        r = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
        q = bsdf.pdf(ctx, si, r, sampled) * om_max
        n_dir = dr.maximum(mi.UInt32(dr.ceil(ns_f * dr.clip(q, ROUGH_MIN, 1.0))), 1)
        nd_f = mi.Float(n_dir)
        n_b = mi.UInt32(dr.round(nd_f * dr.minimum(q / (q + nd_f), B_MAX)))
    else:
        n_dir = mi.UInt32(n_total)
        n_b = mi.UInt32(ns_f * 0.5)
    n_b = dr.minimum(n_b, n_dir - 1)                                      # n_C >= 1: Dirac cones need it
    n_c = n_dir - n_b
    nc_f, nb_f = mi.Float(n_c), mi.Float(n_b)                             # per cone / per pixel
    return Allocation(n_c, n_b, nc_f, nb_f, dr.rcp(dr.maximum(nc_f, 1.0)))


def _cone_samples(bsdf, si, ctx, sampled, cones: ConeState, al: Allocation, rot) -> mi.Color3f:
    """Cone sampling: ``n_C`` directions in each live cone, pattern direction j of every live
    cone in iteration j (the cones unrolled: measured 30 % cheaper than one loop over all
    (cone, j) pairs with a single BSDF call site). A Dirac cone is evaluated once, on its axis.
    ``rot``: the per-pixel rotation of each cone's pattern."""
    K, A, L, Dw, live, delta = cones.K, cones.alpha, cones.L, cones.axis, cones.live, cones.dirac
    n_c, nc_rcp = al.n_c, al.nc_rcp

    def cone_cond(j, acc):
        return (j < n_c) & sampled

    def cone_body(j, acc):
        jf = mi.Float(j)
        for i in range(K):
            u = _frac((jf + rot[i][0]) * nc_rcp)
            wi = dr.select(delta[i], Dw[i], cone_direction(Dw[i], A[i], u, jf * GOLDEN + rot[i][1]))
            m = sampled & live[i] & (~delta[i] | (j == 0))
            f, pdf_b = bsdf.eval_pdf(ctx, si, si.to_local(wi), m)
            Lt, dt = _density(cones, wi, own=i)
            w = dr.select(delta[i], L[i], Lt * _mis(al, dt, pdf_b))
            acc += dr.select(m, mi.Color3f(f) * w, 0.0)
        return j + 1, acc

    _, acc = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(cones.zero)), cond=cone_cond, body=cone_body,
                           labels=("j", "acc"))
    return acc


def _bsdf_samples(bsdf, si, ctx, sampled, cones: ConeState, al: Allocation, rb, acc: mi.Color3f) -> mi.Color3f:
    """BSDF sampling: ``n_B`` directions per pixel from the rank-1 R3 sequence rotated by ``rb``,
    added to ``acc``."""
    n_b, nb_f = al.n_b, al.nb_f

    def bsdf_cond(t, acc):
        return (t < n_b) & sampled

    def bsdf_body(t, acc):
        k = mi.Float(t)
        u1 = _frac(rb[0] + k * (1.0 / R3))
        u2 = mi.Point2f(_frac(rb[1] + k * (1.0 / R3 ** 2)), _frac(rb[2] + k * (1.0 / R3 ** 3)))
        bs, bw = bsdf.sample(ctx, si, u1, u2, sampled)
        wi = si.to_world(bs.wo)
        ok = sampled & (bs.pdf > 0.0)
        Lt, dt = _density(cones, wi)
        dirac = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        # bw = f cos / p_B, so the sample's f cos Lt / den is bw * p_B * Lt / den;
        # a Dirac lobe cannot be reached by cone sampling: weight 1 / n_B
        w = dr.select(dirac, dr.rcp(dr.maximum(nb_f, 1.0)), bs.pdf * _mis(al, dt, bs.pdf))
        acc += dr.select(ok, mi.Color3f(bw) * Lt * w, 0.0)
        return t + 1, acc

    _, acc = dr.while_loop(state=(mi.UInt32(0), acc), cond=bsdf_cond, body=bsdf_body, labels=("t", "acc"))
    return acc
