"""A minimal stand-in for :class:`slc.osc.OnSurfaceCache`: one entry per pixel of
a fixed camera (slot = pixel index of the first G-buffer of frame 0).

It exists for the tests of the cone kernels (they must not depend on the OSC)
and mirrors the OSC's update policy: 8 rays for an entry's first 8 updates and
after reported motion, 1 ray otherwise. Only valid while every viewer keeps the
camera of frame 0 (static camera, any scene animation).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

INVALID = 0xFFFFFFFF


@dataclass
class PixelFrame:
    pixel_slot: list
    active: mi.UInt32
    si: mi.SurfaceInteraction3f
    rays: mi.UInt32
    is_new: mi.Bool
    seed_slot: mi.UInt32
    pixel_index: list      # per viewer: each pixel's index into ``active``


class PixelSlotCache:
    def __init__(self, rays_new: int = 8, rays_settled: int = 1, first_updates: int = 8):
        self.capacity = 0
        self.rays_new, self.rays_settled, self.first_updates = rays_new, rays_settled, first_updates
        self.entry_bytes = 36
        self._updates = None
        self._motion = None
        self._frames = 0

    def set_entry_bytes(self, b):
        self.entry_bytes = int(b)

    def begin_frame(self, frame, gbuffers, timer=None):
        gb = gbuffers[0]
        N = gb.size
        valid = mi.Bool(gb.valid)
        is_new_all = self._updates is None
        if is_new_all:
            self.capacity = N
            self._updates = dr.zeros(mi.UInt32, N)
            self._motion = dr.zeros(mi.UInt32, N)
        idx = dr.arange(mi.UInt32, N)
        active = dr.compress(valid)
        si = dr.gather(mi.SurfaceInteraction3f, gb.si, active)
        upd = dr.gather(mi.UInt32, self._updates, active)
        mot = dr.gather(mi.UInt32, self._motion, active)
        rays = dr.select((upd < self.first_updates) | (mot > 0), self.rays_new, self.rays_settled)
        is_new = upd == 0
        dr.scatter(self._updates, upd + 1, active)
        dr.scatter(self._motion, dr.select(mot > 0, mot - 1, 0), active)
        slots = [dr.select(mi.Bool(g.valid), idx, INVALID) for g in gbuffers]
        self._frames += 1
        # rank of each valid pixel among the valid ones = its index into ``active``
        rank = dr.zeros(mi.UInt32, N)
        dr.scatter(rank, dr.arange(mi.UInt32, dr.width(active)), active)
        index = [dr.select(mi.Bool(g.valid), rank, INVALID) for g in gbuffers]
        fr = PixelFrame(slots, active, si, mi.UInt32(rays), mi.Bool(is_new),
                        dr.full(mi.UInt32, INVALID, dr.width(active)), index)
        dr.eval(fr.active, fr.si, fr.rays, fr.is_new, self._updates, self._motion, *slots, *index)
        return fr

    def mark_motion(self, slots, mask):
        # motion -> the next first_updates updates use rays_new again
        dr.scatter(self._motion, mi.UInt32(self.first_updates), mi.UInt32(slots), mi.Bool(mask))

    def memory_bytes(self):
        return self.capacity * self.entry_bytes

    def stats(self):
        return {"entries": self.capacity}
