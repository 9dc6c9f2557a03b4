"""Ray marching in the binary geometry volume (view-independent indirect
visibility, Sec. 6 of the CRC paper).

A ray is sampled at ``t = t0 + (k + jitter) * step`` for k = 0, 1, ... while
``t < t1``; it is blocked at the first sample inside a set voxel. ``step``
is either a fixed fraction of a voxel (``samples = 0``: dense marching, one
sample per voxel by default) or ``(t1 - t0) / samples`` (the paper's sparse,
fixed count: 8-12 samples for the first bounce, 4-6 for the secondary ones;
thin walls may then be missed).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.crc.grid import Grid


def voxel_set(geometry: mi.UInt32, geo: Grid, p: mi.Point3f, active: mi.Bool) -> mi.Bool:
    i = mi.Vector3i(dr.floor(geo.coords(p)))
    ok = active & geo.inside(i)
    return ok & (dr.gather(mi.UInt32, geometry, dr.select(ok, geo.flat(i), 0), ok) != 0)


def march(geometry: mi.UInt32, geo: Grid, o: mi.Point3f, d: mi.Vector3f, t0, t1, jitter: mi.Float,
          active: mi.Bool, samples: int = 0, step_voxels: float = 1.0):
    """(hit mask, hit distance) of the first set voxel along o + t d, t in [t0, t1)."""
    t0, t1 = mi.Float(t0), mi.Float(t1)
    if samples > 0:
        step = dr.maximum((t1 - t0) / float(samples), 1e-6)
    else:
        step = mi.Float(geo.h * float(step_voxels))
    t = t0 + jitter * step

    def cond(t, hit, th):
        return active & ~hit & (t < t1)

    def body(t, hit, th):
        m = active & ~hit & (t < t1)
        h = voxel_set(geometry, geo, o + t * d, m)
        th = dr.select(h, t, th)
        return t + step, hit | h, th

    _, hit, th = dr.while_loop(state=(t, mi.Bool(False), mi.Float(dr.inf)), cond=cond, body=body,
                               labels=("t", "hit", "th"))
    return hit, th


def visible(geometry: mi.UInt32, geo: Grid, a: mi.Point3f, b: mi.Point3f, jitter: mi.Float, active: mi.Bool,
            start_offset: float, end_offset: float, samples: int = 0, step_voxels: float = 1.0) -> mi.Bool:
    """Visibility between points a and b; the first ``start_offset`` and the
    last ``end_offset`` world units of the segment are skipped (self-occlusion
    of the cache point's and of the sample's own voxels)."""
    v = b - a
    dist = dr.norm(v)
    d = v / dr.maximum(dist, 1e-12)
    t1 = dist - end_offset
    ok = active & (t1 > start_offset)
    hit, _ = march(geometry, geo, a, d, start_offset, t1, jitter, ok, samples, step_voxels)
    return active & ~hit
