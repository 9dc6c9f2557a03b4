"""LOD seeds across render nodes (:class:`slc.distributed.node.Node`): a new entry starts from the
finest coarser entry covering it that exists (:func:`slc.osc.requests.lod_seeds`); with ``seeds``
exact its owner asks the owners of the coarser entries which of them exist
(:class:`slc.distributed.messages.SeedQuery`), with ``seeds`` held it takes the finest one it
holds."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.keys import INVALID
from slc.distributed.messages import SeedQuery
from slc.distributed.records import unpack_into
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


def existing(node, keys: np.ndarray) -> tuple:
    """(mask over ``keys``, their slots): owned entries seen before this frame (a seed's
    condition, :func:`slc.osc.requests.lod_seeds`)."""
    s = node.cache.address_slots(mi.UInt32(keys))
    ok = s != INVALID
    ok &= (dr.gather(mi.UInt32, node.cache.pool.slot_seen, s, ok) > 0) & ~dr.gather(mi.Bool, node.new_now, s, ok)
    ok &= dr.gather(mi.Bool, node.value, s, ok)
    return np.array(ok, bool) & node.owns(keys), s


def seed_queries(node) -> list:
    """With ``seeds`` exact: the node's queries for the coarser entries of its new owned entries
    that it does not own, to their owner when it knows it (as their home), else to their home."""
    new = np.nonzero(node.owned & np.array(node.fr.is_new, bool))[0]
    if len(new) == 0:
        return []
    keys, ok = ancestors(node.cache, dr.gather(mi.UInt32, node.fr.active, mi.UInt32(new)))
    cand = np.unique(keys[ok])
    cand = cand[~node.owns(cand)]
    home = node.home(cand)
    to = np.where(home == node.id, node.dir.away_of(node.regions(cand)), home)   # the owner, or the home
    return [SeedQuery(node.id, o, node.frame, keys=cand[to == o]) for o in node.live
            if o != node.id and np.any(to == o)]


def records_of(node, keys: np.ndarray) -> tuple:
    """(keys, words, the payload's bytes of the records) of the existing owned entries among
    ``keys`` (ascending addresses)."""
    if len(keys) == 0:
        return keys, None, 0
    ok, s = existing(node, keys)
    if not np.any(ok):
        return keys[:0], None, 0
    rec = node.codec.pack(dr.gather(mi.UInt32, s, mi.UInt32(np.nonzero(ok)[0])))
    nbytes = int(dr.sum(node.codec.nbytes(rec))[0])
    return keys[ok], np.stack([np.array(w, np.uint32) for w in rec]), nbytes


def seed_slots(node, idx: np.ndarray, replies: list) -> mi.UInt32:
    """The LOD seed of every owned entry ``idx``: with delay 0 and ``seeds`` exact the finest
    coarser entry that exists at its owner, its record written into the new entry's own slot
    (the update reads it there); else the cache's own choice when this node holds a value of
    it (the finest coarser entry this node holds)."""
    fr = node.fr
    seed = dr.gather(mi.UInt32, fr.seed_slot, mi.UInt32(idx))
    if not node.m.reads_seeds or len(node.live) == 1:
        return seed
    out = dr.full(mi.UInt32, INVALID, len(idx))
    new = idx[np.array(dr.gather(mi.Bool, fr.is_new, mi.UInt32(idx)), bool)] if len(idx) else idx
    if len(new) == 0:
        return out
    if node.s.delay > 0 or node.s.seeds != "exact":
        ok = seed != INVALID
        return dr.select(ok & dr.gather(mi.Bool, node.value, seed, ok), seed, INVALID)
    keys, valid = ancestors(node.cache, dr.gather(mi.UInt32, fr.active, mi.UInt32(new)))
    cand = np.unique(keys[valid])
    found = [records_of(node, cand[node.owns(cand)])[:2]] + [(r.keys, r.words) for r in replies]
    found = [(k, w) for k, w in found if len(k)]
    if not found:
        return out
    fk, fw = np.concatenate([k for k, _ in found]), np.concatenate([w for _, w in found], axis=1)
    order = np.argsort(fk)
    fw, pick = fw[:, order], finest(keys, valid, fk[order])
    seeded = pick >= 0
    if np.any(seeded):
        slots = dr.gather(mi.UInt32, fr.active, mi.UInt32(new[seeded]))
        unpack_into(node.codec, slots, fw[:, pick[seeded]])
        dr.scatter(out, slots, mi.UInt32(np.searchsorted(idx, new[seeded])))
    return out
