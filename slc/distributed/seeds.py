"""LOD seeds across render nodes: a new entry starts from the finest coarser entry covering it
that exists (:func:`slc.osc.requests.lod_seeds`); across nodes its owner asks the owners of the
coarser entries which of them exist (:class:`slc.distributed.messages.SeedQuery`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.distributed.state import in_sorted


def ancestors(cache, slots: mi.UInt32) -> tuple:
    """(addresses, valid) of the coarser entries covering the entries ``slots`` of ``cache``,
    one row per level up: row ``d - 1`` holds level + d (valid up to the island's top level)."""
    L = cache.layout
    isl, lvl, tx, ty = cache.entry_texels(slots)
    maxl = dr.gather(mi.UInt32, L.d_isl_maxl, isl)
    keys, ok = [], []
    for d in range(1, L.max_level + 1):
        lc = lvl + d
        m = lc <= maxl
        cx, cy = tx >> d, ty >> d
        keys.append(np.array(dr.select(m, L.vblock(isl * L.levels + lc, cx, cy, m) * L.block_texels
                                       + L.within(cx, cy), 0), np.uint32))
        ok.append(np.array(m, bool))
    return np.stack(keys), np.stack(ok)


def finest(keys: np.ndarray, valid: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Per entry (a column of :func:`ancestors`' ``keys``), the index into ``found`` (sorted
    addresses of the coarser entries that exist) of its finest existing one, else -1."""
    pick = np.full(keys.shape[1], -1, np.int64)
    for d in range(keys.shape[0]):
        hit = (pick < 0) & valid[d] & in_sorted(keys[d], found)
        pick[hit] = np.searchsorted(found, keys[d][hit])
    return pick
