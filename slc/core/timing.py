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

Timed frames must not build kernels: :class:`KernelCounter` counts the
kernels that were compiled or loaded from Dr.Jit's on-disk kernel cache
(anything but an in-memory cache hit) with Dr.Jit's own kernel history.

Kernel time against host time: while Dr.Jit's kernel history is on (it is
during :func:`slc.run.pipeline.run_sequence`), each stage also records the sum of
the ``execution_time`` of the kernels (and memsets, reductions...) launched in
it (:meth:`StageTimer.kernel_summary`). The rest of the stage's wall time is
host time: Python tracing, kernel lookup or compilation, frozen-function
replay, launches and waits. Both timers read the history through one shared
buffer (:func:`_pull`), since reading it clears it.
"""
from __future__ import annotations

import statistics
import time
from contextlib import contextmanager

import drjit as dr

from slc.core import check


_HISTORY: list[dict] = []     # kernel-history entries not yet consumed (dr.kernel_history() clears)
_COUNTERS = 0                  # active KernelCounters (they consume the buffer; otherwise stages clear it)


def _pull() -> None:
    """Move Dr.Jit's kernel history into the shared buffer."""
    if dr.flag(dr.JitFlag.KernelHistory):
        _HISTORY.extend(dr.kernel_history())


def kernel_ms(entries) -> float:
    """Summed execution time (ms) of kernel-history entries."""
    return float(sum(e.get("execution_time", 0.0) or 0.0 for e in entries))


class _Stage:
    def __init__(self):
        self.values = []

    def outputs(self, *values):
        self.values.extend(values)


class StageTimer:
    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.frames: list[dict[str, float]] = []
        self.kernel_frames: list[dict[str, float]] = []   # per frame: {stage: kernel ms} (history on only)
        self._cur: dict[str, float] | None = None
        self._kcur: dict[str, float] | None = None

    def begin_frame(self) -> None:
        self._cur, self._kcur = {}, {}

    def end_frame(self) -> dict[str, float]:
        cur = self._cur or {}
        cur["total"] = sum(v for k, v in cur.items() if k != "total")
        self.frames.append(cur)
        k = self._kcur or {}
        if k:
            k["total"] = sum(v for n, v in k.items() if n != "total")
        self.kernel_frames.append(k)
        self._cur = self._kcur = None
        return cur

    @contextmanager
    def stage(self, name: str):
        st = _Stage()
        dr.sync_thread()
        # A disabled timer (NullTimer) leaves the kernel history to whoever turned it on.
        history = self.enabled and dr.flag(dr.JitFlag.KernelHistory)
        if history:
            _pull()
            mark = len(_HISTORY)
        t0 = time.perf_counter()
        yield st
        if st.values:
            dr.eval(*st.values)
        dr.sync_thread()
        ms = (time.perf_counter() - t0) * 1e3
        if self._cur is not None:
            self._cur[name] = self._cur.get(name, 0.0) + ms
        if history:                           # after the clock: reading the history is not timed
            _pull()
            kms = kernel_ms(_HISTORY[mark:])
            if self._kcur is not None:
                self._kcur[name] = self._kcur.get(name, 0.0) + kms
            if _COUNTERS == 0:
                del _HISTORY[:]
        if st.values and check.enabled():     # check mode (SLC_CHECK / --check), after the clock
            check.stage_outputs(name, st.values)

    def summary(self, warmup: int = 0) -> dict[str, float]:
        """Median ms per stage over frames after the first ``warmup``."""
        fr = self.frames[warmup:] if len(self.frames) > warmup else self.frames[-1:]
        keys = sorted({k for f in fr for k in f})
        return {k: statistics.median([f.get(k, 0.0) for f in fr]) for k in keys}

    def kernel_summary(self, warmup: int = 0) -> dict[str, float]:
        """Median kernel execution ms per stage (and "total") over the frames
        after the first ``warmup``; empty when the kernel history was off.
        Host time of a stage = its :meth:`summary` time minus this."""
        kf = self.kernel_frames
        fr = kf[warmup:] if len(kf) > warmup else kf[-1:]
        if not any(fr):
            return {}
        keys = sorted({k for f in fr for k in f})
        return {k: statistics.median([f.get(k, 0.0) for f in fr]) for k in keys}


