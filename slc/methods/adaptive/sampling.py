"""Light samples at cache entries with the emitter they came from and the
statistics every representation gathers from them (docs/adaptive.md)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.lib.sh.shading import diffuse_only
from slc.scene import emitter_sampling
from slc.scene.bsdf_table import facing
from slc.lib.cones.cycle import SampleObserver


def lum(c):
    return 0.212671 * c[0] + 0.715160 * c[1] + 0.072169 * c[2]


def sampler_of(scene: mi.Scene):
    """The scene's emitter table (built outside any kernel; see
    :func:`slc.scene.emitter_sampling.for_scene`). The adaptive cache needs the
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

    @classmethod
    def of(cls, values) -> "SampleStats":
        """The statistics from :meth:`values`' list."""
        st = cls()
        st.ed, st.en, st.m = values
        return st

    @staticmethod
    def means(vals, rays):
        inv = dr.rcp(mi.Float(dr.maximum(mi.UInt32(rays), 1)))
        return vals[0] * inv, vals[1] * inv, vals[2] * inv


class LightStats(SampleObserver):
    """The choice rule's statistics (:class:`SampleStats`) of an update cycle's light
    samples at the entries ``si``, the one observer of the three representations. A
    sample's energy is ``lum(w) max(s_z, 0)`` where it is visible (``s`` its direction in
    the entry's frame; ``|s_z|`` on the ``two`` lanes, entries on two-sided BSDFs, whose
    pixels see either side), and it counts as delta-light energy (:meth:`listable`) where a
    VISIBILITY record could list its light (the sky only at entries on a diffuse-only BSDF)."""

    def __init__(self, scene, si, sph=None, env=None, two=None):
        self.si, self.sph, self.env, self.two = si, sph, env, two
        if env is not None and env.has_sky:
            self.diffuse = diffuse_only(si.bsdf())
        self.samp = sampler_of(scene) if (sph is not None or env is not None) else None

    def init(self, n: int) -> SampleStats:
        return SampleStats(n)

    def listable(self, ds, ok):
        """Samples of a light a VISIBILITY record lists: a delta light, a sphere light small
        at the entry (``sph``, :mod:`slc.lib.lights.sphere_lights`), a bright region of the
        environment wholly above the entry's horizon or the rest of the environment, its sky
        (``env``, :mod:`slc.lib.lights.env_lights`)."""
        delta = mi.Bool(ds.delta)
        if self.samp is None:
            return delta
        em, known = self.samp.index_of(ds.emitter, ok & ~delta)
        if self.sph is not None:
            delta |= self.sph.small(self.si.p, em, known)
        if self.env is not None:
            n = facing(self.si.sh_frame.n, ds.d, self.two)
            delta |= self.env.sample_listable(ds.d, em, n, known & ~delta)[0]
            # the sky: listed (its exact irradiance) at entries on a diffuse-only BSDF; a glossy
            # entry's sky is shaded better by the cones (skylit's principled paving: per-pixel error
            # 0.09 in cones, 0.16 with the sky listed and 16 BSDF samples of it at the pixel)
            if self.env.has_sky:
                delta |= self.env.sky_sample(ds.d, em, known & ~delta & self.diffuse)
        return delta

    def observe(self, st: SampleStats, ds, w, ok, s) -> SampleStats:
        cz = s.z if self.two is None else dr.select(self.two, dr.abs(s.z), s.z)
        c = dr.select(ok, lum(w) * dr.maximum(cz, 0.0), 0.0)
        return st.add(c, self.listable(ds, ok), s)
