"""A minimal :class:`slc.osc.protocol.SurfaceCache`: one entry per pixel of a
fixed camera (slot = pixel index of the first G-buffer of frame 0).

It exists for the tests of the cone kernels (they must not depend on the
OSC): the entry of a pixel is the pixel's own surface point, so the cache's
resolution term of the error vanishes. Only valid while every viewer keeps
the camera of frame 0 (static camera, any scene animation). Entry keys are
the slots; no optional capability.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID
from slc.osc.protocol import FrameRequests


class PixelSlotCache:
    capabilities = frozenset()

    def __init__(self):
        self.reset()

    @property
    def capacity(self) -> int:
        return self._capacity

    def reset(self) -> None:
        self._capacity = 0
        self._seen = None

    def begin_frame(self, frame, gbuffers, timer=None) -> FrameRequests:
        gb = gbuffers[0]
        N = gb.size
        if self._seen is None:
            self._capacity = N
            self._seen = dr.zeros(mi.Bool, N)
        idx = dr.arange(mi.UInt32, N)
        active = dr.compress(mi.Bool(gb.valid))
        is_new = ~dr.gather(mi.Bool, self._seen, active)
        dr.scatter(self._seen, True, active)
        # rank of each valid pixel among the valid ones = its index into ``active``
        rank = dr.zeros(mi.UInt32, N)
        dr.scatter(rank, dr.arange(mi.UInt32, dr.width(active)), active)
        fr = FrameRequests(frame=frame, active=active, si=dr.gather(mi.SurfaceInteraction3f, gb.si, active),
                           is_new=is_new, seed_slot=dr.full(mi.UInt32, INVALID, dr.width(active)),
                           keys=mi.UInt32(active),
                           pixel_slot=[dr.select(mi.Bool(g.valid), idx, INVALID) for g in gbuffers],
                           pixel_index=[dr.select(mi.Bool(g.valid), rank, INVALID) for g in gbuffers])
        dr.eval(fr.active, fr.si, fr.is_new, fr.keys, self._seen, *fr.pixel_slot, *fr.pixel_index)
        return fr

    def entries_allocated(self) -> int:
        return self._capacity

    def memory_bytes(self) -> int:
        return 0

    def stats(self) -> dict:
        return {"entries": self._capacity}
