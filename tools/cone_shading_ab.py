"""Cone shading of this checkout against another checkout's ``slc/cones/shading.py``, on the
same inputs, in one process (docs/cones.md, "Session ovl7").

The inputs are those of the last shading call of a run of ``slc`` on the atrium's overlap rig
(96x54, ``N`` viewers at 100 % overlap, 12 frames). Both versions are frozen, called
alternately (12 times each after 3), with one Dr.Jit thread (or ``threads``); per version the
CPU time of a call (``time.process_time``, after ``dr.sync_thread``; with 2 threads the wall
time, ``time.perf_counter``), the summed kernel-history time, each
launch's operations, lanes and minimum time, and whether the values are equal bit for bit.
Under load the kernel times include time the process was descheduled: compare minima.

    PYTHONPATH=. python tools/cone_shading_ab.py /work/main/slc/cones/shading.py 16 [threads]
"""
from __future__ import annotations

import collections
import importlib.util
import statistics
import sys
import time

import drjit as dr
import mitsuba as mi  # noqa: F401 (variant set by slc)
import numpy as np

from slc import methods, scenes, views
from slc.cones import shading as S
from slc.pipeline import RunConfig, run_sequence


def captured_call(n: int):
    """(scene, ConeShading instance, positional arguments) of the last shading call."""
    s = scenes.load("atrium")
    cap = {}
    orig = S.ConeShading.__call__

    def grab(self, *a):
        cap["args"] = (self, a)
        return orig(self, *a)
    S.ConeShading.__call__ = grab
    try:
        m = methods.create("slc", s, seed=0)
        run_sequence(s, m, views.overlap_rig(s, n, 1.0, aspect=96 / 54),
                     RunConfig(width=96, height=54, frames=12, warmup=10, eval_frames=[], measure_overlap=False))
    finally:
        S.ConeShading.__call__ = orig
    return (s, *cap["args"])


def main(other: str, n: int = 16, threads: int = 1, reps: int = 12):
    dr.set_thread_count(threads)
    s, sh, a = captured_call(n)
    spec = importlib.util.spec_from_file_location("slc.cones.shading_other", other)
    O = importlib.util.module_from_spec(spec)
    O.__package__ = "slc.cones"
    spec.loader.exec_module(O)
    old = O.ConeShading(sh.max_cones, table=O.bsdf_table(s))
    new = S.ConeShading(sh.max_cones, table=S.bsdf_table(s))
    calls = {"other": lambda: old(*a), "this": lambda: new(*a)}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    outs = {}
    for name, c in calls.items():
        for _ in range(3):
            o = c()
            dr.eval(o)
            outs[name] = np.array(o)
    dr.kernel_history()
    print(f"{dr.width(a[1])} pixels; the same values bit for bit: {np.array_equal(outs['other'], outs['this'])}")
    cpu, ker, launches = collections.defaultdict(list), collections.defaultdict(list), collections.defaultdict(list)
    for _ in range(reps):
        for name, c in calls.items():
            dr.sync_thread()
            dr.kernel_history()
            clock = time.process_time if threads == 1 else time.perf_counter
            t0 = clock()
            o = c()
            dr.eval(o)
            dr.sync_thread()
            cpu[name].append((clock() - t0) * 1e3)
            hs = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
            ker[name].append(sum(h.get("execution_time", 0.0) for h in hs))
            launches[name].append([(h.get("operation_count"), h.get("size"), h.get("execution_time"))
                                   for h in hs if h.get("operation_count", 0) > 100])
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    for name in calls:
        ls = launches[name]
        each = [(k[0], k[1], round(min(r[j][2] for r in ls if len(r) > j), 3)) for j, k in enumerate(ls[0])]
        print(f"{name}: {'CPU' if threads == 1 else 'wall'} per call min {min(cpu[name]):.2f} median {statistics.median(cpu[name]):.2f} ms; "
              f"kernels min {min(ker[name]):.2f} median {statistics.median(ker[name]):.2f} ms; "
              f"launches (operations, lanes, min ms): {each}")


if __name__ == "__main__":
    main(sys.argv[1], *[int(x) for x in sys.argv[2:4]])
