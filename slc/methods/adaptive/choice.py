r"""The per-entry header of the adaptive cache, its light statistics and the
choice rule (see docs/adaptive.md).

Header (3 x 32 bits per cache entry)::

    w0: tag (2) | streak (6) | count (6) | e (18, the cones' e6m12 radiance code)
    w1: slot of the entry's record in its representation's pool (INVALID: none)
    w2: s_delta (unorm8) | m_x | m_y | m_z (snorm8: m / e_nd, local frame)

Statistics, running means over the entry's own light samples (window
``W``: the update weight is :math:`a = 1/\min(n+1, W)`, :math:`n` the
update count): :math:`e_\delta` and :math:`e_{nd}`, the visible energy
:math:`\frac1N\sum_k \mathrm{lum}(w_k)\cos\theta_k V_k` of delta-light and of
other samples, and :math:`\mathbf m`, the same sum of the other samples
weighted by their local direction :math:`\omega_k`. Stored as
:math:`e = e_\delta + e_{nd}`, :math:`s_\delta = e_\delta / e` and
:math:`\hat{\mathbf m} = \mathbf m / e_{nd}`; the mean resultant length
:math:`R = |\hat{\mathbf m}|` is 1 for light from one direction and
:math:`2/3` for a constant sky (the cosine-weighted hemisphere).

Choice with hysteresis: the target is VISIBILITY when :math:`s_\delta` exceeds
:math:`\theta_\delta + h_\delta` (or, for an entry already in VISIBILITY, stays
above :math:`\theta_\delta - h_\delta`), with :math:`\theta_g \pm h_g` in place of
:math:`\theta_\delta \pm h_\delta` at a glossy entry (its BSDF's glossy and delta lobes
carry most of its light) whose other light is narrow (:math:`R \ge \theta_R`): there the
record's residual, light of unknown direction, shaded as uniform radiance, spreads a light's
highlight over the whole surface; otherwise SH when :math:`R < \theta_R - h_R`
(kept while :math:`R < \theta_R + h_R`); otherwise CONES. An entry switches
once the target differed from its tag for ``switch_after`` updates in a row
and it has at least ``min_count`` updates of statistics; a dark entry
(:math:`e = 0`) keeps its tag.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.lib.cones.packing import decode_radiance, encode_radiance
from slc.scene.bsdf_table import glossy_lobes

NONE, VIS, CONES, SH = 0, 1, 2, 3
NAMES = {NONE: "none", VIS: "visibility", CONES: "cones", SH: "sh"}
TAG_OF = {NAMES[t]: t for t in (VIS, CONES, SH)}     # a setting's representation name -> its tag
HEADER_WORDS = 3


@dataclass(frozen=True)
class ChoiceParams:
    window: int = 32              # statistics' running-mean window (updates)
    theta_delta: float = 0.5      # delta-light energy share for VISIBILITY
    theta_glossy: float = 0.97    # the same at glossy entries with a narrow residual
    h_glossy: float = 0.02
    h_delta: float = 0.15
    theta_r: float = 0.75         # mean resultant length below which light is "wide" (SH)
    h_r: float = 0.06
    switch_after: int = 3         # updates in a row with another target before switching
    min_count: int = 2            # updates of statistics before the first switch
    allow_sh: bool = True         # SH is a candidate (the method: only in scenes with an environment emitter)


@dataclass
class Header:
    tag: mi.UInt32
    streak: mi.UInt32
    count: mi.UInt32
    e: mi.Float
    slot: mi.UInt32
    s_delta: mi.Float
    m: mi.Vector3f


def _unorm8(x):
    return mi.UInt32(dr.clip(dr.round(mi.Float(x) * 255.0), 0.0, 255.0))


def _snorm8(x):
    return mi.UInt32(dr.clip(dr.round(mi.Float(x) * 127.0), -127.0, 127.0) + 127.0)


def unpack_header(w) -> Header:
    w0, w1, w2 = (mi.UInt32(x) for x in w)
    m = mi.Vector3f(*[(mi.Float((w2 >> (8 * (k + 1))) & 0xFF) - 127.0) * (1.0 / 127.0) for k in range(3)])
    return Header(tag=w0 & 3, streak=(w0 >> 2) & 63, count=(w0 >> 8) & 63, e=decode_radiance(w0 >> 14),
                  slot=w1, s_delta=mi.Float(w2 & 0xFF) * (1.0 / 255.0), m=m)


def pack_header(h: Header) -> list:
    w0 = (mi.UInt32(h.tag) & 3) | ((dr.minimum(mi.UInt32(h.streak), 63)) << 2) | \
        (dr.minimum(mi.UInt32(h.count), 63) << 8) | (encode_radiance(h.e) << 14)
    w2 = _unorm8(h.s_delta)
    for k in range(3):
        w2 |= _snorm8(h.m[k]) << (8 * (k + 1))
    return [w0, mi.UInt32(h.slot), w2]


def update_stats(h: Header, e_d_hat, e_n_hat, m_hat, p: ChoiceParams) -> Header:
    """Fold one update cycle's estimates (delta energy, other energy, other
    energy times direction) into the running means."""
    e_d = h.s_delta * h.e
    e_n = h.e - e_d
    m = h.m * e_n
    a = dr.rcp(mi.Float(dr.minimum(h.count + 1, p.window)))
    e_d = dr.fma(a, e_d_hat - e_d, e_d)
    e_n = dr.fma(a, e_n_hat - e_n, e_n)
    m = m + (m_hat - m) * a
    e = e_d + e_n
    s = dr.select(e > 0.0, e_d / dr.select(e > 0.0, e, 1.0), 0.0)
    mn = dr.select(e_n > 0.0, m / dr.select(e_n > 0.0, e_n, 1.0), mi.Vector3f(0.0))
    ok = dr.isfinite(e) & dr.isfinite(s)
    return Header(tag=h.tag, streak=h.streak, count=dr.minimum(h.count + 1, 63), e=dr.select(ok, e, 0.0),
                  slot=h.slot, s_delta=dr.select(ok, s, 0.0), m=mn)


def resultant(h: Header) -> mi.Float:
    return dr.minimum(dr.norm(h.m), 1.0)


def target_of(h: Header, p: ChoiceParams, glossy=None) -> mi.UInt32:
    """The representation the statistics ask for, with the hysteresis bands
    around the thresholds (see the module); ``glossy``: the glossy entries
    (:func:`glossy_entries`; None: none)."""
    is_vis, is_sh = h.tag == VIS, h.tag == SH
    R = resultant(h)
    theta, band = mi.Float(p.theta_delta), mi.Float(p.h_delta)
    if glossy is not None:      # a narrow residual on a glossy lobe: its highlight would be misplaced
        gl = mi.Bool(glossy) & (R >= p.theta_r)
        theta, band = dr.select(gl, p.theta_glossy, theta), dr.select(gl, p.h_glossy, band)
    vis = h.s_delta > dr.select(is_vis, theta - band, theta + band)
    wide = R < dr.select(is_sh, p.theta_r + p.h_r, p.theta_r - p.h_r)
    if not p.allow_sh:
        wide = dr.zeros(mi.Bool, dr.width(R))
    t = dr.select(vis, mi.UInt32(VIS), dr.select(wide, mi.UInt32(SH), mi.UInt32(CONES)))
    return dr.select(h.e > 0.0, t, h.tag)


def decide(h: Header, p: ChoiceParams, allowed: bool = True, glossy=None):
    """(header with the streak advanced, switch mask, target tag). With
    ``allowed`` false (a frame between switch frames) nothing switches and the
    streaks keep counting; ``glossy`` as :func:`target_of`."""
    t = target_of(h, p, glossy)
    differs = (t != h.tag) & (h.tag != NONE)
    streak = dr.select(differs, dr.minimum(h.streak + 1, 63), 0)
    # ``allowed`` opaque: the same kernel in switch frames and between them (the first frame
    # between switch frames may come after a run's warm-up)
    switch = differs & (streak >= p.switch_after) & (h.count >= p.min_count) & dr.opaque(mi.Bool, bool(allowed))
    h2 = Header(tag=h.tag, streak=dr.select(switch, 0, streak), count=h.count, e=h.e, slot=h.slot,
                s_delta=h.s_delta, m=h.m)
    return h2, switch, t


GLOSSY_SHARE = 0.5      # an entry whose BSDF's glossy and delta lobes carry at least this share of its light


def glossy_entries(scene, si, env=None) -> mi.Bool | None:
    """The entries whose BSDF's glossy and delta lobes carry at least ``GLOSSY_SHARE`` of its
    reflected light (:func:`slc.scene.bsdf_table.glossy_lobes`): their VISIBILITY residual, shaded
    as uniform radiance, would misplace a light's highlight (the choice rule's ``theta_glossy``,
    the start of new entries). None in a scene whose sky is listed (``env.has_sky``): a glossy
    pixel there takes the residual's sky from the map's radiance along BSDF samples."""
    if env is not None and env.has_sky:
        return None
    return glossy_lobes(scene, si.bsdf(), si.is_valid()) >= GLOSSY_SHARE
