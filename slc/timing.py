"""Stage timers for Dr.Jit code.

Dr.Jit is lazy and ``dr.eval`` returns before the CPU work ends, so a stage
is timed as: start clock -> build the stage's values -> ``dr.eval(outputs)``
-> ``dr.sync_thread()`` -> stop clock. Frames before ``warmup`` are
discarded (kernel compilation) and medians are reported.

Usage::

    timer = StageTimer()
    timer.begin_frame()
    with timer.stage("update") as st:
        cache = update(cache)
        st.outputs(cache)
    timer.end_frame()
    timer.summary(warmup=2)   # {"update": median ms, ..., "total": median ms}
"""
from __future__ import annotations

import statistics
import time
from contextlib import contextmanager

import drjit as dr

from . import check


class _Stage:
    def __init__(self):
        self.values = []

    def outputs(self, *values):
        self.values.extend(values)


class StageTimer:
    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.frames: list[dict[str, float]] = []
        self._cur: dict[str, float] | None = None

    def begin_frame(self) -> None:
        self._cur = {}

    def end_frame(self) -> dict[str, float]:
        cur = self._cur or {}
        cur["total"] = sum(v for k, v in cur.items() if k != "total")
        self.frames.append(cur)
        self._cur = None
        return cur

    @contextmanager
    def stage(self, name: str):
        st = _Stage()
        dr.sync_thread()
        t0 = time.perf_counter()
        yield st
        if st.values:
            dr.eval(*st.values)
        dr.sync_thread()
        ms = (time.perf_counter() - t0) * 1e3
        if self._cur is not None:
            self._cur[name] = self._cur.get(name, 0.0) + ms
        if st.values and check.enabled():     # check mode (SLC_CHECK / --check), after the clock
            check.stage_outputs(name, st.values)

    def summary(self, warmup: int = 0) -> dict[str, float]:
        """Median ms per stage over frames after the first ``warmup``."""
        fr = self.frames[warmup:] if len(self.frames) > warmup else self.frames[-1:]
        keys = sorted({k for f in fr for k in f})
        return {k: statistics.median([f.get(k, 0.0) for f in fr]) for k in keys}


class NullTimer(StageTimer):
    """A timer that still evaluates stage outputs but records nothing."""

    def __init__(self):
        super().__init__(enabled=False)


def time_call(fn, *args, repeats: int = 5, warmup: int = 1, **kw):
    """Median wall time (ms) of ``fn(*args)`` whose result is evaluated and
    synchronised, after ``warmup`` discarded calls. Returns (ms, last result)."""
    out, ts = None, []
    for i in range(warmup + repeats):
        dr.sync_thread()
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        dr.eval(out)
        dr.sync_thread()
        if i >= warmup:
            ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), out
