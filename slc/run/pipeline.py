"""The frame loop shared by the CLI, the experiments and the notebooks.

For each frame: pose the scene (:meth:`Scene.set_frame`), build one G-buffer
per viewer, hand all of them to the method (timed by stage; G-buffer
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

from slc.core import freeze
from slc.scene import gbuffer as gbuf
from slc.reference import references
from slc.reference.groundtruth import GT_SAMPLES
from slc import methods
from slc.methods import FrameContext, Method
from slc.reference.metrics import evaluate
from slc.core.timing import KernelCounter, StageTimer
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
    """Render ``cfg.frames`` frames with ``method`` for all ``viewers``.

    Kernels built (compiled, loaded from the disk cache, or recorded into a
    frozen function) inside ``method.render`` are counted per frame with Dr.Jit's kernel history
    (the flag's previous state is restored afterwards)."""
    with KernelCounter() as kc:
        return _run_sequence(scene, method, viewers, cfg, progress, kc)


def _run_sequence(scene, method: Method, viewers, cfg: RunConfig, progress, kc: KernelCounter) -> RunResult:
    timer = StageTimer()
    compiled: list[int] = []
    recorded: list[int] = []
    method.reset()
    evals = set(cfg.evaluated())
    acc: dict[str, list] = {}
    images = {}
    stats_acc: dict[str, list] = {}
    last = {}
    for i in range(cfg.frames):
        f = cfg.start_frame + i * cfg.frame_step
        gbs = gbuf.frame_gbuffers(scene, viewers, f, cfg.width, cfg.height)
        ctx = FrameContext(frame=f)
        kc.take()                 # kernels of the G-buffer and of the previous frame's evaluation
        recs = freeze.recordings()
        timer.begin_frame()
        direct = method.render(ctx, gbs, timer)      # in check mode its images are checked (Method.render)
        timer.end_frame()
        compiled.append(kc.take())
        recorded.append(freeze.recordings() - recs)
        for k, v in method.stats().items():
            if isinstance(v, (int, float)):
                # a cache's own overlap of entries is kept apart from the pipeline's measure
                stats_acc.setdefault("cache_overlap" if k == "measured_overlap" else k, []).append(float(v))
        if cfg.measure_overlap and len(gbs) > 1 and i >= cfg.warmup:
            stats_acc.setdefault("measured_overlap", []).append(measure_overlap(gbs))
        if i in evals:
            k = len(gbs) if cfg.eval_viewers is None else min(cfg.eval_viewers, len(gbs))
            for v, (gb, d) in enumerate(zip(gbs[:k], direct[:k])):
                # the reference of the method's own output kind (direct, indirect or full)
                img = references.image_of(method.output, gb, d)
                gt = references.reference_for(method.output, scene, gb, f, gb.viewer,
                                              spp=cfg.gt_spp if method.output == "direct" else cfg.ref_spp,
                                              bounces=references.reference_bounces(method))
                exposure = references.exposure_for(method.output, scene, gt)
                m = evaluate(gt, img, exposure, with_map=True)
                fmap = m.pop("flip_map")
                for k, val in m.items():
                    acc.setdefault(k, []).append(val)
                if cfg.on_eval is not None:
                    cfg.on_eval(f, v, gb, img, gt)
                if cfg.keep_images:
                    images[gb.viewer or f"v{v}"] = {"gt": gt, "img": img, "flip_map": fmap, "frame": f,
                                                    "exposure": exposure}
        if cfg.keep_images and i == cfg.frames - 1:
            last = {gb.viewer: references.image_of(method.output, gb, d) for gb, d in zip(gbs, direct)}
        if progress is not None:
            progress.update(1)
    summ = timer.summary(cfg.warmup)
    ksumm = timer.kernel_summary(cfg.warmup)
    metrics = {k: _mean(v) for k, v in acc.items()}
    stats = {k: float(np.mean(v if k == "measured_overlap" else (v[cfg.warmup:] if len(v) > cfg.warmup else v)))
             for k, v in stats_acc.items()}
    return RunResult(method=method.name, viewers=len(viewers), time_ms=summ.get("total", 0.0),
                     stages={k: v for k, v in summ.items() if k != "total"}, metrics=metrics,
                     memory_mb=method.memory_bytes() / 2 ** 20,
                     stages_kernel={k: v for k, v in ksumm.items() if k != "total"},
                     frames_ms=[dict(f, kernel=k.get("total", 0.0), compiled=c, recordings=n)
                                for f, k, c, n in zip(timer.frames, timer.kernel_frames, compiled, recorded)],
                     compiled_after_warmup=sum(compiled[cfg.warmup:] if len(compiled) > cfg.warmup
                                               else compiled[-1:]),
                     recordings_after_warmup=sum(recorded[cfg.warmup:] if len(recorded) > cfg.warmup
                                                 else recorded[-1:]),
                     images=images, last=last,
                     stats=stats)


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
