"""osc-gi's primary kernels: the entries' cache rays, their light samples binned into texels, and
the per-pixel direct light. Pure functions of their inputs, traced once and replayed by
:class:`slc.core.freeze.FrozenFunction` in :class:`~slc.methods.oscgi.method.OSCGI`."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import mixed_rng
from slc.scene.lights import SurfaceBSDF, direct_sample, sample_light, visible
from slc.methods.oscgi.hemisphere import HemiGrid

STREAM_PRIMARY = 0x05C61001
STREAM_PRIMARY_DIRECT = 0x05C61002
STREAM_SHADE = 0x05C61003
STREAM_GLOSSY = 0x05C61004
STREAM_PIXEL_DIRECT = 0x05C61005


def primary_ray_kernel(pts, keys, tl, mix, D: int, res: int):
    """The jittered cosine rays of the traced lanes ``tl`` (entry tl // D, texel tl % D) from the
    entries' own points ``pts`` = (position, geometric normal, shading normal); returns (rays, mask
    above the geometric surface). Only these three fields of the entries' interactions are inputs:
    passing the whole interaction made the frozen function record again when the sharing of its
    unused literal fields (``dn_du``, ``dn_dv``) with other fields changed between frames."""
    G = HemiGrid(res)
    et, kt = tl // D, tl % D
    si = dr.zeros(mi.SurfaceInteraction3f)   # only what spawn_ray needs; width 1 (a width would be baked)
    si.p = mi.Point3f(*[dr.gather(mi.Float, pts[0][c], et) for c in range(3)])
    si.n = mi.Vector3f(*[dr.gather(mi.Float, pts[1][c], et) for c in range(3)])
    n_sh = mi.Vector3f(*[dr.gather(mi.Float, pts[2][c], et) for c in range(3)])
    s = mixed_rng(dr.gather(mi.UInt32, keys, et) * D + kt, mix)
    d = mi.Frame3f(n_sh).to_world(G.direction(kt, mi.Point2f(s.next_float32(), s.next_float32())))
    ok = dr.dot(d, si.n) > 0.0                      # above the geometric surface
    ray = si.spawn_ray(d)
    dr.eval(ray, ok)
    return ray, ok


def primary_direct_kernel(sc, lights, sie, keys, scratch, mix, nd, scale: float, res: int):
    """``nd`` (opaque) light samples per entry (the project's light sampling, shadow rays) binned
    into the texels of their directions, added to ``scratch`` (3 words per entry and texel;
    returned); ``lights`` declares the emitter table as an input."""
    G = HemiGrid(res)
    D = G.n
    frame_e = mi.Frame3f(sie.sh_frame.n)
    base = dr.arange(mi.UInt32, dr.width(keys)) * D
    sd = mixed_rng(keys, mix)

    def cond(i, sd):
        return i < nd

    def body(i, sd):
        u = mi.Point2f(sd.next_float32(), sd.next_float32())
        ds, w, okd = sample_light(sc, sie, u, mi.Bool(True))
        loc = frame_e.to_local(ds.d)
        okd &= (dr.dot(ds.d, sie.n) > 0.0) & (loc.z > 0.0) & dr.all(dr.isfinite(w))
        okd = visible(sc, sie, ds, okd)
        t = (base + G.texel(loc)) * 3
        for c in range(3):
            # Direct: the default (Expand) bakes the size of scratch into the kernel
            dr.scatter_add(scratch, w[c] * loc.z * scale, t + c, okd, mode=dr.ReduceMode.Direct)
        return i + 1, sd

    dr.while_loop(state=(mi.UInt32(0), sd), cond=cond, body=body, labels=("i", "sd"))
    dr.eval(scratch)
    return scratch


def pixel_direct_kernel(sc, lights, table, si, active, idx, mix, n, lds):
    r"""RT-N direct light of the pixels ``si``: ``n`` (opaque) light samples with shadow rays,
    :math:`\frac1n\sum_j f\,L_e G V / p` (:func:`slc.scene.lights.direct_sample`); ``idx`` the pixels'
    stream keys (their width is the launch width), ``lights`` and ``table`` (the diffuse-BSDF table of
    :class:`slc.scene.lights.SurfaceBSDF`) declare what the kernel reads as inputs.

    ``lds`` (a Python bool, part of the recording's key): the n sample points of a pixel are the Hammersley set
    :math:`((j + \tfrac12)/n,\ \Phi_2(j))` shifted by one random offset r per pixel (Cranley-Patterson
    rotation, :math:`u_j = (h_j + r) \bmod 1`): each :math:`u_j` alone is uniform (unbiased), and
    together they cover the unit square (the light's area, and the emitter choice by
    :math:`u_x`) evenly; else n independent uniform points."""
    sampler = mixed_rng(idx, mix)
    ctx = mi.BSDFContext()
    bsdf = SurfaceBSDF(sc, si, active, ctx)
    inv_n = dr.rcp(mi.Float(dr.maximum(n, 1)))
    if lds:   # the pixel's offset, from its own stream (the independent samples keep theirs)
        rs = mixed_rng(idx, mix ^ STREAM_PIXEL_DIRECT)
        r = mi.Point2f(rs.next_float32(), rs.next_float32())

    def cond(i, L, sampler):
        return i < n

    def body(i, L, sampler):
        if lds:
            # ---- Hammersley point i, rotated by the pixel's offset (radical inverse: bit reversal) ----
            u = mi.Point2f(dr.fma(mi.Float(i), inv_n, 0.5 * inv_n), mi.Float(dr.brev(i)) * 2.3283064365386963e-10) + r
            u = dr.minimum(u - dr.floor(u), 0.99999994)
        else:
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        return i + 1, L + direct_sample(sc, si, bsdf, u, active, ctx), sampler

    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                labels=("i", "L", "sampler"))
    L = L * inv_n
    dr.eval(L)
    return L