class KernelCounter:
    """Kernels built or loaded from disk, from Dr.Jit's kernel history.

    Dr.Jit looks a kernel up by the hash of its IR: first in memory (a hit
    costs nothing), then in the on-disk cache (``~/.drjit``; loading costs a
    few ms), else it compiles it with LLVM (10-200 ms). A history entry of
    type ``KernelType.JIT`` has ``cache_hit = 0`` when it was compiled and
    ``cache_disk = 1`` when it was loaded from disk; :meth:`take` counts both,
    and kernels recorded into a frozen function (``recording_mode ==
    Recorded``: the function was traced again), since the last call (and
    clears the history). Other entry types (memset, compress, reductions...)
    are precompiled and never counted.

    Usage::

        with KernelCounter() as kc:
            kc.take()          # discard what came before
            ...                # the measured work
            n = kc.take()      # kernels built or loaded in between

    The previous state of ``JitFlag.KernelHistory`` is restored on exit.
    """

    def __init__(self):
        self._prev = None
        self.last: list[dict] = []   # the counted entries of the last take()

    def __enter__(self) -> "KernelCounter":
        global _COUNTERS
        self._prev = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        _pull()
        del _HISTORY[:]
        _COUNTERS += 1
        return self

    def __exit__(self, *exc) -> None:
        global _COUNTERS
        _COUNTERS -= 1
        _pull()
        del _HISTORY[:]
        dr.set_flag(dr.JitFlag.KernelHistory, bool(self._prev))

    def take(self) -> int:
        _pull()
        self.last = [e for e in _HISTORY if built(e)]
        del _HISTORY[:]
        return len(self.last)


def built(entry: dict) -> bool:
    """Whether a kernel-history entry was compiled, loaded from disk, or
    recorded into a frozen function (``dr.freeze``: a re-recording traces the
    function again even when its kernels are cached)."""
    if entry.get("type") != dr.KernelType.JIT:
        return False
    if entry.get("recording_mode") == dr.KernelRecordingMode.Recorded:
        return True
    return not entry.get("cache_hit") or bool(entry.get("cache_disk"))


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


STAGE_ORDER = ("requests", "allocate", "queue", "update", "shade")


def stage_table(rows, keys=("scene", "label", "viewers")) -> str:
    """Markdown table of where each row's time goes: per stage the median wall
    ms and, in brackets, the part spent executing kernels (``stages_kernel_ms``;
    wall minus kernel is host time: tracing, lookups, launches, waits). Rows
    without ``stages_ms`` are left out."""
    rows = [r for r in rows if r.get("stages_ms") and not r.get("derived")]
    if not rows:
        return ""
    names = [s for s in STAGE_ORDER if any(s in r["stages_ms"] for r in rows)]
    names += sorted({s for r in rows for s in r["stages_ms"]} - set(names))
    head = "| " + " | ".join(list(keys) + [f"{s} ms (kernel)" for s in names] + ["total ms (kernel)"]) + " |"
    out = [head, "|" + "---|" * (len(keys) + len(names) + 1)]
    for r in rows:
        w, k = r["stages_ms"], r.get("stages_kernel_ms") or {}
        cell = [f"{w[s]:.1f}" + (f" ({k[s]:.1f})" if s in k else "") if s in w else "-" for s in names]
        tot = sum(w.values())
        ktot = f" ({sum(k.values()):.1f})" if k else ""
        out.append("| " + " | ".join([str(r.get(x, "-")) for x in keys] + cell + [f"{tot:.1f}{ktot}"]) + " |")
    return "\n".join(out) + "\n"
