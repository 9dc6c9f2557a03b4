"""What a render node keeps of the other nodes (numpy, on the host): its subscriptions at each
owner (:class:`Subscriptions`) and, as an owner, what each other node asked for and holds
(:class:`Client`). Entries are named by address (:mod:`slc.distributed.messages`); every set is
a sorted ``uint32`` array, so that both ends of a link order a subscription list alike."""
from __future__ import annotations

import numpy as np

from slc.distributed.messages import Requests

_NONE = np.zeros(0, np.uint32)


def in_sorted(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """Mask over ``a``: the elements found in the sorted array ``sorted_b``."""
    if len(sorted_b) == 0 or len(a) == 0:
        return np.zeros(len(a), bool)
    i = np.minimum(np.searchsorted(sorted_b, a), len(sorted_b) - 1)
    return sorted_b[i] == a


class Subscriptions:
    """A node's subscriptions at one owner: ``keys`` (sorted) and the frame each was last
    needed; ``bits``: the need bits last sent."""

    def __init__(self):
        self.keys, self.last, self.bits = _NONE, np.zeros(0, np.int64), None

    def frame(self, src: int, dst: int, frame: int, needed: np.ndarray, lease: int, holds) -> Requests | None:
        """This frame's :class:`Requests` to the owner, or None when nothing changed: ``needed``
        (sorted) the entries of this owner the node's viewers need now; an entry not needed for
        more than ``lease`` frames is cancelled; ``holds(keys)``: a mask of the new ones the node
        holds a record of (they are re-subscriptions)."""
        now = in_sorted(self.keys, needed)
        self.last[now] = frame
        expired = ~now & (frame - self.last > lease)
        new = needed[~in_sorted(needed, self.keys)]
        cancel = self.keys[expired]
        keys = np.concatenate([self.keys[~expired], new])
        last = np.concatenate([self.last[~expired], np.full(len(new), frame, np.int64)])
        order = np.argsort(keys, kind="stable")
        self.keys, self.last = keys[order], last[order]
        bits = np.packbits(in_sorted(self.keys, needed))
        if len(new) == 0 and len(cancel) == 0 and self.bits is not None and np.array_equal(bits, self.bits):
            return None
        self.bits = bits
        h = holds(new) if len(new) else np.zeros(0, bool)
        return Requests(src, dst, frame, subscribe=new[~h], resubscribe=new[h], cancel=cancel, need=bits)


class Client:
    """What an owner knows of one other node: its subscriptions ``keys`` (sorted) with their
    ``need`` flags of the last message, and the records it holds (``held_keys``, sorted, with
    the words last sent, ``held_words``: one row per word) whether it still subscribes or not."""

    def __init__(self):
        self.keys, self.need = _NONE, np.zeros(0, bool)
        self.held_keys, self.held_words = _NONE, np.zeros((0, 0), np.uint32)

    def apply(self, msg: Requests) -> None:
        """Subscriptions, cancellations and need bits of ``msg`` (see :class:`Requests`)."""
        add = np.union1d(msg.subscribe, msg.resubscribe).astype(np.uint32)
        keys = np.union1d(self.keys[~in_sorted(self.keys, np.sort(msg.cancel))], add).astype(np.uint32)
        if len(msg.need) or len(add) or len(msg.cancel):
            self.need = np.unpackbits(msg.need, count=len(keys)).astype(bool) if len(keys) else np.zeros(0, bool)
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
