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
            out = fit_literals(out)
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


# ----------------------------------------------------------------------------- literal outputs

def _leaves(x):
    """The 1-D Dr.Jit arrays of a (nested) array or Dr.Jit struct."""
    if dr.is_struct_v(x) and not dr.is_array_v(x):
        for k in type(x).DRJIT_STRUCT:
            yield from _leaves(getattr(x, k))
    elif dr.is_array_v(x) and dr.depth_v(x) > 1:
        for i in range(len(x)):
            yield from _leaves(x[i])
    elif dr.is_jit_v(x):
        yield x


def _refit(x, width: int):
    """``x`` with every literal leaf whose width is neither 0, 1 nor ``width``
    replaced by the same literal value at ``width`` lanes (in place for structs
    and nested arrays)."""
    if dr.is_struct_v(x) and not dr.is_array_v(x):
        for k in type(x).DRJIT_STRUCT:
            setattr(x, k, _refit(getattr(x, k), width))
        return x
    if dr.is_array_v(x) and dr.depth_v(x) > 1:
        for i in range(len(x)):
            x[i] = _refit(x[i], width)
        return x
    if dr.is_jit_v(x) and x.state == dr.VarState.Literal and dr.width(x) not in (0, 1, width):
        v = x[0]
        if v is None:                       # a null pointer array (e.g. ``si.instance``)
            return dr.zeros(type(x), width)
        try:
            return dr.full(type(x), v, width)
        except TypeError:                   # a non-null literal pointer: left as it is
            return x
    return x


def fit_literals(out):
    """``out`` (a frozen function's output: an array, a Dr.Jit struct, or a
    tuple / list / dict of them, each handled on its own) whose literal leaves
    have the width of the evaluated leaves of the same element, where those all
    have one width (> 1); anything else is returned as it is."""
    if isinstance(out, tuple):
        return tuple(fit_literals(o) for o in out)
    if isinstance(out, list):
        return [fit_literals(o) for o in out]
    if isinstance(out, dict):
        return {k: fit_literals(v) for k, v in out.items()}
    if not (dr.is_array_v(out) or dr.is_struct_v(out)):
        return out
    leaves = list(_leaves(out))
    widths = {dr.width(v) for v in leaves if v.state != dr.VarState.Literal}
    stale = any(v.state == dr.VarState.Literal and dr.width(v) > 1 for v in leaves)
    if len(widths) != 1 or not stale:
        return out
    (w,) = widths
    return _refit(out, w) if w > 1 else out
