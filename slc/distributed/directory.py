"""Who owns a region: its home (rendezvous hashing of the region), or the node that first needed it.

A home sees every node's requests for its regions' entries (the need bits,
:class:`slc.distributed.state.Client`), so in each frame it knows which nodes need each region.
A region no entry of which exists yet, needed by one other node only, is *delegated* to that
node (:class:`~slc.distributed.messages.Delegate`: no state to hand over): it creates and updates
the region's entries itself, and nothing about them crosses the link while it alone needs them.
The delegation holds for the region's life. Other nodes keep sending their requests for it to
its home, which passes them on to the owner (:class:`~slc.distributed.state.Relay`,
:class:`~slc.distributed.messages.Relayed`); the owner sends them the records, as a home does.
A node that needs a region it is the home of sends its requests to the owner directly.

An entry's update depends only on its state, its key and its LOD seed, so the entries of a
delegated region are those of one process wherever they are updated; a seed query for an entry
of a delegated region is answered by its owner (:class:`~slc.distributed.messages.SeedRelay`).
"""
from __future__ import annotations

import numpy as np

from slc.core.keys import INVALID
from slc.distributed.messages import Delegate
from slc.distributed.owners import owners
from slc.distributed.state import Relay, in_sorted


def _sorted(d: dict) -> np.ndarray:
    return np.sort(np.fromiter(d.keys(), np.uint64, len(d)))


class Directory:
    """A node's side of the delegations: ``away`` (region -> the node it is delegated to, this
    node its home), ``mine`` (region -> its home, delegated to this node), ``relays`` ((node,
    owner) -> :class:`~slc.distributed.state.Relay`)."""

    def __init__(self, node):
        self.node = node
        self.away, self.mine, self.relays = {}, {}, {}

    def owns(self, regions: np.ndarray, homes: np.ndarray) -> np.ndarray:
        """Mask: this node owns the region (its home and not delegated away, or delegated to it)."""
        return (((homes == self.node.id) & ~in_sorted(regions, _sorted(self.away)))
                | in_sorted(regions, _sorted(self.mine)))

    def away_of(self, regions: np.ndarray) -> np.ndarray:
        """The node each of ``regions`` is delegated to by this home (-1: none)."""
        if not self.away or len(regions) == 0:
            return np.full(len(regions), -1, np.int64)
        r = _sorted(self.away)
        n = np.array([self.away[int(x)] for x in r], np.int64)
        i = np.minimum(np.searchsorted(r, regions), len(r) - 1)
        return np.where(r[i] == regions, n[i], -1)

    # ------------------------------------------------------------------ as a home
    def decide(self) -> list:
        """This frame's delegations (see the module) and the requests passed on to the owners of
        delegated regions."""
        node = self.node
        if node.s.kind != "sparse" or not node.s.delegate:
            return []
        direct = {j: c for (j, via), c in node.clients.items() if j == via and j in node.live}
        reg, who = [], []
        for keys, j in [(node.need, node.id)] + [(c.needed(), j) for j, c in direct.items()]:
            r = node.regions(keys)
            r = r[owners(r, node.live) == node.id]
            reg.append(r)
            who.append(np.full(len(r), j, np.int64))
        reg, who = np.concatenate(reg), np.concatenate(who)
        pair = np.unique(np.stack([reg, who.astype(np.uint64)]), axis=1) if len(reg) else np.zeros((2, 0), np.uint64)
        regions, first, n_needers = np.unique(pair[0], return_index=True, return_counts=True)
        new = ~in_sorted(regions, self._existing()) & ~in_sorted(regions, _sorted(self.away))
        give = {}
        for i in np.nonzero(new)[0].tolist():
            needers = pair[1][first[i]:first[i] + n_needers[i]].astype(np.int64).tolist()
            if node.id in needers:
                continue                       # the home needs it: it keeps it
            n = int(owners(regions[i:i + 1], needers)[0])      # one of the nodes that need it
            self.away[int(regions[i])] = n
            give.setdefault(n, []).append(int(regions[i]))
        out = [Delegate(node.id, n, node.frame, regions=np.array(rs, np.uint64)) for n, rs in give.items()]
        return out + self._relay(direct)

    def _existing(self) -> np.ndarray:
        """The regions with an entry in this node's cache (sorted)."""
        cache = self.node.cache
        if cache.pool is None:
            return np.zeros(0, np.uint64)
        vb = np.array(cache.pool.blk_vb, np.int64)
        vb = vb[vb != INVALID]
        return np.unique(self.node.regions((vb * cache.layout.block_texels).astype(np.uint32)))

    def _relay(self, direct: dict) -> list:
        """Each node's subscriptions in delegated regions, passed on to their owners."""
        node, out = self.node, []
        for j, c in direct.items():
            to = self.away_of(node.regions(c.keys))
            for n in set(np.unique(to[to >= 0]).tolist()) | {n for (jj, n) in self.relays if jj == j}:
                if n == j or n not in node.live:
                    continue
                sel = to == n
                msg = self.relays.setdefault((j, n), Relay()).frame(node.id, n, j, node.frame, c.keys[sel],
                                                                    c.need[sel] if len(c.need) == len(c.keys)
                                                                    else np.zeros(int(sel.sum()), bool),
                                                                    c.resubscribed)
                if msg is not None:
                    out.append(msg)
        return out

    # ------------------------------------------------------------------ as an owner
    def take(self, msg: Delegate) -> None:
        for r in msg.regions.tolist():
            self.mine[r] = msg.src

    # ------------------------------------------------------------------ membership
    def drop(self, dead: int, regions: np.ndarray) -> np.ndarray:
        """Node ``dead`` left: the delegations to it and from it end. Returns the mask over
        ``regions`` of those whose entries start anew."""
        gone = [r for r, n in self.away.items() if n == dead] + [r for r, h in self.mine.items() if h == dead]
        for r in gone:
            self.away.pop(r, None)
            self.mine.pop(r, None)
        self.relays = {k: v for k, v in self.relays.items() if dead not in k}
        return in_sorted(regions, np.sort(np.array(gone, np.uint64)))

    def count(self) -> int:
        return len(self.mine)

    def nbytes(self) -> int:
        return 16 * (len(self.away) + len(self.mine)) + sum(r.keys.nbytes for r in self.relays.values())
