"""The messages render nodes send each other (:class:`slc.distributed.node.Node`), as plain
dataclasses of numpy arrays: the same objects travel between nodes in one process and between
Ray actors (which pickle them).

An entry is named by its *address* (:meth:`slc.osc.cache.OnSurfaceCache.entry_address`: its
texel's virtual block times B^2 plus its texel in the block, 32 bits, the same on every node).
A message's lists of addresses are ascending and go on the wire as the differences of
consecutive addresses in LEB128 varints (:func:`encode_addresses`: an entry beside the last one
takes a byte); need bits go packed, deflated when that is shorter (:func:`encode_bits`). A
pickled message holds them so encoded. ``nbytes`` is what a message holds on the wire by the
protocol's count (the encoded addresses and bits, the payload's record bytes); the cluster
measures beside it the bytes of the message pickled (:class:`slc.distributed.cluster.Cluster`).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field, fields

import numpy as np

KEY_BYTES = 4          # an entry's address unencoded (the reference count of full replication's records)


def encode_addresses(keys: np.ndarray) -> bytes:
    """Ascending addresses as LEB128 varints of their differences (the first from 0)."""
    k = np.asarray(keys, np.uint64)
    if len(k) == 0:
        return b""
    d = np.diff(k, prepend=np.uint64(0))
    if np.any(k[1:] < k[:-1]):
        raise ValueError("addresses must be ascending")
    n = np.ones(len(d), np.int64)
    for s in range(1, 10):
        n += (d >> np.uint64(7 * s)) > 0
    idx = np.repeat(np.arange(len(d)), n)
    grp = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)).astype(np.uint64)
    more = (grp < (n[idx] - 1).astype(np.uint64)).astype(np.uint64)
    return (((d[idx] >> (np.uint64(7) * grp)) & np.uint64(0x7F)) | (more << np.uint64(7))).astype(np.uint8).tobytes()


def decode_addresses(b: bytes, dtype=np.uint32) -> np.ndarray:
    a = np.frombuffer(b, np.uint8)
    if len(a) == 0:
        return np.zeros(0, dtype)
    end = (a & 0x80) == 0
    start = np.concatenate([[0], np.nonzero(end)[0][:-1] + 1])
    grp = np.arange(len(a)) - np.repeat(start, np.diff(np.append(start, len(a))))
    vals = (a & 0x7F).astype(np.uint64) << (np.uint64(7) * grp.astype(np.uint64))
    return np.cumsum(np.add.reduceat(vals, start), dtype=np.uint64).astype(dtype)


def encode_bits(bits: np.ndarray) -> bytes:
    """Packed need bits: a flag byte (0 raw, 1 deflated), then the shorter form."""
    raw = np.asarray(bits, np.uint8).tobytes()
    packed = zlib.compress(raw, 9, wbits=-15) if raw else b""
    return b"\x01" + packed if len(packed) < len(raw) else b"\x00" + raw


def decode_bits(b: bytes) -> np.ndarray:
    body = zlib.decompress(b[1:], wbits=-15) if b[:1] == b"\x01" else b[1:]
    return np.frombuffer(body, np.uint8).copy()


def _keys(a=None) -> np.ndarray:
    return np.zeros(0, np.uint32) if a is None else np.asarray(a, np.uint32)


@dataclass
class Message:
    """From node ``src`` to node ``dst``, sent in frame ``sent``. ``ADDRESSES``: the fields that
    are ascending address lists, ``BITS``: the packed need bits (both encoded when pickled);
    ``KIND``: the kind (:data:`slc.distributed.node.KINDS`) all of a message's address bytes
    count as, where one kind covers them."""
    src: int
    dst: int
    sent: int
    ADDRESSES = ()
    BITS = ()
    KIND = None

    def encoded(self, name: str) -> bytes:
        v = getattr(self, name)
        return encode_bits(v) if name in self.BITS else encode_addresses(v)

    @property
    def kinds(self) -> dict:
        """Bytes by kind: the encoded addresses, as :data:`KIND`."""
        return {self.KIND: sum(len(self.encoded(k)) for k in self.ADDRESSES)} if self.KIND else {}

    @property
    def nbytes(self) -> int:
        return int(sum(self.kinds.values()))

    def __getstate__(self):
        state = {f.name: getattr(self, f.name) for f in fields(self)}
        state.update({k: self.encoded(k) for k in self.ADDRESSES + self.BITS})
        return state

    def __setstate__(self, state):
        for k, v in state.items():
            if k in self.BITS:
                v = decode_bits(v)
            elif k in self.ADDRESSES:
                v = decode_addresses(v, np.uint64 if k == "regions" else np.uint32)
            object.__setattr__(self, k, v)


@dataclass
class Requests(Message):
    """A node's requests to the owner of the entries: ``subscribe`` (the node holds no record of
    the entry), ``resubscribe`` (it holds one: send it again only if the entry changed), ``cancel``;
    then ``need``, packed bits (numpy ``packbits``, big-endian), one per entry of the node's
    subscriptions at this owner after this message in ascending address order: set where
    whether the node's viewers need the entry in this frame differs from what both ends expect
    (:func:`slc.distributed.state.carried`: as in the last frame; needed, for a new subscription).
    ``kinds``: bytes by :data:`slc.distributed.node.KINDS`."""
    subscribe: np.ndarray = field(default_factory=_keys)
    resubscribe: np.ndarray = field(default_factory=_keys)
    cancel: np.ndarray = field(default_factory=_keys)
    need: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    ADDRESSES = ("subscribe", "resubscribe", "cancel")
    BITS = ("need",)

    @property
    def kinds(self) -> dict:
        return {"requests": sum(len(self.encoded(k)) for k in self.ADDRESSES), "needs": len(self.encoded("need"))}


@dataclass
class SeedQuery(Message):
    """The owner of new entries asks the owner of coarser entries covering them for those of
    ``keys`` that exist (their LOD seeds, :func:`slc.osc.requests.lod_seeds`)."""
    keys: np.ndarray = field(default_factory=_keys)
    ADDRESSES = ("keys",)
    KIND = "seeds"


@dataclass
class SeedRelay(SeedQuery):
    """A seed query a home passes on to the node it delegated the entries' regions to, which
    answers ``origin`` directly."""
    origin: int = -1


@dataclass
class Records(Message):
    """Records of entries: ``keys`` (ascending) and ``words`` (uint32, one row per word of the
    payload's packed record, :meth:`slc.distributed.records.RecordCodec.pack`, one column per
    entry); ``record_kinds``: the payload's record bytes by kind (:data:`KINDS`), ``counts``:
    records by kind; ``kinds`` adds the encoded addresses, shared out by the records' counts."""
    keys: np.ndarray = field(default_factory=_keys)
    words: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.uint32))
    record_kinds: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    ADDRESSES = ("keys",)

    @property
    def kinds(self) -> dict:
        out = dict(self.record_kinds)
        n, key_bytes = max(sum(self.counts.values()), 1), len(self.encoded("keys"))
        share = {k: key_bytes * c // n for k, c in self.counts.items()}
        if share:
            top = max(self.counts, key=self.counts.get)
            share[top] += key_bytes - sum(share.values())
        for k, v in share.items():
            out[k] = out.get(k, 0) + v
        return out


@dataclass
class SeedReply(Records):
    """The records of the queried seeds that exist, from before this frame's update."""


@dataclass
class Delegate(Message):
    """A home hands new ``regions`` (no entry of theirs exists yet) to a node that needs them,
    which owns them for the regions' life."""
    regions: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    ADDRESSES = ("regions",)
    KIND = "ownership"


@dataclass
class Relayed(Requests):
    """A node's requests for entries of regions its home delegated, passed on by the home
    (``src``) to their owner as the node (``client``) made them."""
    client: int = -1


# the phase of the receiver that reads each message (slc.distributed.node.PHASES)
READ_IN = {Requests: "forward", Delegate: "serve", Relayed: "serve", SeedQuery: "answer", SeedRelay: "relay",
           SeedReply: "update", Records: "shade"}
