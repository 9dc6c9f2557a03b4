"""The driver of render nodes: it runs the phases of every frame on every live node and carries
their messages, ``delay`` frames late, through a transport: :class:`InProcess` (the
:class:`~slc.distributed.node.Node` objects in this process, for tests) or
:class:`slc.distributed.actors.RayNodes` (one Ray actor process per node, for runs).

A transport answers a phase call per node with the node's result, or :data:`DEAD` when the node
is gone (a Ray actor whose process died, a node :meth:`Cluster.kill` ended). Whichever the
transport, a lost node takes one path (:meth:`Cluster.lose`): the rest of the frame runs without
it, its messages in flight are dropped, and before the next frame every survivor drops it
(:meth:`slc.distributed.node.Node.drop`).

Bytes are counted per message sent: by the protocol's own count (``nbytes``, by kind) and
pickled (protocol 5, as Ray's object store carries a message from one process to the next; a
message crosses one link: Ray carries it through the driver, whose second hop is not counted).
"""
from __future__ import annotations

import pickle
import time

from slc.distributed.messages import READ_IN
from slc.distributed.node import KINDS, PHASES

DEAD = object()


class InProcess:
    """Nodes (:class:`~slc.distributed.node.Node`) in this process."""

    def __init__(self, nodes: dict):
        self.nodes, self.dead = dict(nodes), set()

    def call(self, phase: str, args: dict) -> dict:
        return {n: DEAD if n in self.dead else getattr(self.nodes[n], phase)(*a) for n, a in args.items()}

    def kill(self, node: int) -> None:
        self.dead.add(node)

    def drop(self, dead: int, live_before: list, survivors: list) -> None:
        for n in survivors:
            self.nodes[n].drop(dead, live_before)


class Cluster:
    """The live nodes ``live`` behind ``transport``, messages ``delay`` frames late."""

    def __init__(self, transport, live: list, delay: int = 0):
        self.t, self.live, self.delay = transport, [int(n) for n in live], int(delay)
        self.queue: dict = {}       # (frame, phase, node) -> messages
        self.lost: list = []

    def kill(self, node: int) -> None:
        """End node ``node`` (its process, on Ray): the next call finds it gone."""
        self.t.kill(node)

    def step(self, frame: int, images: bool = False) -> dict:
        """One frame on every live node. Returns ``results`` (node -> its ``shade`` result),
        ``frame_ms`` (the driver's wall time of the frame), ``bytes`` and ``serialized``
        (sent in the frame, all nodes), ``kinds`` (bytes by :data:`KINDS`), ``messages`` and
        ``links`` (distinct (sender, receiver) pairs)."""
        t0 = time.perf_counter()
        acc = {"bytes": 0, "serialized": 0, "messages": 0, "links": set(), "kinds": dict.fromkeys(KINDS, 0)}
        gone, results = [], {}
        for phase in PHASES:
            args = {}
            for n in self.live:
                if n in gone:
                    continue
                inbox = self.queue.pop((frame, phase, n), [])
                args[n] = (frame,) if phase == "begin" else (inbox, images) if phase == "shade" else (inbox,)
            for n, res in self.t.call(phase, args).items():
                if res is DEAD:
                    gone.append(n)
                elif phase == "shade":
                    results[n] = res
                else:
                    for msg in res:
                        self._post(frame, msg, acc)
        for n in gone:
            self.lose(n)
        acc["links"] = len(acc["links"])
        return {"results": results, "frame_ms": 1e3 * (time.perf_counter() - t0), **acc}

    def _post(self, frame: int, msg, acc: dict) -> None:
        acc["bytes"] += msg.nbytes
        acc["serialized"] += len(pickle.dumps(msg, protocol=5))
        acc["messages"] += 1
        acc["links"].add((msg.src, msg.dst))
        for k, v in msg.kinds.items():
            acc["kinds"][k] += v
        self.queue.setdefault((frame + self.delay, READ_IN[type(msg)], msg.dst), []).append(msg)

    def lose(self, node: int) -> None:
        """Node ``node`` is gone (see the module)."""
        if node not in self.live:
            return
        before = list(self.live)
        self.live.remove(node)
        self.lost.append(node)
        self.queue = {k: [m for m in msgs if m.src != node] for k, msgs in self.queue.items() if k[2] != node}
        self.t.drop(node, before, list(self.live))
