"""Light samples at cache entries with the emitter they came from and the
statistics every representation gathers from them (docs/adaptive.md)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import emitter_sampling


def lum(c):
    return 0.212671 * c[0] + 0.715160 * c[1] + 0.072169 * c[2]


def sampler_of(scene: mi.Scene):
    """The scene's emitter table (built outside any kernel; see
    :func:`slc.emitter_sampling.for_scene`). The adaptive cache needs the
    emitter index of every sample, so it samples from the table whatever
    ``SLC_EMITTER_SAMPLING`` says; emitters the table does not model (spot,
    directional, environment) are sampled by Mitsuba inside it."""
    return emitter_sampling.for_scene(scene)


class SampleStats:
    """Per-entry sums of one update cycle: visible energy of delta-light
    samples ``ed``, of other samples ``en``, and ``m`` = sum of the other
    samples' energy times their local direction."""

    DRJIT_STRUCT = {"ed": mi.Float, "en": mi.Float, "m": mi.Vector3f}

    def __init__(self, n: int = 0):
        self.ed = dr.zeros(mi.Float, n)
        self.en = dr.zeros(mi.Float, n)
        self.m = dr.zeros(mi.Vector3f, n)

    def add(self, c, delta, d_local):
        c = dr.select(dr.isfinite(c), c, 0.0)
        self.ed = self.ed + dr.select(delta, c, 0.0)
        en = dr.select(delta, 0.0, c)
        self.en = self.en + en
        self.m = self.m + d_local * en
        return self

    def values(self):
        return [self.ed, self.en, self.m]

    @staticmethod
    def means(vals, rays):
        inv = dr.rcp(mi.Float(dr.maximum(mi.UInt32(rays), 1)))
        return vals[0] * inv, vals[1] * inv, vals[2] * inv
