"""Records written into a node's own slots.

A record is the payload's words as stored (:meth:`slc.methods.cache_method.PayloadMethod.pack_records`),
so that a receiver shades from the owner's value bit for bit. A payload whose entries point into
pools of their own (``method.pools``: the adaptive cache's representation pools,
:mod:`slc.methods.adaptive.records`: word 0's low two bits the representation, word 1 the pool
slot) holds the record in a pool slot of the receiver's own pools: :func:`relocate_pooled`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.methods.adaptive.choice import NONE


def unpack_into(method, slots: mi.UInt32, words: np.ndarray) -> None:
    """Write the records ``words`` (numpy, one row per word) of the entries ``slots`` into
    ``method``'s storage (and pools)."""
    w = [mi.UInt32(np.ascontiguousarray(r)) for r in words]
    if getattr(method, "pools", None) is not None:
        w[1] = relocate_pooled(method, slots, w[0] & 3, w[1])
    method.unpack_records(method.entry_state(), slots, w)


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
