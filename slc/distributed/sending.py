"""What an owner sends: per other node, the records of the entries it updated in the frame that
the node gets (:func:`records_to`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.distributed.messages import Records
from slc.distributed.owners import changed_records
from slc.distributed.state import Client, in_sorted


def records_to(node, sub, keys: np.ndarray, is_new: np.ndarray) -> list:
    """The :class:`~slc.distributed.messages.Records` ``node`` sends of its entries updated in
    the frame (``sub``: their requests, ``keys`` their addresses, ``is_new`` new at this owner):
    ``full``, every record to every other node; ``sparse``, to a node that needs the entry now,
    its record when the node holds none or the entry changed by more than the threshold since the
    record it holds. Bytes by kind (:data:`slc.distributed.node.KINDS`)."""
    m, s = node.m, node.s
    if dr.width(sub.active) == 0:
        return []
    rec = node.codec.pack(sub.active)
    nb = np.array(node.codec.nbytes(rec), np.int64)
    st = dr.gather(mi.UInt32, m.policy_state, sub.active)       # after this update
    young = np.array((st & 0xFFFF) <= m.ray_policy().new_updates, bool)
    moving = ~young & np.array((st >> 16) > 0, bool)
    rec_np = np.stack([np.array(w, np.uint32) for w in rec])
    out = {}
    streams = [((j, j), node.clients.setdefault((j, j), Client())) for j in node.live if j != node.id]
    streams += [(k, c) for k, c in node.clients.items() if k[0] != k[1] and k[0] in node.live]
    for (j, _), c in streams:
        held, last = c.holds(keys)
        if s.kind == "full":
            send = np.ones(len(keys), bool) if j not in out else np.zeros(len(keys), bool)
        else:
            send = in_sorted(keys, c.needed())
            test = np.nonzero(send & held)[0]
            if len(test):
                t = mi.UInt32(test)
                changed = changed_records(node.codec, [mi.UInt32(w) for w in last[:, test]],
                                          [dr.gather(mi.UInt32, w, t) for w in rec], s.threshold)
                send[test] = np.array(changed, bool)
        idx = np.nonzero(send)[0]
        if len(idx) == 0:
            continue
        again = held[idx]
        kinds = {"new": is_new[idx], "first": ~is_new[idx] & ~again,
                 "resend_young": again & young[idx], "resend_moving": again & moving[idx],
                 "resend_settled": again & ~young[idx] & ~moving[idx]}
        words = rec_np[:, idx]
        c.sent(keys[idx], words)
        part = (keys[idx], words, {k: int(nb[idx][v].sum()) for k, v in kinds.items()},
                {k: int(v.sum()) for k, v in kinds.items()})
        out.setdefault(j, []).append(part)
    return [_message(node, j, parts) for j, parts in out.items()]


def _message(node, j: int, parts: list) -> Records:
    """One message to node ``j`` of the records of ``parts`` (disjoint entries), ascending by address."""
    keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(keys)
    return Records(node.id, j, node.frame, keys=keys[order], words=np.concatenate([p[1] for p in parts], axis=1)[:, order],
                   record_kinds={k: sum(p[2][k] for p in parts) for k in parts[0][2]},
                   counts={k: sum(p[3][k] for p in parts) for k in parts[0][3]})
