r"""A function traced once and replayed (``dr.freeze``) under one recording
policy, shared by the cone update (:class:`slc.cones.update.ConeUpdate`), the
cone shading (:class:`slc.cones.shading.ConeShading`) and the adaptive cache's
SH shading (:class:`slc.adaptive.sh_rep.SHShading`).

Freezing pays only while its recordings are replayed. Each instance owns its
frozen function, so recordings are freed with the method and never shared
between scenes. A frozen function traverses every object of Mitsuba's registry
(shapes, BSDFs, emitters, the scene) on each call; when meshes move, that state
changes from frame to frame and the function is recorded again on the frame's
first call. So:

- in a static scene, a function recorded more than ``max_recordings`` times is
  dropped (traced on every call from then on);
- in an animated scene, the function keeps at most 2 recordings (LRU) and is
  dropped once 8 calls show that almost every call records (> 90%).
"""
from __future__ import annotations

import gc

import drjit as dr


class FrozenFunction:
    """``fn`` frozen under the module's policy.

    Parameters (defaults): ``fn``, ``freeze=True`` (False: ``fn`` traced on
    every call), ``animated=False`` (the scene's meshes move),
    ``max_recordings=4``. ``calls`` counts the calls made while frozen,
    ``n_recordings`` the recordings made (including those of a dropped
    function), ``frozen`` whether calls are still replayed."""

    def __init__(self, fn, freeze: bool = True, animated: bool = False, max_recordings: int = 4):
        self.fn = fn
        self.animated, self.max_recordings = bool(animated), int(max_recordings)
        self.frozen = bool(freeze)
        if not freeze:
            self.kernel = fn
        elif self.animated:
            self.kernel = dr.freeze(fn, limit=2, warn_after=1 << 30)
        else:
            self.kernel = dr.freeze(fn, warn_after=self.max_recordings + 1)
        self.recordings = 0
        self.calls = 0

    def __call__(self, *args):
        # no garbage collection while a function records or replays: the collector freed
        # cyclic garbage holding Dr.Jit state (an earlier test's objects) in the middle of
        # a recording, and Dr.Jit aborted the process
        gc_on = gc.isenabled()
        gc.disable()
        try:
            out = self.kernel(*args)
        finally:
            if gc_on:
                gc.enable()
        if self.frozen:
            self.calls += 1
            self.recordings = int(self.kernel.n_recordings)
            if self.animated:
                drop = self.calls >= 8 and self.recordings > 0.9 * self.calls
            else:
                drop = self.recordings > self.max_recordings
            if drop:
                self.kernel.clear()
                self.kernel, self.frozen = self.fn, False
        return out

    @property
    def n_recordings(self) -> int:
        """Recordings made by this instance's frozen function (0 when never frozen)."""
        return self.recordings

    @property
    def n_cached_recordings(self) -> int:
        """Recordings the frozen function holds now (0 once dropped)."""
        return int(self.kernel.n_cached_recordings) if self.frozen else 0
