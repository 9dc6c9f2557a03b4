r"""A function traced once and replayed (``dr.freeze``) under one recording
policy, shared by every frozen kernel of the project (the cone update and
shading, the cache's entry interactions, the adaptive cache's updates and
shadings, osc-gi's kernels, the path tracer).

Freezing pays only while its recordings are replayed. Each instance owns its
frozen function, so recordings are freed with the method and never shared
between scenes. What makes a call miss its recordings (``dr.set_log_level(
dr.LogLevel.Info)`` and ``warn_after=1`` print the difference to the previous
call):

- Dr.Jit traverses, with the call's inputs, every object of Mitsuba's registry
  in the domains the inputs reach (all shapes, emitters, BSDFs alive in the
  process, of any scene), and the key holds an equivalence class of sizes over
  all those arrays. Objects of a released scene must therefore be freed (the
  per-scene tables of :mod:`slc.emitter_sampling` and :mod:`slc.lights` are
  dropped with their :class:`slc.scenes.Scene`); and a call whose number of
  lanes equals the size of some registry array (a mesh's 486 vertex
  coordinates) has a key of its own: one more recording, replayed whenever
  that width comes back (sponza, 240 frames: 3 recordings of the cone update).
- When meshes move, the traversed state changes from frame to frame and the
  function is recorded again on the frame's first call.

So:

- in a static scene, a function recorded more than ``max_recordings`` times is
  dropped (traced on every call from then on);
- in an animated scene, the function keeps at most 2 recordings (LRU) and is
  dropped once 8 calls show that almost every call records (> 90%).

Literal outputs take the call's width. A replayed recording returns an output
that was a literal when recorded (e.g. the zero ``dn_du`` of a flat mesh's
``SurfaceInteraction3f``) with the width it had *at the recording*, not the
width of the call (Dr.Jit 1.5): 480 lanes while the other fields have 482.
Passed on to a second frozen function, such a stale width changes that
function's input key whenever the first one records anew (auto-opaque makes
the literal an array, whose size class then differs from call to call), so the
second one records again. :func:`fit_literals` gives every literal leaf of each
output the width of its evaluated leaves (values unchanged: a literal has one
value).
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
            n = int(self.kernel.n_recordings)
            if n == self.recordings:        # a replay (a recording returns the traced outputs)
                out = fit_literals(out)
            self.recordings = n
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


# ----------------------------------------------------------------------------- literal outputs

def _slots(x, out: list) -> None:
    """Append (container, key, leaf) for every 1-D Dr.Jit array of a (nested)
    array or Dr.Jit struct ``x``; ``key`` a field name or an index."""
    if dr.is_struct_v(x) and not dr.is_array_v(x):
        for k in type(x).DRJIT_STRUCT:
            v = getattr(x, k)
            if dr.is_jit_v(v) and dr.depth_v(v) == 1:
                out.append((x, k, v))
            else:
                _slots(v, out)
    elif dr.is_array_v(x) and dr.depth_v(x) > 1:
        for i in range(len(x)):
            v = x[i]
            if dr.depth_v(v) == 1:
                out.append((x, i, v))
            else:
                _slots(v, out)


def _fit_one(out):
    if dr.is_array_v(out):
        if not dr.is_jit_v(out) or dr.depth_v(out) == 1:
            return out                              # a 1-D array: nothing to compare with
    elif not dr.is_struct_v(out):
        return out
    slots = []
    _slots(out, slots)
    lit = dr.VarState.Literal
    widths = {dr.width(v) for _, _, v in slots if v.state != lit}
    if len(widths) != 1:
        return out
    (w,) = widths
    for c, k, v in slots:
        if v.state == lit and dr.width(v) not in (0, 1, w):
            val = v[0]
            if val is None:                         # a null pointer array (e.g. ``si.instance``)
                new = dr.zeros(type(v), w)
            else:
                try:
                    new = dr.full(type(v), val, w)
                except TypeError:                   # a non-null literal pointer: left as it is
                    continue
            if isinstance(k, str):
                setattr(c, k, new)
            else:
                c[k] = new
    return out


def fit_literals(out):
    """``out`` (a frozen function's output: an array, a Dr.Jit struct, or a
    tuple / list / dict of them, each handled on its own) whose literal leaves
    have the width of the evaluated leaves of the same element, where those all
    have one width; anything else is returned as it is (modified in place)."""
    if isinstance(out, tuple):
        return tuple(fit_literals(o) for o in out)
    if isinstance(out, list):
        return [fit_literals(o) for o in out]
    if isinstance(out, dict):
        return {k: fit_literals(v) for k, v in out.items()}
    return _fit_one(out)
