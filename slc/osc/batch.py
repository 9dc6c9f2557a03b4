"""Every viewer's pixels laid out one after another for one shading launch (:class:`PixelBatch`),
as a multi-view renderer's layered G-buffer holds them: a cache method that shades all viewers
at once (:meth:`slc.methods.cache_method.PayloadMethod.shade_all`) maps each pixel to its entry, keys its
random numbers by its index within its own viewer (so the images are the per-viewer ones) and
splits the result per viewer."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID
from slc.osc.protocol import FrameRequests
from slc.scene.gbuffer import viewer_lanes


@dataclass
class PixelBatch:
    """Every viewer's pixels one after another, for one shading launch (:func:`pixel_batch`):
    viewer ``v``'s pixels at ``lanes[v]``; per pixel its interaction ``si``, ``valid`` and
    ``active`` (valid with an entry) masks, ``pid`` (its index within its own viewer, which keys
    its random numbers as in a launch per viewer), ``viewer`` (its viewer's index), ``slot`` (its
    entry) and ``index`` (its entry's index into the frame's active entries)."""
    si: mi.SurfaceInteraction3f
    valid: mi.Bool
    active: mi.Bool
    pid: mi.UInt32
    viewer: mi.UInt32
    slot: mi.UInt32
    index: mi.UInt32
    lanes: list

    def split(self, out) -> list:
        """Each viewer's part of ``out`` (one value per pixel of the batch)."""
        return [dr.gather(type(out), out, at) for at in self.lanes]


def pixel_batch(owner, fr: FrameRequests, gbuffers) -> PixelBatch:
    """Every viewer's pixels laid out one after another: the frame's layered G-buffer
    (``gb.layers``, :func:`slc.scene.gbuffer.attach_layers`) when there is one, else the
    G-buffers concatenated here; the cache's slots laid out the same way (``fr.layer_slot``,
    ``fr.layer_index``) when it provides them, else concatenated here. ``owner`` (the method
    instance) keeps the lanes of each viewer and the per-pixel indices while the sizes hold (no
    opaque offset made per viewer and frame)."""
    lay = gbuffers[0].layers
    if lay is None or any(gb.layers is not lay or gb.layer != v for v, gb in enumerate(gbuffers)):
        lay = None
    sizes = [gb.size for gb in gbuffers]
    lanes, batch_pid, batch_viewer = _layout(owner, sizes)
    total = sum(sizes)
    own = fr.layer_slot is not None and fr.layer_index is not None
    slot = fr.layer_slot if own else dr.empty(mi.UInt32, total)
    index = fr.layer_index if own else dr.empty(mi.UInt32, total)
    if lay is None:
        si, valid, pid, viewer = dr.empty(mi.SurfaceInteraction3f, total), dr.empty(mi.Bool, total), \
            batch_pid, batch_viewer
    else:
        si, valid, pid = lay.si, lay.valid, lay.pixel
        viewer = lay.viewer if lay.viewer is not None else batch_viewer
    for v, gb in enumerate(gbuffers):
        if own and lay is not None:
            break
        at = lanes[v]
        if not own:
            dr.scatter(slot, mi.UInt32(fr.pixel_slot[v]), at)
            dr.scatter(index, mi.UInt32(fr.pixel_index[v]), at)
        if lay is None:
            dr.scatter(si, gb.si, at)
            dr.scatter(valid, mi.Bool(gb.valid), at)
    return PixelBatch(si, valid, valid & (slot != INVALID), pid, viewer, slot, index, lanes)


def _layout(owner, sizes):
    """Each viewer's lanes of a batched launch (:func:`slc.scene.gbuffer.viewer_lanes`), each
    batched pixel's index within its own viewer and its viewer's index, evaluated and kept on
    ``owner`` while the sizes hold."""
    key = tuple(sizes)
    cached = getattr(owner, "_layout_cache", None)
    if cached is None or cached[0] != key:
        offsets = [sum(sizes[:v]) for v in range(len(sizes))]
        lanes = [viewer_lanes(n, off) for n, off in zip(sizes, offsets)]
        pid, viewer = dr.empty(mi.UInt32, sum(sizes)), dr.empty(mi.UInt32, sum(sizes))
        for v, (n, at) in enumerate(zip(sizes, lanes)):
            dr.scatter(pid, dr.arange(mi.UInt32, n), at)
            dr.scatter(viewer, dr.opaque(mi.UInt32, v), at)
        dr.eval(lanes, pid, viewer)
        owner._layout_cache = cached = (key, lanes, pid, viewer)
    return cached[1], cached[2], cached[3]
