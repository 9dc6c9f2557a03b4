r"""Projection of radiance onto an :class:`~slc.lib.sh.ycocg.Encoding` and
reconstruction of irradiance and radiance from its coefficients.

Projection of one radiance sample arriving from direction :math:`\omega`
with weight :math:`w` (``L / pdf`` of the sample, divided by the sample
count by the caller):

.. math:: \lambda_{c,lm} \mathrel{+}= w\, L_c(\omega)\, Y_{lm}(\omega),
          \qquad l < b_c,

for each channel c of the encoding's space (YCoCg or RGB). Irradiance at
normal n by the closed-form cosine convolution (Ramamoorthi and Hanrahan
2001):

.. math:: E_c(n) = \sum_{l < b_c} \hat A_l \sum_m \lambda_{c,lm} Y_{lm}(n),
          \qquad \hat A = (\pi, 2\pi/3, \pi/4)

converted back to RGB. ``presence`` scales Y and ``bleeding`` scales Co
and Cg (the paper's artistic controls; 1 = physically based). Negative
values, from ringing of the truncated series (at most
:func:`~slc.lib.sh.basis.ringing_bound` times the total incident power for 3
bands), are clamped to 0 after the conversion to RGB.

Coefficients are a list of ``enc.n`` arrays (one per coefficient, laid out
channel by channel). All functions work on Dr.Jit and numpy arrays.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from slc.lib.sh.basis import A_HAT, band_of, basis
from slc.lib.sh.ycocg import Encoding, encoding


def _max0(x):
    if dr.is_array_v(x):
        return dr.maximum(x, 0.0)
    return np.maximum(x, 0.0)


def project(enc: Encoding | str, d, rgb, weight=1.0, Y=None) -> list:
    """Coefficients of one radiance sample ``rgb`` (3 arrays) from unit
    direction ``d`` (3 arrays), times ``weight``. ``Y``: precomputed basis
    values (a list of at least ``enc.max_bands**2`` arrays)."""
    enc = encoding(enc)
    if Y is None:
        Y = basis(d[0], d[1], d[2], enc.max_bands)
    chans = enc.to_space(rgb[0], rgb[1], rgb[2])
    out = []
    for c, k in enumerate(enc.counts):
        wc = chans[c] * weight
        out += [wc * Y[i] for i in range(k)]
    return out


def _channel_dot(enc: Encoding, coeffs, Y, factors):
    """Per channel: sum_i factors[l(i)] * coeffs[i] * Y[i]."""
    out = []
    for c, k in enumerate(enc.counts):
        o = enc.offsets[c]
        acc = 0.0
        for i in range(k):
            acc = acc + factors[band_of(i)] * coeffs[o + i] * Y[i]
        out.append(acc)
    return out


def _select(cond, a, b):
    if dr.is_array_v(cond):
        return dr.select(cond, a, b)
    return np.where(cond, a, b)


def irradiance(enc: Encoding | str, coeffs, n, presence=1.0, bleeding=1.0, clamp=True, chroma="offset"):
    """RGB irradiance (3 arrays) at unit normal ``n`` from radiance
    coefficients ``coeffs``; see the module docstring.

    ``chroma``: ``"offset"`` (the paper: chrominance irradiance from its own
    truncated series, added to Y) or ``"ratio"`` (an extension, for
    constant-term chrominance only: Co and Cg irradiance follow the
    directional luminance, ``E_Co(n) = E_Co,0 * E_Y(n) / E_Y,0`` with E_.,0
    the DC-only irradiance, i.e. constant chromaticity instead of a constant
    colour offset; where E_Y,0 <= 0 the chroma is 0)."""
    enc = encoding(enc)
    Y = basis(n[0], n[1], n[2], enc.max_bands)
    e = _channel_dot(enc, coeffs, Y, A_HAT)
    if enc.space == "ycocg" and chroma == "ratio" and enc.bands[1] == 1 and enc.bands[2] == 1:
        dc = A_HAT[0] * coeffs[0] * Y[0]
        ok = dc > 1e-12
        r = _select(ok, e[0] / _select(ok, dc, 1.0), 0.0)
        e = [e[0], e[1] * r, e[2] * r]
    if enc.space == "ycocg":
        e = [e[0] * presence, e[1] * bleeding, e[2] * bleeding]
    rgb = enc.to_rgb(*e)
    return tuple(_max0(v) for v in rgb) if clamp else tuple(rgb)


def radiance(enc: Encoding | str, coeffs, d, presence=1.0, bleeding=1.0, clamp=True):
    """RGB radiance (3 arrays) arriving from unit direction ``d``
    reconstructed from the truncated series (used for glossy shading by
    sampling the BSDF)."""
    enc = encoding(enc)
    Y = basis(d[0], d[1], d[2], enc.max_bands)
    e = _channel_dot(enc, coeffs, Y, (1.0, 1.0, 1.0))
    if enc.space == "ycocg":
        e = [e[0] * presence, e[1] * bleeding, e[2] * bleeding]
    rgb = enc.to_rgb(*e)
    return tuple(_max0(v) for v in rgb) if clamp else tuple(rgb)


def scale(coeffs, s) -> list:
    return [c * s for c in coeffs]
