"""Lane helpers of the adaptive cache's update and shading: the lanes of a mask as an index
list whose kernels keep one IR whatever the lane count (:func:`subset`), the true lanes of
several masks counted in one queued array and read back with one wait (:func:`count_hist`,
:func:`tally`), header fields evaluated to memory (:func:`opaque_header`) and the per-ray means
of an update's sums (:func:`means`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.adaptive.choice import Header


def subset(mask: mi.Bool):
    """Lanes of ``mask`` as an index list of width >= 2 (a repeated lane, or two
    masked lanes when there is none: every kernel runs, with the same IR, in
    every frame, so none is first built after warm-up), and its lane mask."""
    idx = dr.compress(mask)
    n = dr.width(idx)
    if n >= 2:
        return idx, dr.opaque(mi.Bool, True, n), n
    if n == 1:
        i0 = int(idx[0])          # a width-1 array would enter kernels as a scalar: another IR
        return mi.UInt32([i0, i0]), dr.opaque(mi.Bool, True, 2), 1
    return dr.opaque(mi.UInt32, 0, 2), dr.opaque(mi.Bool, False, 2), 0


def count_hist(masks) -> mi.UInt32:
    """The number of true lanes of each mask (same width) as a queued array
    (read back by :func:`tally`)."""
    hist = dr.zeros(mi.UInt32, max(len(masks), 2))     # width >= 2: never loaded as a scalar
    for i, m in enumerate(masks):
        dr.scatter_reduce(dr.ReduceOp.Add, hist, mi.UInt32(1), mi.UInt32(i), mi.Bool(m))
    return hist


def tally(masks, hist=None) -> list:
    """The number of true lanes of each mask, read back together: one wait for
    the queued kernels instead of one per mask (``hist``: :func:`count_hist` of
    ``masks`` queued earlier)."""
    hist = count_hist(masks) if hist is None else hist
    return [int(x) for x in hist.numpy()[:len(masks)]]


def opaque_header(h: Header) -> None:
    """Evaluate every header field to memory (literals too: see
    :meth:`slc.methods.adaptive.method.AdaptiveCache.update`)."""
    dr.make_opaque(h.tag, h.streak, h.count, h.e, h.slot, h.s_delta, h.m)


def means(ed, en, mv, rays):
    inv = dr.rcp(mi.Float(dr.maximum(mi.UInt32(rays), 1)))
    return ed * inv, en * inv, mv * inv
