"""The VISIBILITY representation's update and shading as frozen functions, traced once and
replayed (``dr.freeze``): :class:`VisUpdate` runs :func:`~slc.methods.adaptive.visibility.update.update`,
:class:`VisShading` runs :func:`~slc.methods.adaptive.visibility.shading.shade`, with the emitter, sphere
and region tables declared as inputs (:mod:`slc.methods.adaptive.frozen_inputs`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.freeze import FrozenFunction
from slc.core.keys import mixed_rng, stream_mix
from slc.methods.adaptive.frozen_inputs import light_tables, sampler_inputs
from slc.lib.lights.polygon_glossy import has_glossy
from slc.lib.lights.polygon_ltc import LtcTable
from slc.methods.adaptive.visibility.shading import shade
from slc.methods.adaptive.visibility.update import VisLanes, VisParams, mix_of, update
from slc.scene import bsdf_table
from slc.scene.bsdf_table import side_inputs

STREAM_GLOSSY = 0x5BD1E995         # the glossy pixels' light samples (plus the viewer's index)
STREAM_ALBEDO = 0x2545F491         # xor'ed into that key: the residual's BSDF samples


class VisShading(FrozenFunction):
    """:func:`shade` on the pixels' VISIBILITY records, traced once and replayed
    (``dr.freeze``, as :class:`slc.methods.adaptive.sh_rep.SHShading`): tracing the
    shading (a BSDF call site in the listed lights' loop and one in the
    environment regions' loop) cost more host time than its kernel. The
    records (gathered outside), mask, interactions and the scene are inputs;
    the sphere and region tables are declared as inputs too (a frozen function
    reads only arrays reachable from its inputs). ``K``, ``sph`` and ``env``
    are fixed per instance; ``glossy`` is the method's ``polygon_glossy`` (``ltc``: the fitted
    table and the scene's BSDF table are inputs too; ``sample``: ``S`` sample pairs); ``back``:
    the records keep a residual behind the surface (the scene has two-sided BSDFs).
    Unfrozen with ``freeze=False`` and after more than ``max_recordings`` recordings."""

    def __init__(self, K: int, sph=None, env=None, freeze: bool = True, glossy: str = "point", S: int = 0,
                 seed: int = 0, max_recordings: int = 4, back: bool = False):
        S, ltc = (S if glossy == "sample" else 0), glossy == "ltc"
        if sph is None or sph.poly is None or not has_glossy(getattr(sph.scene, "mi_scene", sph.scene)):
            S, ltc = 0, False           # no polygon light or no glossy BSDF: nothing to sample
        table = LtcTable(bsdf_table.for_scene(sph.scene)) if ltc else None
        self.K, self.sph, self.env, self.S, self.seed, self.ltc = int(K), sph, env, int(S), int(seed), table
        K, S, back = int(K), int(S), bool(back)

        # the closure holds no reference to self: a cycle through the frozen function would be
        # freed by the garbage collector, which may run while another function records (abort)
        def kernel(rec, active, si, bsdf, scene, tables, pid, viewer, mixes):
            mix = dr.gather(mi.UInt32, mixes, viewer)         # each pixel's viewer's streams
            rng = mixed_rng(pid, mix) if S > 0 else None
            rng_a = mixed_rng(pid, mix ^ STREAM_ALBEDO)
            return shade(scene, rec, si, bsdf, active, K, sph, env, rng, S, table, back, rng_a)
        super().__init__(kernel, freeze, max_recordings=max_recordings)

    def __call__(self, rec, active, si, scene, frame: int = 0, viewer=0, pid=None, n_viewers: int = 1) -> mi.Color3f:
        """``S`` > 0: a glossy pixel's polygon lights are sampled (``S`` pairs), and non-diffuse
        pixels take BSDF samples for their residual: random numbers keyed by the pixel (``pid``,
        its index within its viewer; None: its index in the arrays), ``seed``, ``frame`` and
        ``viewer`` (an int, or per pixel a ``mi.UInt32`` of ``n_viewers`` viewers)."""
        n = dr.width(active)
        if isinstance(viewer, int):
            mixes, viewer = [stream_mix(self.seed, frame, STREAM_GLOSSY + viewer)], dr.zeros(mi.UInt32, n)
        else:
            mixes = [stream_mix(self.seed, frame, STREAM_GLOSSY + v) for v in range(int(n_viewers))]
        # the viewers' mixes as a table of two lanes or more (a width-1 array would enter the
        # kernel as a scalar: another recording), opaque (a new frame is no new recording)
        table = mi.UInt32(mixes + mixes[-1:] * max(2 - len(mixes), 0))
        dr.make_opaque(table)
        pid = dr.arange(mi.UInt32, n) if pid is None else mi.UInt32(pid)
        return super().__call__([mi.UInt32(w) for w in rec], mi.Bool(active), si, si.bsdf(), scene,
                                light_tables(self.sph, self.env) + (self.ltc.arrays() if self.ltc else []), pid,
                                mi.UInt32(viewer), table)


class VisUpdate(FrozenFunction):
    """:func:`update` traced once and replayed (``dr.freeze``, as ``slc``'s
    :class:`slc.methods.cones.update_kernel.ConeUpdate`): tracing the update (the sample loop
    with its K unrolled slots) cost more host time than its kernel. Inputs:
    the scene, the emitter table's arrays (:func:`sampler_inputs`),
    the sphere and region tables, the entries' records and interactions, and
    the random streams' mix (opaque: a new frame is no new recording). ``K``,
    ``seed``, ``sph`` and ``env`` are fixed per instance. Unfrozen after more
    than ``max_recordings`` recordings."""

    def __init__(self, K: int, seed: int, sph=None, env=None, freeze: bool = True, max_recordings: int = 4):
        self.K, self.seed, self.sph, self.env = int(K), int(seed), sph, env
        K, seed = int(K), int(seed)

        def kernel(scene, lights, tables, rec, si, key, rays, moving, fresh, on, texel, mix):   # no self (VisShading)
            out, gone, st = update(scene, VisLanes(rec, si, key, rays, moving, fresh, on, texel),
                                   VisParams(K, sph, env), mix)
            st = st.values()
            dr.eval(out, gone, st)
            return out, gone, st
        super().__init__(kernel, freeze, max_recordings=max_recordings,
                         lanes=("rec", "si", "key", "rays", "moving", "fresh", "on", "texel"))   # per entry

    def __call__(self, scene, rec, si, key, rays, moving, fresh, on, frame: int, texel=None):
        """``texel``: the entries' footprints (:func:`update`; None: every sample from the entry's point)."""
        return super().__call__(scene, sampler_inputs(scene), light_tables(self.sph, self.env) + side_inputs(scene),
                                [mi.UInt32(w) for w in rec],
                                si, mi.UInt32(key), mi.UInt32(rays), mi.Bool(moving), mi.Bool(fresh), mi.Bool(on),
                                None if texel is None else mi.Float(texel), mix_of(self.seed, frame))
