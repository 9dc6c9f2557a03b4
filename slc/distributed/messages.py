"""The messages render nodes send each other (:class:`slc.distributed.node.Node`), as plain
dataclasses of numpy arrays: the same objects travel between nodes in one process and between
Ray actors (which pickle them).

An entry is named by its *address* (:meth:`slc.osc.cache.OnSurfaceCache.entry_address`: its
texel's virtual block times B^2 plus its texel in the block, 32 bits, the same on every node).
``nbytes`` is what a message holds on the wire by the protocol's own count (4 bytes per address,
the payload's record bytes, 1 bit per need flag); the cluster measures beside it the bytes of
the message pickled (:class:`slc.distributed.cluster.Cluster`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KEY_BYTES = 4          # an entry's address in a request, a query or in front of a record


def _keys(a=None) -> np.ndarray:
    return np.zeros(0, np.uint32) if a is None else np.asarray(a, np.uint32)


@dataclass
class Message:
    """From node ``src`` to node ``dst``, sent in frame ``sent``."""
    src: int
    dst: int
    sent: int

    @property
    def nbytes(self) -> int:
        return 0


@dataclass
class Requests(Message):
    """A node's requests to the owner of the entries: ``subscribe`` (the node holds no record of
    the entry), ``resubscribe`` (it holds one: send it again only if the entry changed), ``cancel``;
    then ``need``, packed bits (numpy ``packbits``, big-endian), one per entry of the node's
    subscriptions at this owner after this message in ascending address order: set where the
    node's viewers need the entry in this frame. An empty ``need`` with no subscription change
    means: as last time. ``kinds``: bytes by :data:`slc.distributed.node.KINDS`."""
    subscribe: np.ndarray = field(default_factory=_keys)
    resubscribe: np.ndarray = field(default_factory=_keys)
    cancel: np.ndarray = field(default_factory=_keys)
    need: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))

    @property
    def kinds(self) -> dict:
        return {"requests": KEY_BYTES * (len(self.subscribe) + len(self.resubscribe) + len(self.cancel)),
                "needs": int(len(self.need))}

    @property
    def nbytes(self) -> int:
        return sum(self.kinds.values())


@dataclass
class SeedQuery(Message):
    """The owner of new entries asks the owner of coarser entries covering them for those of
    ``keys`` that exist (their LOD seeds, :func:`slc.osc.requests.lod_seeds`)."""
    keys: np.ndarray = field(default_factory=_keys)

    @property
    def kinds(self) -> dict:
        return {"seeds": KEY_BYTES * len(self.keys)}

    @property
    def nbytes(self) -> int:
        return KEY_BYTES * len(self.keys)


@dataclass
class Records(Message):
    """Records of entries: ``keys`` and ``words`` (uint32, one row per word of the payload's
    packed record, :meth:`slc.osc.payload.PayloadMethod.pack_records`, one column per entry);
    ``kinds``: their bytes (address and the payload's record bytes) by kind (:data:`KINDS`)."""
    keys: np.ndarray = field(default_factory=_keys)
    words: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.uint32))
    kinds: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        return int(sum(self.kinds.values()))


@dataclass
class SeedReply(Records):
    """The records of the queried seeds that exist, from before this frame's update."""


# the phase of the receiver that reads each message (slc.distributed.node.PHASES)
READ_IN = {Requests: "serve", SeedQuery: "answer", SeedReply: "update", Records: "shade"}
