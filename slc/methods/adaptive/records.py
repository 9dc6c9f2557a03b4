"""The adaptive cache's records between render nodes (slc.distributed): an entry's record is
its header and its representation's pool record, padded to the largest pool's words; a
receiver writes the pool record at the same pool slot of its own copy of the pools."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID
from slc.methods.adaptive.choice import CONES, SH, VIS
from slc.methods.cache_method import PayloadMethod

REPS = (VIS, CONES, SH)


def entry_state(method) -> dict:
    """The header storage and every pool's data (what shading reads per entry)."""
    out = {"storage": method.storage}
    if method.pools is not None:
        out.update({f"pool{r}": method.pools[r].data for r in REPS})
    return out


def set_entry_state(method, state: dict) -> None:
    method.storage = state["storage"]
    if method.pools is not None:
        for r in REPS:
            method.pools[r].data = state[f"pool{r}"]


def pack(method, head: list) -> list:
    """``head`` (the header words) followed by each entry's pool record."""
    if method.pools is None:
        return head
    tag, ps = head[0] & 3, head[1]
    width = max(p.words for p in method.pools.values())
    body = [dr.zeros(mi.UInt32, dr.width(ps)) for _ in range(width)]
    for r in REPS:
        on = (tag == r) & (ps != INVALID)
        for k, w in enumerate(method.pools[r].gather(ps, on)):
            body[k] = dr.select(on, w, body[k])
    return head + body


def unpack_pools(method, state: dict, words: list, active=True) -> None:
    """The pool records of ``words`` (from :func:`pack`) into ``state``'s pools."""
    if method.pools is None:
        return
    W = method.words
    tag, ps = words[0] & 3, words[1]
    for r in REPS:
        on = mi.Bool(active) & (tag == r) & (ps != INVALID)
        base = ps * method.pools[r].words
        for k in range(method.pools[r].words):
            dr.scatter(state[f"pool{r}"], words[W + k], base + k, on)


def record_bytes(method, words: list) -> mi.UInt32:
    """The header and the words of the entry's own representation."""
    tag = words[0] & 3
    n = dr.full(mi.UInt32, 4 * method.words, dr.width(tag))
    if method.pools is not None:
        for r in REPS:
            n = dr.select(tag == r, n + 4 * method.pools[r].words, n)
    return n


def pack_records(method, slots) -> list:
    """:meth:`PayloadMethod.pack_records` of the adaptive cache: header and pool record."""
    return pack(method, PayloadMethod.pack_records(method, slots))


def unpack_records(method, state: dict, slots, words: list, active=True) -> None:
    """:meth:`PayloadMethod.unpack_records` of the adaptive cache: header and pool record."""
    PayloadMethod.unpack_records(method, state, slots, words[:method.words], active)
    unpack_pools(method, state, words, active)
