"""A method's run over a sequence, shared by the CLI, the experiments and the notebooks.

The frames are walked by the frame loop (:class:`slc.methods.frames.FrameLoop`, the one the
render nodes' driver walks too). For each frame: pose the scene (:meth:`Scene.set_frame`),
build one G-buffer per viewer, hand all of them to the method (timed by stage; G-buffer
generation and tone mapping are not timed, as in the papers), compose with
directly seen emission, and on evaluation frames compare every viewer's
image with the reference of the method's own ``output`` kind at the same
points (:func:`slc.reference.references.reference_for`: the 2048-sample direct
ground truth, the indirect reference, or both).

Kernels compiled or loaded from Dr.Jit's disk cache while the method
renders are counted per frame (:class:`slc.core.timing.KernelCounter`); their sum
over the timed frames is ``compiled_after_warmup`` in every row, and it must
be 0: otherwise the median time depends on the state of the kernel cache. The
frozen functions' recordings (:func:`slc.core.freeze.recordings`: a function
traced again because its inputs missed its recordings) are counted alike:
``recordings_after_warmup``, 0 when the timed frames replay.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slc.reference import references
from slc.reference.groundtruth import GT_SAMPLES
from slc import methods
from slc.methods import FrameContext, Method
from slc.methods.frames import Frame, FrameLoop
from slc.reference.metrics import evaluate
from slc.core.timing import StageTimer
from slc.scene.views import measure_overlap


@dataclass
class RunConfig:
    """Settings of one sequence run.

    ``eval_frames``: frames compared with the ground truth (default: the last
    frame only). ``warmup``: frames whose timings are discarded."""
    width: int = 320
    height: int = 180
    frames: int = 32
    warmup: int = 4
    eval_frames: list[int] | None = None
    seed: int = 0
    gt_spp: int = GT_SAMPLES
    keep_images: bool = True
    start_frame: int = 0
    frame_step: int = 1               # camera-path frames per rendered frame (frame i is start + i * step)
    eval_viewers: int | None = None   # compare only the first k viewers with the ground truth
    measure_overlap: bool = True      # screen-independent overlap of the viewers' visible surface
    ref_spp: int | None = None        # samples of indirect references (None: references.INDIRECT_SAMPLES)
    on_eval: Callable | None = None   # on_eval(frame, viewer index, gb, image, reference) per evaluated image

    def evaluated(self) -> list[int]:
        if self.eval_frames is None:
            return [self.frames - 1]
        return [f for f in self.eval_frames if 0 <= f < self.frames]


@dataclass
class RunResult:
    method: str
    viewers: int
    time_ms: float
    stages: dict
    metrics: dict
    memory_mb: float
    frames_ms: list = field(default_factory=list)  # per frame: {stage: ms, "total": ms, "kernel": ms, "compiled": n,
    #                                                "recordings": n}, warm-up included
    stages_kernel: dict = field(default_factory=dict)  # median kernel execution ms per stage (the rest is host time)
    compiled_after_warmup: int = 0  # kernels compiled or loaded from disk in the timed frames (0 when steady)
    recordings_after_warmup: int = 0  # frozen-function recordings in the timed frames (0 when steady)
    images: dict = field(default_factory=dict)  # viewer -> {"gt", "img", "flip_map", "exposure"}, last evaluated frame
    last: dict = field(default_factory=dict)    # viewer -> composed image of the last frame
    stats: dict = field(default_factory=dict)

    @property
    def per_frame_ms(self) -> list:
        return [f.get("total", 0.0) for f in self.frames_ms]

    def row(self) -> dict:
        r = {"method": self.method, "viewers": self.viewers, "time_ms": self.time_ms,
             "memory_mb": self.memory_mb, "stages_ms": self.stages,
             "stages_kernel_ms": self.stages_kernel,
             "compiled_after_warmup": int(self.compiled_after_warmup),
             "recordings_after_warmup": int(self.recordings_after_warmup),
             "frames_ms": [{k: round(v, 3) for k, v in f.items()} for f in self.frames_ms]}
        r.update(self.metrics)
        r.update(self.stats)
        return r


def run_sequence(scene, method: Method, viewers, cfg: RunConfig, progress=None) -> RunResult:
    """Render ``cfg.frames`` frames with ``method`` for all ``viewers`` (the frame loop
    :class:`slc.methods.frames.FrameLoop`).

    Kernels built (compiled, loaded from the disk cache, or recorded into a
    frozen function) inside ``method.render`` are counted per frame with Dr.Jit's kernel history
    (the flag's previous state is restored afterwards)."""
    timer = StageTimer()
    method.reset()
    loop = FrameLoop(cfg.frames, cfg.warmup, cfg.start_frame, cfg.frame_step, frozenset(cfg.evaluated()),
                     scene, viewers, cfg.width, cfg.height, timer, count_kernels=True)
    figures = _Figures(scene, method, cfg, progress)
    frames = loop.run(lambda fr: method.render(FrameContext(frame=fr.number), fr.gbuffers, timer), figures.add)
    return figures.result(len(viewers), timer, frames)


class _Figures:
    """What :func:`run_sequence` gathers after every frame: the method's statistics, the
    viewers' measured overlap, the metrics (and images) of evaluated frames, the last frame's
    composed images; then the run's :class:`RunResult`."""

    def __init__(self, scene, method: Method, cfg: RunConfig, progress):
        self.scene, self.method, self.cfg, self.progress = scene, method, cfg, progress
        self.acc: dict[str, list] = {}          # metric -> values over evaluated images
        self.stats: dict[str, list] = {}        # statistic -> per-frame values
        self.images, self.last = {}, {}

    def add(self, fr: Frame, direct: list) -> None:
        """One frame's figures (``direct``: the light per viewer the method returned)."""
        cfg, gbs = self.cfg, fr.gbuffers
        for k, v in self.method.stats().items():
            if isinstance(v, (int, float)):
                # a cache's own overlap of entries is kept apart from the pipeline's measure
                self.stats.setdefault("cache_overlap" if k == "measured_overlap" else k, []).append(float(v))
        if cfg.measure_overlap and len(gbs) > 1 and not fr.warm:
            self.stats.setdefault("measured_overlap", []).append(measure_overlap(gbs))
        if fr.evaluated:
            self._evaluate(fr, direct)
        if cfg.keep_images and fr.last:
            self.last = {gb.viewer: references.image_of(self.method.output, gb, d) for gb, d in zip(gbs, direct)}
        if self.progress is not None:
            self.progress.update(1)

    def _evaluate(self, fr: Frame, direct: list) -> None:
        """Every compared viewer's image against the reference of the method's own output kind
        (direct, indirect or full) at the same points."""
        cfg, m, gbs, f = self.cfg, self.method, fr.gbuffers, fr.number
        n = len(gbs) if cfg.eval_viewers is None else min(cfg.eval_viewers, len(gbs))
        for v, (gb, d) in enumerate(zip(gbs[:n], direct[:n])):
            img = references.image_of(m.output, gb, d)
            gt = references.reference_for(m.output, self.scene, gb, f, gb.viewer,
                                          spp=cfg.gt_spp if m.output == "direct" else cfg.ref_spp,
                                          bounces=references.reference_bounces(m))
            exposure = references.exposure_for(m.output, self.scene, gt)
            metrics = evaluate(gt, img, exposure, with_map=True)
            fmap = metrics.pop("flip_map")
            for k, val in metrics.items():
                self.acc.setdefault(k, []).append(val)
            if cfg.on_eval is not None:
                cfg.on_eval(f, v, gb, img, gt)
            if cfg.keep_images:
                self.images[gb.viewer or f"v{v}"] = {"gt": gt, "img": img, "flip_map": fmap, "frame": f,
                                                     "exposure": exposure}

    def result(self, viewers: int, timer: StageTimer, frames: list[Frame]) -> RunResult:
        """The run's result: medians after the warm-up, mean metrics and statistics."""
        cfg, m = self.cfg, self.method
        compiled, recorded = [fr.compiled for fr in frames], [fr.recordings for fr in frames]
        summ = timer.summary(cfg.warmup)
        ksumm = timer.kernel_summary(cfg.warmup)
        stats = {k: float(np.mean(v if k == "measured_overlap" else (v[cfg.warmup:] if len(v) > cfg.warmup else v)))
                 for k, v in self.stats.items()}
        return RunResult(method=m.name, viewers=viewers, time_ms=summ.get("total", 0.0),
                         stages={k: v for k, v in summ.items() if k != "total"},
                         metrics={k: _mean(v) for k, v in self.acc.items()},
                         memory_mb=m.memory_bytes() / 2 ** 20,
                         stages_kernel={k: v for k, v in ksumm.items() if k != "total"},
                         frames_ms=[dict(f, kernel=k.get("total", 0.0), compiled=c, recordings=n)
                                    for f, k, c, n in zip(timer.frames, timer.kernel_frames, compiled, recorded)],
                         compiled_after_warmup=sum(compiled[cfg.warmup:] if len(compiled) > cfg.warmup
                                                   else compiled[-1:]),
                         recordings_after_warmup=sum(recorded[cfg.warmup:] if len(recorded) > cfg.warmup
                                                     else recorded[-1:]),
                         images=self.images, last=self.last, stats=stats)


def _mean(vals):
    vals = [float(v) for v in vals]
    if any(np.isinf(v) for v in vals):
        finite = [v for v in vals if np.isfinite(v)]
        return float("inf") if not finite else statistics.mean(finite)
    return statistics.mean(vals) if vals else float("nan")


def run_case(scene, spec: str, viewers, cfg, bar=None, seed: int = 0, method=None, **extra) -> dict:
    """One (scene, method, viewers) sequence -> a results row; ``method``: the method ``spec``
    names, made by the caller (from its settings as data), else made here."""
    m = methods.create(spec, scene, seed=seed) if method is None else method
    if bar is not None:
        bar.set_postfix_str(f"{scene.name}/{spec}/{len(viewers)}v")
    res = run_sequence(scene, m, viewers, cfg, progress=bar)
    row = {"scene": scene.name, **res.row(), "setting": spec, "label": m.label or m.name,
           "resolution": f"{cfg.width}x{cfg.height}", **extra}
    row["_result"] = res
    return row
