"""What a render node keeps of the other nodes (numpy, on the host): its subscriptions at each
owner (:class:`Subscriptions`) and, as an owner, what each other node asked for and holds
(:class:`Client`). Entries are named by address (:mod:`slc.distributed.messages`); every set is
a sorted ``uint32`` array, so that both ends of a link order a subscription list alike."""
from __future__ import annotations

import numpy as np

from slc.distributed.messages import Relayed, Requests

_NONE = np.zeros(0, np.uint32)


def in_sorted(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """Mask over ``a``: the elements found in the sorted array ``sorted_b``."""
    if len(sorted_b) == 0 or len(a) == 0:
        return np.zeros(len(a), bool)
    i = np.minimum(np.searchsorted(sorted_b, a), len(sorted_b) - 1)
    return sorted_b[i] == a


def carried(old_keys: np.ndarray, old_flags: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """The flags both ends of a link expect for the sorted ``keys``: an entry's flag of the last
    frame, set for an entry new to the list (a node subscribes when it needs the entry)."""
    out = np.ones(len(keys), bool)
    if len(old_keys) and len(keys):
        i = np.minimum(np.searchsorted(old_keys, keys), len(old_keys) - 1)
        hit = old_keys[i] == keys
        out[hit] = old_flags[i[hit]]
    return out


class Subscriptions:
    """A node's subscriptions at one owner: ``keys`` (sorted), the frame each was last needed,
    and the need flags last sent (``flags``)."""

    def __init__(self):
        self.keys, self.last, self.flags = _NONE, np.zeros(0, np.int64), np.zeros(0, bool)

    def frame(self, src: int, dst: int, frame: int, needed: np.ndarray, lease: int, holds) -> Requests | None:
        """This frame's :class:`Requests` to the owner, or None when nothing changed: ``needed``
        (sorted) the entries of this owner the node's viewers need now; an entry not needed for
        more than ``lease`` frames is cancelled; ``holds(keys)``: a mask of the new ones the node
        holds a record of (they are re-subscriptions). The need bits sent are those that differ
        from the expected ones (:func:`carried`)."""
        now = in_sorted(self.keys, needed)
        self.last[now] = frame
        expired = ~now & (frame - self.last > lease)
        new = needed[~in_sorted(needed, self.keys)]
        cancel = self.keys[expired]
        keys = np.concatenate([self.keys[~expired], new])
        last = np.concatenate([self.last[~expired], np.full(len(new), frame, np.int64)])
        order = np.argsort(keys, kind="stable")
        keys, last = keys[order], last[order]
        expect, flags = carried(self.keys, self.flags, keys), in_sorted(keys, needed)
        self.keys, self.last, self.flags = keys, last, flags
        if len(new) == 0 and len(cancel) == 0 and np.array_equal(flags, expect):
            return None
        h = holds(new) if len(new) else np.zeros(0, bool)
        return Requests(src, dst, frame, subscribe=new[~h], resubscribe=new[h], cancel=cancel,
                        need=np.packbits(flags ^ expect))


class Client:
    """What an owner knows of one other node: its subscriptions ``keys`` (sorted) with their
    ``need`` flags of the last message, and the records it holds (``held_keys``, sorted, with
    the words last sent, ``held_words``: one row per word) whether it still subscribes or not."""

    def __init__(self):
        self.keys, self.need = _NONE, np.zeros(0, bool)
        self.held_keys, self.held_words = _NONE, np.zeros((0, 0), np.uint32)
        self.resubscribed = _NONE         # the re-subscriptions of the last message (sorted)

    def apply(self, msg: Requests) -> None:
        """Subscriptions, cancellations and need bits of ``msg`` (see :class:`Requests`)."""
        self.resubscribed = np.sort(msg.resubscribe).astype(np.uint32)
        add = np.union1d(msg.subscribe, msg.resubscribe).astype(np.uint32)
        keys = np.union1d(self.keys[~in_sorted(self.keys, np.sort(msg.cancel))], add).astype(np.uint32)
        flip = np.unpackbits(msg.need, count=len(keys)).astype(bool) if len(keys) else np.zeros(0, bool)
        self.need = carried(self.keys, self.need, keys) ^ flip
        self.keys = keys
        if len(msg.subscribe):            # the node holds no record of these (any more)
            self.forget(np.sort(msg.subscribe))

    def needed(self) -> np.ndarray:
        return self.keys[self.need] if len(self.need) == len(self.keys) else _NONE

    def forget(self, keys: np.ndarray) -> None:
        """The node holds no record of ``keys`` (sorted)."""
        keep = ~in_sorted(self.held_keys, keys)
        self.held_keys, self.held_words = self.held_keys[keep], self.held_words[:, keep]

    def holds(self, keys: np.ndarray) -> tuple:
        """(mask over ``keys``: the node holds a record, the words sent, zeros where not)."""
        n = len(self.held_keys)
        if n == 0 or len(keys) == 0:
            return np.zeros(len(keys), bool), np.zeros((self.held_words.shape[0], len(keys)), np.uint32)
        i = np.minimum(np.searchsorted(self.held_keys, keys), n - 1)
        found = self.held_keys[i] == keys
        return found, np.where(found[None, :], self.held_words[:, i], 0).astype(np.uint32)

    def sent(self, keys: np.ndarray, words: np.ndarray) -> None:
        """Records ``words`` of ``keys`` were sent to the node: it holds them now."""
        if len(keys) == 0:
            return
        if self.held_words.shape[0] != words.shape[0]:          # the first records sent
            self.held_words = np.zeros((words.shape[0], len(self.held_keys)), np.uint32)
        keep = ~in_sorted(self.held_keys, np.sort(keys))
        k = np.concatenate([self.held_keys[keep], keys])
        w = np.concatenate([self.held_words[:, keep], words], axis=1)
        order = np.argsort(k, kind="stable")
        self.held_keys, self.held_words = k[order], w[:, order]

    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.need.nbytes + self.held_keys.nbytes + self.held_words.nbytes)


class Relay:
    """What a home passes on to the owner of regions it delegated, of one node's subscriptions
    there: the node's subscriptions in those regions (``keys``, sorted) and their need flags
    (``flags``), as :class:`~slc.distributed.messages.Relayed` requests."""

    def __init__(self):
        self.keys, self.flags = _NONE, np.zeros(0, bool)

    def frame(self, home: int, owner: int, client: int, frame: int, keys: np.ndarray, need: np.ndarray,
              resubscribed: np.ndarray) -> Relayed | None:
        """This frame's relayed requests (None when nothing changed): ``keys`` (sorted) the
        node's subscriptions in the owner's regions, ``need`` their need flags, ``resubscribed``
        (sorted) what the node re-subscribed to in this frame."""
        new = keys[~in_sorted(keys, self.keys)]
        cancel = self.keys[~in_sorted(self.keys, keys)]
        expect = carried(self.keys, self.flags, keys)
        self.keys, self.flags = keys, np.asarray(need, bool)
        if len(new) == 0 and len(cancel) == 0 and np.array_equal(self.flags, expect):
            return None
        h = in_sorted(new, resubscribed)
        return Relayed(home, owner, frame, subscribe=new[~h], resubscribe=new[h], cancel=cancel,
                       need=np.packbits(self.flags ^ expect), client=client)
