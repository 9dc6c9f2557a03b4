"""Records: what one render node sends another for one cache entry, and how they are written.

A record is the payload's words as stored, so that a receiver shades from the owner's value bit
for bit. How a payload's entries become records is a codec chosen here per payload kind
(:func:`codec_for`), so that the method classes carry none of the protocol:

- :class:`RecordCodec` (every cache method): the entry's storage words; any changed word counts
  as a change;
- :class:`ConeCodec` (``slc``): the same records, changes measured on the cones' light and axes
  against the entry's noise (:meth:`ConeCodec.change`);
- :class:`PooledCodec` (``adaptive``): an entry's header and its representation's pool record,
  padded to the largest pool's words; a receiver holds the pool record in a pool slot of its own
  pools (:func:`relocate_pooled`; word 0's low two bits the representation, word 1 the pool slot).

``entry_state`` is everything shading reads per entry, so that a node may shade from its own
copy of it.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.methods.adaptive.choice import CONES, NONE, SH, VIS
from slc.methods.adaptive.method import AdaptiveCache
from slc.methods.cache_method import PayloadMethod
from slc.methods.cones.method import SurfaceLightCones
from slc.lib.cones.packing import unpack

REPS = (VIS, CONES, SH)


class RecordCodec:
    """The records of a cache method's entries: its storage words as stored (``mi.Float`` words
    reinterpreted as ``mi.UInt32``), one lane per entry."""

    def __init__(self, method: PayloadMethod):
        self.m = method

    def entry_state(self) -> dict:
        """The per-entry arrays shading reads (name -> Dr.Jit array): the storage."""
        return {"storage": self.m.storage}

    def pack(self, slots: mi.UInt32) -> list:
        """The records of the entries ``slots``: a list of ``mi.UInt32`` words, one lane per entry."""
        m = self.m
        words = m.read(mi.UInt32(slots), 0, n=m.words)
        words = words if isinstance(words, list) else [words]
        return [w if m.storage_type is mi.UInt32 else dr.reinterpret_array(mi.UInt32, w) for w in words]

    def unpack(self, state: dict, slots: mi.UInt32, words: list, active=True) -> None:
        """Write the records ``words`` (from :meth:`pack`) of the entries ``slots`` into ``state``
        (an :meth:`entry_state` copy)."""
        m = self.m
        vals = words if m.storage_type is mi.UInt32 else [dr.reinterpret_array(m.storage_type, w) for w in words]
        m.write(vals, mi.UInt32(slots), 0, active, storage=state["storage"])

    def nbytes(self, words: list) -> mi.UInt32:
        """Bytes of each record on the wire (all of its words)."""
        return dr.full(mi.UInt32, 4 * len(words), dr.width(words[0]) if words else 0)

    def change(self, old: list, new: list) -> mi.Float:
        """How much each entry changed between two of its records, in the payload's own terms
        (0: identical): 1 where any word differs, else 0 (a payload without a finer measure
        sends every changed record at any positive threshold)."""
        diff = mi.Bool(False)
        for a, b in zip(old, new):
            diff |= mi.UInt32(a) != mi.UInt32(b)
        return dr.select(diff, mi.Float(1.0), mi.Float(0.0))


class ConeCodec(RecordCodec):
    """The records of Surface Light Cones (``slc``): the packed cones, their change measured on
    the light."""

    def change(self, old: list, new: list) -> mi.Float:
        r"""How much an entry's cones changed between two records: the largest over its cones of
        the radiance change :math:`\lvert L_c' - L_c \rvert` (luminance; a cone missing from one
        record counts with radiance 0) relative to the entry's total radiance, and of the axis turn
        in radians weighted by the cone's share of that radiance (cones in both records), times
        :math:`\sqrt{C' / 255}` for the newer record's :math:`C'` samples: an estimate of
        :math:`C'` samples is noisy by about :math:`1/\sqrt{C'}` of its value, so the change is
        counted in units of that noise, scaled so that an entry with the full 255 samples of
        memory keeps the plain change."""
        K = self.m.max_cones
        D0, _, L0, _, n0 = unpack(old, K)
        D1, _, L1, C1, n1 = unpack(new, K)
        Y0 = [dr.select(n0 > i, mi.luminance(L0[i]), 0.0) for i in range(K)]
        Y1 = [dr.select(n1 > i, mi.luminance(L1[i]), 0.0) for i in range(K)]
        total = mi.Float(0.0)
        for i in range(K):
            total += dr.maximum(Y0[i], Y1[i])
        inv = dr.select(total > 0.0, dr.rcp(dr.maximum(total, 1e-30)), 0.0)
        change = mi.Float(0.0)
        for i in range(K):
            d_energy = dr.abs(Y1[i] - Y0[i]) * inv
            turn = dr.safe_acos(dr.clip(dr.dot(D0[i], D1[i]), -1.0, 1.0))
            share = dr.select((n0 > i) & (n1 > i), dr.maximum(Y0[i], Y1[i]) * inv, 0.0)
            change = dr.maximum(change, dr.maximum(d_energy, turn * share))
        return change * dr.sqrt(dr.clip(C1, 1.0, 255.0) / 255.0)


class PooledCodec(RecordCodec):
    """The records of the adaptive cache (``adaptive``): an entry's header and its
    representation's pool record, padded to the largest pool's words; a receiver writes the pool
    record at the same pool slot of its own copy of the pools."""

    def entry_state(self) -> dict:
        """The header storage and every pool's data (what shading reads per entry)."""
        m = self.m
        out = {"storage": m.storage}
        if m.pools is not None:
            out.update({f"pool{r}": m.pools[r].data for r in REPS})
        return out

    def pack(self, slots: mi.UInt32) -> list:
        """The header words followed by each entry's pool record."""
        m, head = self.m, super().pack(slots)
        if m.pools is None:
            return head
        tag, ps = head[0] & 3, head[1]
        width = max(p.words for p in m.pools.values())
        body = [dr.zeros(mi.UInt32, dr.width(ps)) for _ in range(width)]
        for r in REPS:
            on = (tag == r) & (ps != INVALID)
            for k, w in enumerate(m.pools[r].gather(ps, on)):
                body[k] = dr.select(on, w, body[k])
        return head + body

    def unpack(self, state: dict, slots: mi.UInt32, words: list, active=True) -> None:
        """The header words into ``state``'s storage, the pool records into its pools."""
        m = self.m
        super().unpack(state, slots, words[:m.words], active)
        if m.pools is None:
            return
        W = m.words
        tag, ps = words[0] & 3, words[1]
        for r in REPS:
            on = mi.Bool(active) & (tag == r) & (ps != INVALID)
            base = ps * m.pools[r].words
            for k in range(m.pools[r].words):
                dr.scatter(state[f"pool{r}"], words[W + k], base + k, on)

    def nbytes(self, words: list) -> mi.UInt32:
        """The header and the words of the entry's own representation."""
        m, tag = self.m, words[0] & 3
        n = dr.full(mi.UInt32, 4 * m.words, dr.width(tag))
        if m.pools is not None:
            for r in REPS:
                n = dr.select(tag == r, n + 4 * m.pools[r].words, n)
        return n


def codec_for(method: PayloadMethod) -> RecordCodec:
    """The record codec of ``method``'s payload kind."""
    if isinstance(method, SurfaceLightCones):
        return ConeCodec(method)
    if isinstance(method, AdaptiveCache):
        return PooledCodec(method)
    return RecordCodec(method)


def unpack_into(codec: RecordCodec, slots: mi.UInt32, words: np.ndarray) -> None:
    """Write the records ``words`` (numpy, one row per word) of the entries ``slots`` into the
    storage (and pools) of ``codec``'s method."""
    w = [mi.UInt32(np.ascontiguousarray(r)) for r in words]
    if getattr(codec.m, "pools", None) is not None:
        w[1] = relocate_pooled(codec.m, slots, w[0] & 3, w[1])
    codec.unpack(codec.entry_state(), slots, w)


def relocate_pooled(method, slots: mi.UInt32, tag: mi.UInt32, pool_slot: mi.UInt32) -> mi.UInt32:
    """The receiver's pool slots for records of representation ``tag`` arriving at ``slots``:
    the slot the entry already holds in that representation's pool, else a new one (and the old
    one, of another representation, given back)."""
    W = method.words
    head = dr.gather(mi.UInt32, method.storage, slots * W)
    old_tag, old = head & 3, dr.gather(mi.UInt32, method.storage, slots * W + 1)
    holds = (old_tag != NONE) & (old != INVALID)
    keep = holds & (old_tag == tag)
    new = dr.select(keep, old, INVALID)
    for r, pool in method.pools.items():
        give = holds & ~keep & (old_tag == r)
        pool.release(old, give)
        take = ~keep & (tag == r) & (pool_slot != INVALID)
        new = dr.select(take, pool.acquire(take), new)
    dr.eval(new)
    return new
