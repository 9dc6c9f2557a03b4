r"""SH representation: incident direct radiance as spherical harmonics with
YCoCg chrominance compression (:mod:`slc.methods.sh`, default Y3Co1Cg1: 11
coefficients), in the entry's local frame, in a pool of its own.

Record: the coefficients and the sample count, one float word each. Update: the
``sh`` method's (:mod:`slc.lib.sh.update`), in the entry's frame,
:math:`\hat\lambda_{lm} = \frac1n \sum_k w_k V_k Y_{lm}(\omega_k)`,
:math:`\lambda \leftarrow \lambda + \min(n/C, 1)(\hat\lambda - \lambda)`, C the sample
count capped at ``max_count``; lights below the surface are dropped (but at entries on
two-sided BSDFs, whose pixels on the back see them). Shading: the
Ramamoorthi-Hanrahan irradiance for diffuse-only BSDFs (chrominance by the
"ratio" rule of :func:`slc.lib.sh.project.irradiance`: the paper's offset rule
shifted the colour of a constant sky on a plane by 5%), BSDF samples of the
reconstructed radiance otherwise: the ``sh`` method's shading
(:func:`slc.lib.sh.shading.shade_radiance`) on the pool's local-frame coefficients.

Conversion. To lobes: one cone about the mean direction of the luminance,
:math:`\mathbf d \propto (\lambda_{1,1}, \lambda_{1,-1}, \lambda_{1,0})`, with
integrated radiance :math:`\sqrt{4\pi}\lambda_{00}` per channel and the
half-angle of a uniform cone of the same mean resultant length
:math:`R = |\int L\omega| / \int L`: :math:`\cos\alpha = 2R - 1`. From lobes:
each lobe (d, alpha, L) projected as a uniform cone, band l attenuated by
:math:`g_0 = 1`, :math:`g_1 = (1 + c)/2`, :math:`g_2 = c(1 + c)/2`,
:math:`c = \cos\alpha`.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from slc.core.freeze import FrozenFunction
from slc.core.keys import STREAM_SH_SHADE, STREAM_SH_UPDATE, keyed_rng, mixed_rng, stream_key
from slc.lib.sh.basis import C1, band_of, basis
from slc.lib.sh.project import irradiance, radiance
from slc.lib.sh.shading import shade_radiance
from slc.lib.sh.update import project_samples, running_mean
from slc.lib.sh.ycocg import encoding as get_encoding
from slc.methods.adaptive.choice import SH
from slc.methods.adaptive.representation import Entries, Pixels, Representation, Updated
from slc.methods.adaptive.sampling import LightStats, SampleStats
from slc.methods.adaptive.frozen_inputs import light_tables, sampler_inputs
from slc.scene.bsdf_table import side_inputs, side_normal, two_sided

CONVERT_COUNT = 4.0


def words(enc) -> int:
    return enc.n + 1


def unpack(rec, enc):
    f = [dr.reinterpret_array(mi.Float, mi.UInt32(w)) for w in rec]
    return f[:enc.n], f[enc.n]


def pack(coeffs, C):
    return [dr.reinterpret_array(mi.UInt32, mi.Float(c)) for c in list(coeffs) + [C]]


def update(scene: mi.Scene, rec, si, key, rays, fresh, on, frame: int, seed: int, enc, max_count: int, sph=None,
           env=None, mix=None):
    """One update cycle of SH records (:mod:`slc.lib.sh.update`, in the entry's frame, fresh
    records restarting empty), with the choice rule's statistics
    (:class:`~slc.methods.adaptive.sampling.LightStats`, ``sph`` and ``env`` see there) from the
    same samples. Returns (new words, stats values). ``mix``: the random streams' (seed,
    frame) mix as an opaque ``mi.UInt32`` (:func:`slc.core.keys.stream_key`), in place of
    ``seed`` and ``frame`` (:class:`SHUpdate`)."""
    if mix is None:
        rng = keyed_rng(key, seed, frame, STREAM_SH_UPDATE)
    else:                              # keyed_rng with the mix given
        rng = mixed_rng(key, mix)
    valid = mi.Bool(on) & si.is_valid()
    two = two_sided(scene, si.bsdf(), valid)
    acc, st = project_samples(scene, si, si.sh_frame, rays, rng, valid, enc, LightStats(scene, si, sph, env, two),
                              two)
    coeffs, C = unpack(rec, enc)
    fresh = mi.Bool(fresh)
    coeffs, C = running_mean([dr.select(fresh, 0.0, c) for c in coeffs], dr.select(fresh, 0.0, C), acc, rays,
                             max_count)
    return pack(coeffs, C), st.values()


class SHUpdate(FrozenFunction):
    """:func:`update` traced once and replayed (``dr.freeze``, as
    :class:`~slc.methods.adaptive.visibility.frozen.VisUpdate` and
    :class:`~slc.methods.adaptive.cones_rep.ConesUpdate`): tracing the SH update (the
    sample loop, the projection on the encoding's basis) was Python work on
    every frame. Inputs: the scene, the emitter table's arrays
    (:func:`~slc.methods.adaptive.frozen_inputs.sampler_inputs`), the sphere and region
    tables, the entries' records and interactions, and the random streams' mix
    (opaque: a new frame is no new recording). The encoding, ``seed``,
    ``max_count``, ``sph`` and ``env`` are fixed per instance. Unfrozen after
    more than ``max_recordings`` recordings. Images
    are those of the traced update bit for bit."""

    def __init__(self, enc_name: str, seed: int, max_count: int, sph=None, env=None, freeze: bool = True,
                 max_recordings: int = 4):
        self.enc_name, self.seed, self.max_count = str(enc_name), int(seed), int(max_count)
        self.sph, self.env = sph, env
        enc, seed, max_count = get_encoding(self.enc_name), int(seed), int(max_count)

        def kernel(scene, lights, tables, rec, si, key, rays, fresh, on, mix):     # no self (see VisShading)
            out, st = update(scene, rec, si, key, rays, fresh, on, 0, seed, enc, max_count, sph, env, mix=mix)
            # a statistic the samples never touch (e_delta without delta lights) may be a literal
            # zero, which a recording replays at the recorded width: a select makes it a kernel's output
            st = [dr.select(on, x, 0.0) for x in st]
            dr.eval(out, st)
            return out, st
        super().__init__(kernel, freeze, max_recordings=max_recordings,
                         lanes=("rec", "si", "key", "rays", "fresh", "on"))     # per entry (slc.core.freeze)

    def __call__(self, scene, rec, si, key, rays, fresh, on, frame: int):
        return super().__call__(scene, sampler_inputs(scene), light_tables(self.sph, self.env) + side_inputs(scene),
                                [mi.UInt32(w) for w in rec], si, mi.UInt32(key), mi.UInt32(rays), mi.Bool(fresh),
                                mi.Bool(on), stream_key(self.seed, frame, STREAM_SH_UPDATE))


def shade(rec, si, bsdf, tf, active, enc, seed: int, glossy_samples: int, scene=None, pid=None) -> mi.Color3f:
    """L_o of the pixels from their SH records (:func:`slc.lib.sh.shading.shade_radiance`);
    ``tf`` each entry's local frame, in which the coefficients live. ``scene``: a scene with
    two-sided BSDFs (None: none), whose pixels seen from behind are shaded from that side.
    ``pid``: each pixel's random-number key (None: its index in the arrays)."""
    coeffs, _ = unpack(rec, enc)
    two = two_sided(scene, bsdf, active) if scene is not None else None
    nrm = tf.to_local(mi.Vector3f(si.sh_frame.n) if two is None else side_normal(si))
    return shade_radiance(
        si, bsdf, active,
        lambda: mi.Color3f(*irradiance(enc, coeffs, nrm, chroma="ratio")),
        lambda d, m: (mi.Color3f(*radiance(enc, coeffs, tf.to_local(d))), m),
        keyed_rng(dr.arange(mi.UInt32, dr.width(active)) if pid is None else pid, seed, 0, STREAM_SH_SHADE),
        glossy_samples, two)


def lobes(rec, active, enc):
    """The record as one lobe (see the module)."""
    coeffs, _ = unpack(rec, enc)
    o = enc.offsets
    dc = [coeffs[o[c]] * math.sqrt(4.0 * math.pi) for c in range(3)]     # integral of each channel
    Lr = mi.Color3f(*enc.to_rgb(*dc))
    Lr = dr.maximum(Lr, 0.0)
    k = C1 * 4.0 * math.pi / 3.0
    v = mi.Vector3f(coeffs[3], coeffs[1], coeffs[2]) * k          # Y channel: (x, y, z) <- (1,1), (1,-1), (1,0)
    y0 = dc[0]
    R = dr.select(y0 > 0.0, dr.norm(v) / dr.select(y0 > 0.0, y0, 1.0), 0.0)
    R = dr.clip(R, 0.0, 1.0)
    d = dr.select(dr.norm(v) > 0.0, dr.normalize(v), mi.Vector3f(0.0, 0.0, 1.0))
    alpha = dr.acos(dr.clip(2.0 * R - 1.0, -1.0, 1.0))
    return [(d, alpha, Lr, mi.Bool(active) & (y0 > 0.0))]


def from_lobes(lobes, n_lanes: int, enc):
    """Coefficients of the lobes, each a uniform cone (band factors g_l)."""
    out = [dr.zeros(mi.Float, n_lanes) for _ in range(enc.n)]
    for d, a, Lr, m in lobes:
        c = dr.cos(a)
        g = (1.0, 0.5 * (1.0 + c), c * 0.5 * (1.0 + c))
        Y = basis(d[0], d[1], d[2], enc.max_bands)
        chans = enc.to_space(Lr[0], Lr[1], Lr[2])
        k = 0
        for ch, cnt in enumerate(enc.counts):
            for i in range(cnt):
                out[k] = out[k] + dr.select(m, chans[ch] * Y[i] * g[band_of(i)], 0.0)
                k += 1
    return pack(out, dr.full(mi.Float, CONVERT_COUNT, n_lanes))


def irradiance_at_normal(rec, enc, side: float = 1.0) -> mi.Color3f:
    """The records' irradiance at the entry's normal (``side`` -1: at the reversed normal)."""
    coeffs, _ = unpack(rec, enc)
    return mi.Color3f(*irradiance(enc, coeffs, mi.Vector3f(0.0, 0.0, side), chroma="ratio"))


# ----------------------------------------------------------------------------- frozen shading

def _shade_kernel(rec, active, si, bsdf, tf, enc_name: str, seed: int, glossy_samples: int, scene, tables, pid):
    """:func:`shade` (the body of :class:`SHShading`'s frozen function; ``tables``: the arrays
    the two-sided lookup reads)."""
    return shade(rec, si, bsdf, tf, active, get_encoding(enc_name), seed, glossy_samples, scene, pid)


class SHShading(FrozenFunction):
    """:func:`shade` on an SH pool, traced once and replayed (``dr.freeze``, as
    :class:`slc.lib.cones.shading.ConeShading`): tracing the SH shading (basis,
    BSDF sampling loop) cost more host time than its kernel. The pixels' records
    (gathered outside: the pool's width changes when it grows, the pixels' does
    not), mask and interactions are the frozen function's inputs; the encoding, seed
    and glossy sample count are fixed per instance; ``scene``: the scene where it has
    two-sided BSDFs (None: none; see :func:`shade`). A function recorded
    more than ``max_recordings`` times shades unfrozen."""

    def __init__(self, enc_name: str, seed: int, glossy_samples: int, freeze: bool = True,
                 max_recordings: int = 4, scene=None):
        self.enc_name, self.seed, self.glossy_samples = str(enc_name), int(seed), int(glossy_samples)
        self.scene = scene
        super().__init__(_shade_kernel, freeze, max_recordings=max_recordings)

    def __call__(self, rec, active, si, tf, pid=None) -> mi.Color3f:
        """``pid``: each pixel's random-number key (None: its index in the arrays)."""
        tables = side_inputs(self.scene) if self.scene is not None else []
        return super().__call__([mi.UInt32(w) for w in rec], mi.Bool(active), si, si.bsdf(), tf, self.enc_name,
                                self.seed, self.glossy_samples, self.scene, tables, pid)


class SHRep(Representation):
    """The SH representation of the adaptive cache: the coefficients of ``cache.encoding`` in
    the entry's local frame and their sample count, the ``sh`` method's projection and shading
    (see the module); its irradiance at the normal is the SH closed form."""

    tag, name = SH, "sh"
    restarts_stats = False

    def words(self) -> int:
        return words(self.cache.enc)

    def update(self, e: Entries) -> Updated:
        c = self.cache
        fn = self.frozen("update_fn", lambda fz: SHUpdate(c.encoding, c.seed, c.sh_count, c.sph, c.env, freeze=fz))
        out, st = fn(c.scene.mi_scene, e.rec, e.si, e.key, e.rays, e.fresh, e.on, e.frame)
        return Updated(out, None, SampleStats.of(st))

    def shade(self, px: Pixels) -> mi.Color3f:
        c = self.cache
        fn = self.frozen("shade_fn", lambda fz: SHShading(c.encoding, c.seed, c.glossy_samples, freeze=fz,
                                                           scene=c.scene.mi_scene if c._back else None))
        return fn(self.pool.gather(px.slot, px.active), px.active, px.si, px.tf, px.pid)

    def lobes(self, rec, si, active) -> list:
        return lobes(rec, active, self.cache.enc)

    def irradiance(self, rec, lobes, side: float) -> mi.Color3f:
        return irradiance_at_normal(rec, self.cache.enc, side)

    def convert(self, src, rec, lobes, n: int) -> list:
        return from_lobes(lobes, n, self.cache.enc)
