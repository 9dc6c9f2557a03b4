"""Bit packing of a cone entry (Dr.Jit, vectorized over entries).

Layout of one entry (little end first, fields may straddle 32-bit words)::

    per cone (92 bits):  theta fp16 (16) | phi fp16 (16) | alpha (6) | R (18) | G (18) | B (18)
    then:                C (8) | cone count (2 bits, 3 bits when max_cones = 4)

``max_cones = 3``: 3 x 92 + 8 + 2 = 286 bits -> 3 RGB32 texels (9 x UInt32, 36 bytes).
``max_cones = 4``: 4 x 92 + 8 + 3 = 379 bits -> 4 texels (12 x UInt32, 48 bytes).
``max_cones = 1, 2``: 101 / 194 bits -> 2 / 3 texels (see :func:`words_per_entry`).

Encodings (see docs/cones.md for the error bounds):

- direction: local spherical coordinates, ``theta = atan2(sqrt(x^2+y^2), z)`` in [0, pi] and
  ``phi = atan2(y, x)`` in [-pi, pi], each an IEEE fp16 (round to nearest even; the bit
  conversion is done by hand with integer ops, subnormals kept) -> angular error <= 1.4e-3 rad.
- opening angle alpha: 6-bit cubic code ``alpha = pi * (q / 63)^3``, rounded *up*
  (a packed cone always encloses the unpacked one; q = 0 is exactly 0 for point lights;
  smallest non-zero angle 1.3e-5 rad; step <= 3/q relative, <= 0.148 rad near pi).
- radiance: per channel an unsigned 18-bit float with 6 exponent bits (bias 31) and 12
  mantissa bits, round to nearest: relative error <= 2^-13 = 1.2e-4 on [2^-30, 2^33);
  values below 2^-30 become 0, values above saturate at 8.6e9; negative/NaN -> 0.
- C: integer 0..255 (rounded, clamped). Count: 0..max_cones.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

CONE_BITS = 92
C_BITS = 8
ALPHA_LEVELS = 63          # 6-bit code, alpha = pi * (q / 63)^3
ALPHA_POWER = 3.0
RAD_EXP_BITS, RAD_MAN_BITS, RAD_BIAS = 6, 12, 31
RAD_MAX_CODE = (1 << 18) - 1
C_MAX = 255


def count_bits(max_cones: int) -> int:
    return max(1, int(max_cones).bit_length())   # 1->1, 2..3->2, 4->3


def entry_bits(max_cones: int) -> int:
    return CONE_BITS * max_cones + C_BITS + count_bits(max_cones)


def texels_per_entry(max_cones: int) -> int:
    """RGB32 texels (96 bits each) per entry: 3 for the default 3 cones."""
    return -(-entry_bits(max_cones) // 96)


def words_per_entry(max_cones: int) -> int:
    return 3 * texels_per_entry(max_cones)


def bytes_per_entry(max_cones: int) -> int:
    return 4 * words_per_entry(max_cones)


# ----------------------------------------------------------------------------- fp16

def f32_to_f16_bits(x: mi.Float) -> mi.UInt32:
    """IEEE half bits (in the low 16 bits) of ``x``; round to nearest even,
    subnormals kept, overflow -> +-inf, NaN -> quiet NaN."""
    b = dr.reinterpret_array(mi.UInt32, mi.Float(x))
    sign = (b >> 16) & 0x8000
    a = b & 0x7FFFFFFF
    # normal range of half: a >= 2^-14 (0x38800000)
    rnd = 0x0FFF + ((a >> 13) & 1)
    normal = (a - 0x38000000 + rnd) >> 13
    normal = dr.select(a >= 0x477FF000, mi.UInt32(0x7C00), normal)       # >= 65520 rounds to inf
    # subnormal: value * 2^24 rounded to nearest even
    sub = mi.UInt32(dr.round(dr.abs(mi.Float(x)) * 16777216.0))
    h = dr.select(a < 0x38800000, sub, normal)
    h = dr.select(a > 0x7F800000, mi.UInt32(0x7E00), h)                  # NaN
    return sign | h


def f16_bits_to_f32(h: mi.UInt32) -> mi.Float:
    h = mi.UInt32(h) & 0xFFFF
    sign = (h & 0x8000) << 16
    e = (h >> 10) & 0x1F
    m = h & 0x3FF
    normal = ((h & 0x7FFF) << 13) + 0x38000000
    normal = dr.select(e == 0x1F, (m << 13) | 0x7F800000, normal)
    v = dr.reinterpret_array(mi.Float, sign | normal)
    sub = mi.Float(m) * (1.0 / 16777216.0)
    sub = dr.select(sign != 0, -sub, sub)
    return dr.select(e == 0, sub, v)


# ----------------------------------------------------------------------------- fields

def dir_to_sph(d: mi.Vector3f):
    theta = dr.atan2(dr.sqrt(dr.square(d.x) + dr.square(d.y)), d.z)
    phi = dr.atan2(d.y, d.x)
    return theta, phi


def sph_to_dir(theta: mi.Float, phi: mi.Float) -> mi.Vector3f:
    st, ct = dr.sincos(theta)
    sp, cp = dr.sincos(phi)
    return mi.Vector3f(st * cp, st * sp, ct)


def encode_alpha(alpha: mi.Float) -> mi.UInt32:
    """6-bit code, rounded up (conservative)."""
    a = dr.clip(mi.Float(alpha), 0.0, math.pi)
    a = dr.select(dr.isnan(a), 0.0, a)
    q = dr.ceil(ALPHA_LEVELS * dr.cbrt(a / math.pi) - 1e-4)
    return mi.UInt32(dr.clip(q, 0.0, float(ALPHA_LEVELS)))


def decode_alpha(q: mi.UInt32) -> mi.Float:
    t = mi.Float(q) * (1.0 / ALPHA_LEVELS)
    return math.pi * t * t * t


def alpha_levels():
    """All representable opening angles (python floats)."""
    return [math.pi * (q / ALPHA_LEVELS) ** 3 for q in range(ALPHA_LEVELS + 1)]


def encode_radiance(x: mi.Float) -> mi.UInt32:
    """Unsigned e6m12 float in 18 bits (bias 31), round to nearest."""
    x = mi.Float(x)
    x = dr.select(x > 0.0, x, 0.0)                 # negatives and NaN -> 0
    b = dr.reinterpret_array(mi.UInt32, x)
    lo = (127 - RAD_BIAS) << 23                    # bits of 2^-31: exponent field e=0 of our format
    shift = 23 - RAD_MAN_BITS
    rnd = (1 << (shift - 1)) - 1 + ((b >> shift) & 1)
    code = (b - lo + rnd) >> shift
    code = dr.select(b < lo + (1 << 23), mi.UInt32(0), code)   # below 2^-30 -> 0
    code = dr.select(b >= 0x7F800000, mi.UInt32(RAD_MAX_CODE), code)
    return dr.minimum(code, RAD_MAX_CODE)


def decode_radiance(code: mi.UInt32) -> mi.Float:
    code = mi.UInt32(code)
    lo = (127 - RAD_BIAS) << 23
    b = (code << (23 - RAD_MAN_BITS)) + lo
    return dr.select(code == 0, 0.0, dr.reinterpret_array(mi.Float, b))


RAD_MIN = 2.0 ** -30
RAD_MAX = (2.0 - 2.0 ** -12) * 2.0 ** (63 - RAD_BIAS)
RAD_REL_ERR = 2.0 ** -(RAD_MAN_BITS + 1)


# ----------------------------------------------------------------------------- bit streams

class WordWriter:
    def __init__(self, n_words: int):
        self.words = [mi.UInt32(0) for _ in range(n_words)]
        self.off = 0

    def put(self, v: mi.UInt32, width: int):
        v = mi.UInt32(v) & ((1 << width) - 1)
        w, s = divmod(self.off, 32)
        self.words[w] = self.words[w] | (v << s) if s else self.words[w] | v
        if s + width > 32:
            self.words[w + 1] = self.words[w + 1] | (v >> (32 - s))
        self.off += width


class WordReader:
    def __init__(self, words):
        self.words = words
        self.off = 0

    def get(self, width: int) -> mi.UInt32:
        w, s = divmod(self.off, 32)
        v = self.words[w] >> s if s else mi.UInt32(self.words[w])
        if s + width > 32:
            v = v | (self.words[w + 1] << (32 - s))
        self.off += width
        return v & ((1 << width) - 1) if width < 32 else v


def pack(D, alpha, L, C, count, max_cones: int):
    """Pack cone arrays (lists of length max_cones: mi.Vector3f local directions,
    mi.Float angles, mi.Color3f radiance), C (mi.Float) and count (mi.UInt32)
    into a list of ``words_per_entry(max_cones)`` mi.UInt32 arrays."""
    wr = WordWriter(words_per_entry(max_cones))
    for i in range(max_cones):
        th, ph = dir_to_sph(D[i])
        wr.put(f32_to_f16_bits(th), 16)
        wr.put(f32_to_f16_bits(ph), 16)
        wr.put(encode_alpha(alpha[i]), 6)
        for ch in range(3):
            wr.put(encode_radiance(L[i][ch]), 18)
    c = dr.clip(dr.round(mi.Float(C)), 0.0, float(C_MAX))
    wr.put(mi.UInt32(dr.select(dr.isnan(c), 0.0, c)), C_BITS)
    wr.put(dr.minimum(mi.UInt32(count), max_cones), count_bits(max_cones))
    return wr.words


def unpack(words, max_cones: int):
    """Inverse of :func:`pack`: (D, alpha, L, C, count)."""
    rd = WordReader(words)
    D, A, L = [], [], []
    for i in range(max_cones):
        th = f16_bits_to_f32(rd.get(16))
        ph = f16_bits_to_f32(rd.get(16))
        D.append(sph_to_dir(th, ph))
        A.append(decode_alpha(rd.get(6)))
        L.append(mi.Color3f(*[decode_radiance(rd.get(18)) for _ in range(3)]))
    C = mi.Float(rd.get(C_BITS))
    n = dr.minimum(rd.get(count_bits(max_cones)), max_cones)
    return D, A, L, C, n


def gather_words(storage: mi.UInt32, slot: mi.UInt32, max_cones: int, active=True):
    W = words_per_entry(max_cones)
    base = mi.UInt32(slot) * W
    return [dr.gather(mi.UInt32, storage, base + k, active) for k in range(W)]


def scatter_words(storage: mi.UInt32, words, slot: mi.UInt32, max_cones: int, active=True):
    W = words_per_entry(max_cones)
    base = mi.UInt32(slot) * W
    for k in range(W):
        dr.scatter(storage, words[k], base + k, active)
