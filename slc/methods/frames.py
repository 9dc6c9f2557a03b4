"""The frame loop of a run, the one the experiment pipeline (:func:`slc.run.pipeline.run_sequence`)
and the driver of render nodes (:mod:`slc.distributed.run`, :mod:`slc.distributed.actors`) walk.

:meth:`FrameLoop.run` walks the run's frames: frame ``i`` of the run is the camera path's frame
``start + i * step``, the first ``warmup`` are warm-up frames (their figures are discarded), the
run indices ``evaluated`` are compared with a reference. Per frame it

1. makes the viewers' G-buffers when it is given the viewers
   (:func:`slc.scene.gbuffer.frame_gbuffers`; render nodes make their own);
2. calls ``render(frame)``: the method's frame (``Method.render``) or a cluster's
   (``Cluster.step``), timed by ``timer`` (:class:`slc.core.timing.StageTimer`) when given;
   around it the kernels compiled or loaded (``count_kernels``:
   :class:`slc.core.timing.KernelCounter`) and the frozen functions' recordings
   (:func:`slc.core.freeze.recordings`) are counted;
3. calls ``done(frame, out)`` with what ``render`` returned: the caller's figures, its
   evaluation at evaluated frames (neither timed nor counted).
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Callable

from slc.core import freeze
from slc.core.timing import KernelCounter, StageTimer
from slc.scene import gbuffer as gbuf


@dataclass
class Frame:
    """One frame of a run (see the module)."""
    index: int                    # i: the frame's place in the run
    number: int                   # the camera path's frame, start + i * step
    warm: bool                    # a warm-up frame
    evaluated: bool               # compared with a reference
    last: bool                    # the run's last frame
    gbuffers: list | None = None  # the viewers' G-buffers (None: the loop was not given the viewers)
    compiled: int = 0             # kernels compiled or loaded in render (0 unless count_kernels)
    recordings: int = 0           # frozen-function recordings in render


@dataclass
class FrameLoop:
    """The frames of a run (see the module): ``frames`` frames from the camera path's frame
    ``start`` in steps of ``step``, ``warmup`` of them warm-up, the run indices ``evaluated``
    evaluated; with ``viewers``, their G-buffers of ``scene`` at ``width`` x ``height``."""
    frames: int
    warmup: int = 0
    start: int = 0
    step: int = 1
    evaluated: frozenset = frozenset()
    scene: object = None
    viewers: list | None = None
    width: int = 0
    height: int = 0
    timer: StageTimer | None = None
    count_kernels: bool = False

    def run(self, render: Callable, done: Callable) -> list[Frame]:
        """Every frame: ``out = render(frame)``, then ``done(frame, out)``; the frames walked."""
        with KernelCounter() if self.count_kernels else nullcontext() as kc:
            return [self._frame(i, render, done, kc) for i in range(self.frames)]

    def _frame(self, i: int, render: Callable, done: Callable, kc: KernelCounter | None) -> Frame:
        f = self.start + i * self.step
        fr = Frame(index=i, number=f, warm=i < self.warmup, evaluated=i in self.evaluated,
                   last=i == self.frames - 1)
        if self.viewers is not None:
            fr.gbuffers = gbuf.frame_gbuffers(self.scene, self.viewers, f, self.width, self.height)
        if kc is not None:
            kc.take()             # kernels of the G-buffer and of the previous frame's evaluation
        recs = freeze.recordings()
        if self.timer is not None:
            self.timer.begin_frame()
        out = render(fr)
        if self.timer is not None:
            self.timer.end_frame()
        if kc is not None:
            fr.compiled = kc.take()
        fr.recordings = freeze.recordings() - recs
        done(fr, out)
        return fr
