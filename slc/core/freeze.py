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
  per-scene tables of :mod:`slc.scene.emitter_sampling` and :mod:`slc.scene.lights` are
  dropped with their :class:`slc.scene.scenes.Scene`); and a call whose number of
  lanes equals the size of some registry array (a mesh's 486 vertex
  coordinates) has a key of its own: one more recording, replayed whenever
  that width comes back (sponza, 240 frames: 3 recordings of the cone update),
  unless the function declares its lanes (below) and the array belongs to the
  call's own scene.
- When meshes move, the traversed state changes from frame to frame: the moved
  meshes' buffers are new arrays, their area distributions recomputed, the
  acceleration structure rebuilt. None of this changes the key as long as the
  new arrays are made as the old ones were (see "Host data that changes between
  calls" below): the street and the hangar record each function once and
  replay it in every later frame, bit for bit the traced function's images.

So a function recorded more than ``max_recordings`` times is dropped (traced on
every call from then on), in a static scene as in an animated one; the
recordings made in each frame are counted (:func:`recordings`, the rows'
``recordings_after_warmup``).

Widths that coincide. Dr.Jit keys a recording on which of its inputs share a
width (their "size equivalence class"), and the inputs include every array of
the scene (vertex buffers, index buffers, textures). A per-frame lane count
(the active entries) that happens to equal one of them (the atrium: 2,880 =
one mesh's index buffer) makes a new key, so the function is recorded again in
a timed frame, and after ``max_recordings`` such frames it is dropped. A
function made with ``lanes`` (the positions of its per-lane arguments) runs
such a call on a width that is free (:meth:`FrozenFunction.free_width`): its
per-lane arguments get copies of their last lane appended, and its outputs of
that width are cut back to the call's. Only for functions whose extra lanes
change nothing: pure functions and plain scatters of equal values (a copy of
the last lane computes and writes what the last lane does).

Tables whose length changes from call to call collide in the same way: the
cones' shading gathers each pixel's entry frame from the frame's entries, 4,224
of them in frame 31 of the street at 160x90, the width of one of the street's
vertex buffers, and the shading was recorded again in a timed frame. A function
made with ``tables`` (the arguments it reads only through indices) gets such an
argument padded to the next free width (copies of its last element appended,
never read), with the widths of ``scene`` (the scene its inputs reach through
the registry) counted as taken.

Host data that changes between calls. An array made from a numpy array
(``mi.Float(a)``) maps the numpy memory (no copy), and that breaks a recording
twice over. Dr.Jit keys a recording on whether each input is aligned to the
SIMD width: a mesh's vertex buffer rebuilt from numpy in every frame lands on
16- or 32-byte boundaries by chance, and each new combination records the
function again (street: a recording in every frame, even of ``lambda scene, x:
x * 2``). And a recording takes a pointer that a virtual call reads (a moving
mesh's vertex buffer in ``compute_surface_interaction``) as a literal unless
Dr.Jit allocated the memory: the replay reads the first frame's buffer, freed
since. Per-frame host data goes through :func:`device_array` (a copy in memory
Dr.Jit allocates). The acceleration structure is no such input: Mitsuba
rebuilds it in place, its handle an input of the recording, so a replay traces
rays against the moved geometry.

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
import inspect

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core import leaves


_RECORDINGS = [0]      # recordings made by every FrozenFunction of the process


def recordings() -> int:
    """The recordings made so far by every :class:`FrozenFunction` of the process (a
    function traced again because its inputs missed its recordings): the difference over a
    frame is the frame's recordings."""
    return _RECORDINGS[0]


class FrozenFunction:
    """``fn`` frozen under the module's policy.

    Parameters (defaults): ``fn``, ``freeze=True`` (False: ``fn`` traced on
    every call), ``max_recordings=4``, ``lanes=()`` (the per-lane arguments, by the names of
    ``fn``'s parameters, or their positions: a call whose lane count collides with another input's
    width runs on a free width, see the module; an argument named here may be a
    structure, a Dr.Jit struct or a dataclass, whose every array is per lane), ``narrow=()``
    (the arguments, by name or position, whose width decides whether a call is replayed: a call
    where one of them has fewer than 2 lanes runs ``fn`` traced, since a width-1 input is loaded
    as a scalar and would need a recording of its own), ``tables=()`` (the arguments, by name or
    position, read only through indices: padded to a free width where theirs collides, see the module),
    ``scene=None`` (with ``tables``: the ``mi.Scene`` whose array widths count as taken; its widths
    are read once, no reference is kept). ``calls`` counts the calls made while frozen,
    ``n_recordings`` the recordings made (including those of a dropped
    function), ``frozen`` whether calls are still replayed."""

    def __init__(self, fn, freeze: bool = True, max_recordings: int = 4, lanes: tuple = (), narrow: tuple = (),
                 tables: tuple = (), scene=None):
        self.fn = fn
        self.lanes, self.narrow, self.tables = _positions(fn, lanes), _positions(fn, narrow), _positions(fn, tables)
        self._table_taken = leaves.scene_widths(scene) if (tables and scene is not None) else set()
        self.padded_calls = 0           # calls run on a free width
        self._scene_key, self._scene_ws = None, set()
        self.max_recordings = int(max_recordings)
        self.frozen = bool(freeze)
        if not self.frozen:
            self.kernel = fn
        else:
            self.kernel = dr.freeze(fn, warn_after=self.max_recordings + 1)
        self.recordings = 0
        self.calls = 0

    def __call__(self, *args):
        if self.narrow and any(leaves.width(args[i]) < 2 for i in self.narrow):
            return self.fn(*args)          # too narrow to replay (see the class)
        # no garbage collection while a function records or replays: the collector freed
        # cyclic garbage holding Dr.Jit state (an earlier test's objects) in the middle of
        # a recording, and Dr.Jit aborted the process
        n = w = None
        if self.frozen and self.lanes:
            # the inputs evaluated here, together, as the frozen function would: the
            # per-leaf copies below then read evaluated arrays on every call
            dr.eval(*[a for a in args if leaves.is_tree(a)])
            n = leaves.width(args[self.lanes[0]])
            args = self._distinct(args, n)
            w = self.free_width(n, args)
            if self.calls == 0 or w != n:
                # the first call also pads (by one lane, result unused), so that the
                # copy kernels exist before a collision needs them in a timed frame
                padded = self._pad(args, n, w if w != n else n + 1)
                if w != n:
                    args = padded
                    self.padded_calls += 1
                del padded
        if self.frozen and self.tables:
            args = self._free_tables(args)
        gc_on = gc.isenabled()
        gc.disable()
        try:
            out = self.kernel(*args)
        finally:
            if gc_on:
                gc.enable()
        if n is not None and w != n:
            out = leaves.cut(out, w, n)
        elif n is not None and self.calls == 0:
            leaves.cut(out, n, n)             # the cut's kernels made now (see above), result unused
        if self.frozen:
            self.calls += 1
            recs = int(self.kernel.n_recordings)
            if recs == self.recordings:     # a replay (a recording returns the traced outputs)
                out = fit_literals(out)
            _RECORDINGS[0] += max(recs - self.recordings, 0)
            self.recordings = recs
            if self.recordings > self.max_recordings:
                self.kernel.clear()
                self.kernel, self.frozen = self.fn, False
        return out

    def restart(self) -> None:
        """Drop the recordings of a frozen function: the next call records anew. For a
        host-side input whose change must reach the kernels for certain (a Python value
        that selects code), rather than through the recording's key alone."""
        if self.frozen:
            self.kernel = dr.freeze(self.fn, warn_after=self.max_recordings + 1)
            self.recordings = 0

    def free_width(self, n: int, args) -> int:
        """``n`` if no other input of the call (the arguments not in ``lanes``,
        the arrays of a Mitsuba scene among them) has width ``n``, else the
        next width that is free. Widths 0 and 1 are never free (a width-1 array
        is loaded as a scalar). A width this misses (an array of the scene that
        is no parameter) records once: Dr.Jit keeps that recording for the
        next call of the same width."""
        if n == 0:
            return n
        return _next_free(n, self._taken(args, self.lanes))

    def _taken(self, args, skip) -> set:
        """Widths 0 and 1 and the widths of every argument not in ``skip`` (a Mitsuba scene's
        read once per scene instance), with those of the ``scene`` given at construction."""
        taken = {0, 1} | self._table_taken
        for i, a in enumerate(args):
            if i in skip:
                continue
            if leaves.is_scene(a):
                # a scene's widths once per instance (a Mitsuba scene is not weakly
                # referenceable, and a strong reference would keep a freed scene in
                # the registry that every frozen function traverses)
                if self._scene_key != id(a):
                    self._scene_key, self._scene_ws = id(a), leaves.input_widths(a)
                taken |= self._scene_ws
            else:
                taken |= leaves.input_widths(a)
        return taken

    def _free_tables(self, args):
        """``args`` with each argument of ``tables`` padded to the next free width where its
        width is one of the other inputs' or the scene's (copies of its last element: indices
        never reach them). The first call pads each table by one element, result unused, so
        that the copy kernels exist before a collision needs them in a timed frame."""
        taken = self._taken(args, self.tables)
        out = list(args)
        for i in self.tables:
            n = leaves.width(args[i])
            if n < 2:
                continue
            if self.calls == 0:
                leaves.pad_leaves(args[i], n, n + 1)
            w = _next_free(n, taken)
            if w != n:
                out[i] = leaves.pad_leaves(args[i], n, w)
                self.padded_calls += 1
            taken.add(w)
        return tuple(out)

    def _distinct(self, args, n: int):
        """``args`` with every per-lane leaf an evaluated variable of its own: a literal
        leaf is evaluated, a leaf that refers to the same variable as an earlier one is
        replaced by a copy. Dr.Jit keys a recording on which inputs are literals and which
        share a variable, and both vary from call to call (a literal field of the entries'
        interactions whose width changes is made opaque by the frozen function, so the next
        call has another key: a recording in a timed frame)."""
        seen = set()
        lit = dr.VarState.Literal

        def own(x):
            if x.index == 0:
                return x
            if x.state == lit:
                x = type(x)(x)
                dr.make_opaque(x)
            elif x.index in seen:
                x = leaves.gather_leaf(x, leaves.lane_index(dr.width(x), dr.width(x)), dr.width(x))
            seen.add(x.index)
            return x
        return tuple(leaves.map_leaves(a, own) if i in self.lanes else a for i, a in enumerate(args))

    def _pad(self, args, n: int, w: int):
        """``args`` with the per-lane ones widened from ``n`` to ``w`` lanes
        (copies of lane ``n - 1``; the index opaque: one kernel for all widths)."""
        return tuple(leaves.pad_leaves(a, n, w) if i in self.lanes else a for i, a in enumerate(args))

    @property
    def n_recordings(self) -> int:
        """Recordings made by this instance's frozen function (0 when never frozen)."""
        return self.recordings

    @property
    def n_cached_recordings(self) -> int:
        """Recordings the frozen function holds now (0 once dropped)."""
        return int(self.kernel.n_cached_recordings) if self.frozen else 0


def _next_free(n: int, taken: set) -> int:
    """The first width from ``n`` up that is not in ``taken``."""
    while n in taken:
        n += 1
    return n


def _positions(fn, lanes) -> tuple:
    """The positions of ``fn``'s parameters named in ``lanes`` (an int: a position)."""
    names = list(inspect.signature(fn).parameters)
    unknown = [n for n in lanes if not isinstance(n, int) and n not in names]
    if unknown:
        raise ValueError(f"{getattr(fn, '__name__', fn)} has no parameter {', '.join(unknown)}")
    return tuple(n if isinstance(n, int) else names.index(n) for n in lanes)


def device_array(tp, a):
    """``a`` (a numpy array or anything ``tp`` takes) as a Dr.Jit array of type ``tp`` (a
    1-D type: ``mi.Float``, ``mi.UInt32``...) in memory that Dr.Jit allocated, evaluated: made
    from numpy, ``tp(a)`` would map the numpy memory (see the module: host data that changes
    between calls). One copy kernel per type; it has run when this returns (kernels run
    asynchronously: the caller may change or free ``a`` right after)."""
    v = tp(np.ascontiguousarray(a)) if isinstance(a, np.ndarray) else tp(a)
    out = dr.gather(tp, v, dr.arange(mi.UInt32, dr.width(v)) + dr.opaque(mi.UInt32, 0))
    dr.eval(out)
    dr.sync_thread()
    return out


# ----------------------------------------------------------------------------- literal outputs

def _fit_one(out):
    """``out`` with its literal leaves of a stale width (neither 0, 1 nor the one
    width of its evaluated leaves) rebuilt at that width; ``out`` itself when
    there is none (the usual case: nothing rebuilt)."""
    lit = dr.VarState.Literal
    lv = list(leaves.leaves(out))
    widths = {dr.width(v) for v in lv if v.state != lit}
    if len(widths) != 1:
        return out
    (w,) = widths

    def stale(v):
        return v.state == lit and dr.width(v) not in (0, 1, w)

    def refit(v):
        if not stale(v):
            return v
        val = v[0]
        if val is None:                             # a null pointer array (e.g. ``si.instance``)
            return dr.zeros(type(v), w)
        try:
            return dr.full(type(v), val, w)
        except TypeError:                           # a non-null literal pointer: left as it is
            return v
    return leaves.map_leaves(out, refit) if any(stale(v) for v in lv) else out


def fit_literals(out):
    """``out`` (a frozen function's output: an array, a Dr.Jit struct, or a
    tuple / list / dict of them, each handled on its own) whose literal leaves
    have the width of the evaluated leaves of the same element, where those all
    have one width; anything else is returned as it is."""
    if isinstance(out, tuple):
        return tuple(fit_literals(o) for o in out)
    if isinstance(out, list):
        return [fit_literals(o) for o in out]
    if isinstance(out, dict):
        return {k: fit_literals(v) for k, v in out.items()}
    return _fit_one(out)
