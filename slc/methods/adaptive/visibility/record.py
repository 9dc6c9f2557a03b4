"""The VISIBILITY record: its layout (:mod:`slc.methods.adaptive.visibility`), packing, and the
per-slot helpers of the update and the shading."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from slc.lib.cones.packing import WordReader, WordWriter, decode_radiance, encode_radiance

EMPTY = 0xFFFF              # an empty slot's light index
VIS_BITS = 10               # bits of a listed light's visible fraction (stochastically rounded)
VIS_COUNT_MAX = (1 << (16 - VIS_BITS)) - 1      # a listed light's sample count cap (the slot word's last 6 bits)
VIS_WINDOW = VIS_COUNT_MAX + 1                  # samples in a listed light's visible fraction's running mean
ENV_WINDOW = 64             # samples in the running means of the unlisted regions' and the sky's visible fractions
RES_MAX_COUNT = 255         # the residual's count cap, in samples (as the cones' C, 8 bits)
MOVED_COUNT = 1             # visibility count of a listed light that moved (its next sample weighs 1/2)
UNSETTLED_COUNT = 4         # residual count cap of moving entries, in update cycles
RESIDUAL_ALPHA = math.radians(60.0)     # the residual as a lobe (conversion): a 60-degree cone about n


def words(K: int, env: bool = False, back: bool = False) -> int:
    """Record words: K lights, the residual (2), with an environment the unlisted regions'
    and the sky's visible fractions (2), and with ``back`` (two-sided BSDFs in the scene) the
    residual behind the surface (2)."""
    return K + 2 + (2 if env else 0) + (2 if back else 0)


class Record:
    """An unpacked VISIBILITY record: the K listed lights (index, visible
    fraction, sample count), the residual irradiance ``E`` and its sample
    count ``C``, the unlisted environment regions' visible fraction ``vu``
    and its sample count ``nu``, the sky's visible fraction ``vs`` and its samples' weight sum
    ``ns`` (in units of 1/16; 0 without an environment), and
    the residual behind the surface ``Eb`` (0 without two-sided BSDFs); ``conv``: converted from
    another representation and not updated since (its residual holds all of its light)."""

    def __init__(self, idx, vis, cnt, E, C, vu, nu, Eb=None, vs=None, ns=None, conv=None):
        self.idx, self.vis, self.cnt, self.E, self.C, self.vu, self.nu = idx, vis, cnt, E, C, vu, nu
        self.conv = conv if conv is not None else dr.zeros(mi.Bool, dr.width(C))
        self.Eb = Eb if Eb is not None else dr.zeros(mi.Color3f, dr.width(C))
        self.vs = vs if vs is not None else dr.zeros(mi.Float, dr.width(C))
        self.ns = ns if ns is not None else dr.zeros(mi.UInt32, dr.width(C))


def unpack(w, K: int, env: bool = False, back: bool = False) -> Record:
    idx = [w[i] & 0xFFFF for i in range(K)]
    q = (1 << VIS_BITS) - 1
    vis = [mi.Float((w[i] >> 16) & q) * (1.0 / q) for i in range(K)]
    cnt = [(w[i] >> (16 + VIS_BITS)) & VIS_COUNT_MAX for i in range(K)]
    rd = WordReader([w[K], w[K + 1]])
    E = mi.Color3f(*[decode_radiance(rd.get(18)) for _ in range(3)])
    C = mi.Float(rd.get(8))
    conv = rd.get(1) != 0
    vu = nu = vs = ns = None
    if env:
        vu, nu = _fraction(w[K + 2])
        x = mi.UInt32(w[K + 3])
        vs, ns = mi.Float(x & 0xFFFF) * (1.0 / 65535.0), mi.UInt32(x >> 16)
    else:
        vu, nu = dr.zeros(mi.Float, dr.width(C)), dr.zeros(mi.UInt32, dr.width(C))
    Eb = None
    if back:
        j = K + 2 + (2 if env else 0)
        rb = WordReader([w[j], w[j + 1]])
        Eb = mi.Color3f(*[decode_radiance(rb.get(18)) for _ in range(3)])
    return Record(idx, vis, cnt, E, C, vu, nu, Eb, vs, ns, conv)


def _fraction(x):
    """(visible fraction, count) of a word [unorm 16 | count 8 | spare 8]."""
    x = mi.UInt32(x)
    return mi.Float(x & 0xFFFF) * (1.0 / 65535.0), mi.UInt32((x >> 16) & 0xFF)


def _fraction_word(v, n):
    return mi.UInt32(dr.clip(dr.round(v * 65535.0), 0.0, 65535.0)) | (dr.minimum(mi.UInt32(n), 255) << 16)


def quantized_fraction(v, u=None) -> mi.UInt32:
    """A visible fraction in ``VIS_BITS`` bits: rounded up with probability equal to its
    remainder where ``u`` (uniform in [0, 1), drawn anew at every update) is given, to the
    nearest quantum otherwise. The running mean's step ``(V - v)/n`` is below half a quantum
    near 0 and 1 (for ``n = 64`` within 3% of either end at 10 bits): rounded to nearest, a
    lit entry's fraction stays where one occluded sample put it; rounded stochastically, it
    returns in expectation."""
    q = float((1 << VIS_BITS) - 1)
    return mi.UInt32(dr.clip(dr.floor(dr.fma(mi.Float(v), q, 0.5 if u is None else u)), 0.0, q))


def pack(r: Record, K: int, env: bool = False, back: bool = False, dither=None):
    """The record's words. ``dither``: one random 32-bit word per lane (the update's), from
    which every slot's visible fraction is rounded stochastically (:func:`quantized_fraction`);
    None: rounded to nearest."""
    out = []
    for i in range(K):
        u = None if dither is None else mi.sample_tea_float32(mi.UInt32(dither), mi.UInt32(i), 4)
        v = quantized_fraction(r.vis[i], u)
        out.append((mi.UInt32(r.idx[i]) & 0xFFFF) | (v << 16)
                   | (dr.minimum(mi.UInt32(r.cnt[i]), VIS_COUNT_MAX) << (16 + VIS_BITS)))
    wr = WordWriter(2)
    for ch in range(3):
        wr.put(encode_radiance(r.E[ch]), 18)
    wr.put(mi.UInt32(dr.clip(dr.round(r.C), 0.0, 255.0)), 8)
    wr.put(dr.select(mi.Bool(r.conv), mi.UInt32(1), mi.UInt32(0)), 1)
    out += wr.words
    if env:
        out += [_fraction_word(r.vu, r.nu),
                mi.UInt32(dr.clip(dr.round(r.vs * 65535.0), 0.0, 65535.0)) | (dr.minimum(mi.UInt32(r.ns), 0xFFFF) << 16)]
    if back:
        wb = WordWriter(2)
        for ch in range(3):
            wb.put(encode_radiance(r.Eb[ch]), 18)
        out += wb.words
    return out


def empty(n: int, K: int) -> Record:
    return Record([dr.full(mi.UInt32, EMPTY, n) for _ in range(K)], [dr.zeros(mi.Float, n) for _ in range(K)],
                  [dr.zeros(mi.UInt32, n) for _ in range(K)], dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n),
                  dr.zeros(mi.Float, n), dr.zeros(mi.UInt32, n))


def from_irradiance(E, n: int, K: int, env: bool = False, Eb=None):
    """A record with no listed light and residual ``E`` (the energy of another
    representation at the normal; ``Eb``: at the reversed normal, for records with the
    residual behind the surface); the lights come in with the next samples
    (the unlisted regions' visible fraction starts with no sample)."""
    r = empty(n, K)
    r.E, r.C, r.conv = mi.Color3f(E), dr.full(mi.Float, 4.0, n), dr.full(mi.Bool, True, n)
    if Eb is not None:
        r.Eb = mi.Color3f(Eb)
    return pack(r, K, env, Eb is not None)


def slot(lst, i):
    """Element ``i`` (a per-lane index) of a per-slot list."""
    r = lst[0]
    for j in range(1, len(lst)):
        r = dr.select(i == j, lst[j], r)
    return r


def used_slots(idx: list) -> mi.UInt32:
    """One past the last listed slot of each lane (0 for an empty list): the slots' loops stop
    there (an entry often lists fewer lights than its record has slots)."""
    n = dr.zeros(mi.UInt32, dr.width(idx[0]))
    for i, j in enumerate(idx):
        n = dr.select(j != EMPTY, i + 1, n)
    return n


def listed(idx: list, wl: list, em: mi.UInt32):
    """(whether emitter ``em`` is in the list ``idx``, its listed unoccluded irradiance ``wl``)."""
    hit, w = mi.Bool(False), dr.zeros(mi.Color3f, dr.width(em))
    for i, j in enumerate(idx):
        h = j == em
        hit |= h
        w = dr.select(h, wl[i], w)
    return hit, w


def residual(rec: Record, nrm, env, active) -> mi.Color3f:
    """The record's irradiance not from listed lights at normal ``nrm`` (world): the
    residual E_r plus the unlisted environment regions' closed form times their visible
    fraction and the sky's times its own."""
    E = mi.Color3f(rec.E)
    if env is not None:
        E += env.unlisted_irradiance(nrm, rec.idx, active) * rec.vu
        if env.has_sky:
            E += env.sky_irradiance(nrm, active) * rec.vs
    return E
