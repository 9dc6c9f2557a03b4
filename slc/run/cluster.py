"""Jobs on Ray: a pool of scene-caching actors (used by :mod:`slc.run.jobs`).

- ``RayPool(runner, workers=N)`` starts a local Ray instance in this process (no
  dashboard) with N actors; ``RayPool(runner, address="auto" | "HOST:PORT")``
  connects to a running cluster (``ray start --head`` / ``ray start
  --address``, see ``docs/cluster.md``).
- Each actor (:class:`SceneWorker`) reserves ``threads`` CPUs and runs one
  job at a time with ``dr.set_thread_count(threads)``, keeping the last scene
  it loaded. The driver hands a free actor a job of the scene it already has
  when there is one, else a job of the scene with the most pending jobs per
  actor already holding it.
- Threads: on a local instance ``cores // N`` (at least 1); on a cluster the
  CPUs of the smallest node, so that by default one timed job runs per node
  (no two jobs compete for a node's cores and memory bandwidth), and N the
  cluster's CPUs // threads. ``--threads`` overrides both.
- A job that raises in an actor is retried there; an actor that dies (a
  killed process, a lost node) fails the attempt of the job it ran and is
  replaced by a new actor (at most ``workers * (retries + 1)`` replacements).
- Workers see the driver's ``SLC_VARIANT`` (the same backend everywhere),
  ``SLC_CHECK`` (check mode) and ``SLC_CACHE`` when set (the ground-truth cache: put it on storage every node
  shares) and a ``PYTHONPATH`` that starts with this checkout.
"""
from __future__ import annotations

import logging
import os
import socket
import time
from collections import deque
from pathlib import Path

import numpy as np
import ray

from slc.core import backend
from slc.run.errors import ExperimentError, raise_fatal


@ray.remote
class SceneWorker:
    """A Ray actor running jobs one at a time on a ``runner`` (:class:`slc.run.jobs.Runner`)."""

    def __init__(self, runner, threads: int):
        self.runner = runner(threads)

    def info(self) -> dict:
        return {"host": socket.gethostname(), "pid": os.getpid(), "threads": self.runner.threads}

    def run(self, job) -> dict:
        res = self.runner.run_safe(job)
        res["node"] = ray.get_runtime_context().get_node_id()
        return res


def _runtime_env() -> dict:
    root = str(Path(__file__).resolve().parents[2])
    env = {"SLC_VARIANT": backend.variant(),
           "PYTHONPATH": os.pathsep.join([root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                   if p and p != root])}
    for k in ("SLC_CACHE", "SLC_CHECK"):  # shared ground-truth cache; check mode (slc --check)
        if os.environ.get(k):
            env[k] = os.environ[k]
    return {"env_vars": env}


def _writable(obj):
    """Ray hands numpy arrays back read-only (zero-copy from its object
    store); copy them so the driver's writers (e.g. ``mi.Bitmap``) take them."""
    if isinstance(obj, np.ndarray):
        return obj if obj.flags.writeable else obj.copy()
    if isinstance(obj, dict):
        return {k: _writable(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_writable(v) for v in obj]
    return obj


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """One line instead of Ray's minutes of reconnection attempts when a
    HOST:PORT head is not listening."""
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout).close()
    except (OSError, ValueError) as e:
        raise ExperimentError(f"no Ray head at '{address}' ({e}); start one with 'ray start --head' "
                              f"(docs/cluster.md)") from None


