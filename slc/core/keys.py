"""Small pieces every cache shares: the invalid index and keyed random numbers.

Random numbers of a cache entry (or grid cell) must not depend on which
other entries are active, on the viewers, or on the entry's lane in a
kernel, so that a second viewer cannot change the first viewer's image:
:func:`keyed_rng` derives one PCG32 stream from the entry's own 32-bit key
(e.g. :meth:`slc.osc.OnSurfaceCache.entry_keys`), the run seed, the frame and
a stream id. Per-pixel random numbers of the per-viewer methods come from
:func:`slc.scene.lights.rng` instead (lanes are pixels there).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

INVALID = 0xFFFFFFFF
"""Index of nothing: a pixel without a cache entry, a free block, no seed."""

# Stream ids (added to the seed/frame mix; distinct per use of random numbers).
STREAM_CONE_UPDATE = 0x165667B1
STREAM_SH_UPDATE = 0x27D4EB2F
STREAM_SH_SHADE = 0x5A5A0001
STREAM_CRC = 0xC2B2AE00


def stream_mix(seed: int, frame: int, stream: int) -> int:
    """The 32-bit mix of (seed, frame, stream) (:func:`stream_key`'s value, on the host)."""
    return (int(seed) * 0x9E3779B1 + int(frame) * 0x85EBCA77 + int(stream)) & 0xFFFFFFFF


def stream_key(seed: int, frame: int, stream: int) -> mi.UInt32:
    """The opaque 32-bit mix of (seed, frame, stream): opaque, so that a new
    frame or seed never recompiles a kernel."""
    return dr.opaque(mi.UInt32, stream_mix(seed, frame, stream))


def mixed_rng(keys: mi.UInt32, mix: mi.UInt32) -> mi.PCG32:
    """:func:`keyed_rng` with its (seed, frame, stream) mix given as a ``mi.UInt32``
    (e.g. :func:`stream_key`'s, or computed inside a kernel): frozen functions take
    the mix as an input, so a new frame gets new streams without a new recording."""
    keys = mi.UInt32(keys)
    v0, v1 = mi.sample_tea_32(keys, mi.UInt32(mix), 6)
    rng = mi.PCG32()
    rng.seed(mi.UInt64(v0) | (mi.UInt64(v1) << 32), mi.UInt64(keys))
    return rng


def keyed_rng(keys: mi.UInt32, seed: int, frame: int, stream: int) -> mi.PCG32:
    """One PCG32 stream per key for (seed, frame, stream): state from a
    6-round TEA hash of (key, mix), increment from the key.

    ``PCG32.seed()`` rather than the constructor: ``PCG32(size, ...)`` adds
    ``arange(size)`` to both inputs, which would tie a key's stream to its
    lane position."""
    return mixed_rng(keys, stream_key(seed, frame, stream))
