"""Jobs as data: a :class:`Job` is one scene and the :class:`Case` s run on it side by side, its viewers
travelling as a :class:`Rig` (every viewer's camera at every frame the run touches), so that a job
pickles and a worker rebuilds exactly the same cameras without the experiment's code. Its key hashes
everything that decides its rows (see :mod:`slc.run.jobs`)."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slc.scene.camera import Viewer

class FrozenPose:
    """A viewer's camera at a fixed set of frames (picklable stand-in for a
    :class:`~slc.scene.camera.Viewer` pose function)."""

    def __init__(self, cameras: dict):
        self.cameras = cameras

    def __call__(self, frame):
        try:
            return self.cameras[int(frame)]
        except KeyError:
            raise KeyError(f"frame {frame} is outside the frames this job was built for "
                           f"({min(self.cameras)}-{max(self.cameras)})") from None


@dataclass(frozen=True)
class Rig:
    """Viewers as data: ``(name, rig, {frame: Camera})`` per viewer, for the
    frames ``cfg`` renders (and the frame before each, for motion)."""
    viewers: tuple

    @classmethod
    def from_viewers(cls, viewers, cfg) -> "Rig":
        first = max(cfg.start_frame - 1, 0)
        frames = range(first, cfg.start_frame + cfg.frames)
        return cls(tuple((v.name, v.rig, {f: v.camera(f) for f in frames}) for v in viewers))

    def build(self) -> list:
        return [Viewer(name, FrozenPose(cams), rig) for name, rig, cams in self.viewers]

    def __len__(self) -> int:
        return len(self.viewers)

    def fingerprint(self) -> str:
        h = hashlib.sha1()
        for name, rig, cams in self.viewers:
            h.update(f"{name}|{rig}|".encode())
            for f in sorted(cams):
                c = cams[f]
                h.update(str(f).encode())
                for a in (c.origin, c.target, c.up, [c.fov]):
                    h.update(np.asarray(a, np.float64).tobytes())
        return h.hexdigest()[:16]


@dataclass(frozen=True)
class Case:
    """One (method, viewers) sequence of a job -> one row. ``index`` is the
    case's place in the experiment's order (not part of the key)."""
    spec: str
    rig: Rig
    extra: dict = field(default_factory=dict)
    index: int = 0


@dataclass
class Job:
    """Cases on one scene, run in order in one process (see the module).

    ``scene`` is what :func:`slc.scene.scenes.load` takes (a built-in name or a
    path, which must then exist on every worker); ``keep_images`` returns the
    evaluated images to the driver (for the experiment's image files)."""
    experiment: str
    scene: str
    cases: tuple
    cfg: object
    seed: int = 0
    keep_images: bool = False

    @property
    def key(self) -> str:
        k = getattr(self, "_key", None)
        if k is None:
            desc = {"experiment": self.experiment, "scene": self.scene, "cfg": asdict(self.cfg), "seed": self.seed,
                    "keep_images": self.keep_images,
                    "cases": [[c.spec, c.extra, c.rig.fingerprint()] for c in self.cases]}
            h = hashlib.sha1(json.dumps(desc, sort_keys=True, default=repr).encode()).hexdigest()[:12]
            safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in Path(self.scene).stem)
            k = self._key = f"{safe}-{h}"
        return k

    def describe(self) -> str:
        n = sorted({len(c.rig) for c in self.cases})
        rigs = sorted({str(c.extra.get("rig", "")) for c in self.cases} - {""})
        specs = list(dict.fromkeys(c.spec for c in self.cases))
        return (f"{Path(self.scene).stem} {'/'.join(rigs) + ' ' if rigs else ''}"
                f"{','.join(map(str, n))}v [{' '.join(specs)}]")


def scene_source(scene) -> str:
    """What loads ``scene`` again (set by :func:`slc.run.experiment.each_scene`)."""
    return getattr(scene, "source", None) or scene.name


def jobs_from_cases(experiment: str, cases, cfg, seed: int = 0, keep_images: bool = False,
                    start: int = 0) -> list[Job]:
    """(scene, spec, viewers, extra) cases -> jobs, one per (scene, viewers):
    every method of one comparison runs in the same job, in the given order.
    Cases are numbered from ``start`` (:attr:`Case.index`)."""
    groups: dict[tuple, list] = {}
    rigs: dict[tuple, Rig] = {}
    for i, (s, spec, viewers, extra) in enumerate(cases):
        rig = Rig.from_viewers(viewers, cfg)
        g = (scene_source(s), rig.fingerprint())
        rigs.setdefault(g, rig)
        groups.setdefault(g, []).append(Case(spec, rigs[g], dict(extra), start + i))
    return [Job(experiment, src, tuple(cs), cfg, seed, keep_images) for (src, _), cs in groups.items()]