class RayPool:
    """N :class:`SceneWorker` actors on a local instance or a cluster."""

    def __init__(self, runner, workers: int | None = None, address: str | None = None,
                 threads: int | None = None):
        self._own = not ray.is_initialized()
        kw = dict(logging_level=logging.WARNING, runtime_env=_runtime_env())
        if address:
            if self._own:
                _check_reachable(address)
                try:
                    ray.init(address=address, **kw)
                except (ConnectionError, ValueError, RuntimeError) as e:
                    msg = str(e).strip().splitlines()
                    raise ExperimentError(f"cannot connect to Ray at '{address}': {msg[0] if msg else e}") from None
            cpus = [int(n["Resources"].get("CPU", 0)) for n in ray.nodes() if n.get("Alive")]
            cpus = [c for c in cpus if c > 0] or [1]
            threads = threads or min(cpus)
            workers = workers or max(sum(c // threads for c in cpus), 1)
        else:
            threads = threads or max((os.cpu_count() or 1) // workers, 1)
            if self._own:
                # a new local instance, never another process's cluster on this machine
                ray.init(address="local", num_cpus=workers * threads, include_dashboard=False,
                         _system_config=backend.RAY_SYSTEM_CONFIG, **kw)
        self.runner, self.workers, self.threads = runner, workers, threads
        self._replacements = 0
        self.actors = [self._new_actor() for _ in range(workers)]
        # wait until every worker has imported slc, so that jobs are not charged with worker start-up
        self.info = self._started()

    def _new_actor(self):
        return SceneWorker.options(num_cpus=self.threads, scheduling_strategy="SPREAD",
                                   max_restarts=0, max_task_retries=0).remote(self.runner, self.threads)

    def _started(self) -> list:
        """Every worker's ``info`` once it has started; a worker that dies before it starts (Ray
        cancels an actor whose process does not come up) is replaced, at most ``workers`` times
        in all."""
        info, tries = [None] * len(self.actors), 0
        while True:
            refs = {a.info.remote(): i for i, a in enumerate(self.actors) if info[i] is None}
            if not refs:
                return info
            for ref, i in refs.items():
                try:
                    info[i] = ray.get(ref)
                except ray.exceptions.RayError as e:
                    tries += 1
                    if tries > self.workers:
                        msg = str(e).strip().splitlines()
                        raise ExperimentError(f"Ray workers do not start: {msg[0] if msg else type(e).__name__}") from None
                    try:
                        ray.kill(self.actors[i])
                    except Exception:
                        pass
                    self.actors[i] = self._new_actor()

    def close(self) -> None:
        for a in self.actors:
            try:
                ray.kill(a)
            except Exception:
                pass
        self.actors = []
        if self._own and ray.is_initialized():
            ray.shutdown()

    # ----------------------------------------------------------------------
    def run(self, jobs, finished, gave_up, retries: int, progress) -> None:
        """Run ``jobs``; ``finished(job, result, t_submit, attempts)`` or
        ``gave_up(job, error)`` is called on this thread for each."""
        self._max_replacements = self.workers * (retries + 1)
        pending = deque(jobs)
        attempts: dict[str, int] = {}
        holds: dict = {a: None for a in self.actors}  # actor -> scene it has loaded
        idle = list(self.actors)
        inflight: dict = {}  # ObjectRef -> (actor, job, t_submit)

        def pick(actor):
            same = [j for j in pending if j.scene == holds.get(actor)]
            if same:
                job = same[0]
            else:
                counts: dict[str, int] = {}
                for j in pending:
                    counts[j.scene] = counts.get(j.scene, 0) + 1
                held = list(holds.values())
                best = max(counts, key=lambda s: (counts[s] / (1 + held.count(s)), -list(counts).index(s)))
                job = next(j for j in pending if j.scene == best)
            pending.remove(job)
            return job

        def retry_or_give_up(job, err):
            n = attempts[job.key]
            if n <= retries:
                progress.note(f"{job.describe()}: attempt {n} failed ({err}); retrying")
                pending.appendleft(job)
            else:
                gave_up(job, err)

        while pending or inflight:
            while idle and pending:
                actor = idle.pop()
                job = pick(actor)
                attempts[job.key] = attempts.get(job.key, 0) + 1
                inflight[actor.run.remote(job)] = (actor, job, time.perf_counter())
                holds[actor] = job.scene
            if not inflight:
                if not self.actors:
                    for job in list(pending):
                        gave_up(job, "no Ray worker left")
                    pending.clear()
                break
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=1.0)
            for ref in ready:
                actor, job, t0 = inflight.pop(ref)
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as e:  # the actor (process or node) died
                    self._drop(actor, holds)
                    replacement = self._replace()
                    if replacement is not None:
                        holds[replacement] = None
                        idle.append(replacement)
                    msg = str(e).strip().splitlines()
                    retry_or_give_up(job, f"worker lost: {type(e).__name__}: {msg[0] if msg else ''}")
                    continue
                idle.append(actor)
                res = _writable(res)
                raise_fatal(res)  # check mode: the first bad value stops the run
                if "error" in res:
                    retry_or_give_up(job, res["error"])
                else:
                    finished(job, res, t0, attempts[job.key])

    def _drop(self, actor, holds) -> None:
        holds.pop(actor, None)
        if actor in self.actors:
            self.actors.remove(actor)
        try:
            ray.kill(actor)
        except Exception:
            pass

    def _replace(self):
        if self._replacements >= getattr(self, "_max_replacements", self.workers):
            return None
        self._replacements += 1
        a = self._new_actor()
        self.actors.append(a)
        return a
