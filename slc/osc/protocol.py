"""The contract between a surface cache and the payload that lives in it.

A *surface cache* decides which surface points have entries and where they
live; a *payload* (cones, SH, ...; see :class:`slc.methods.cache_method.PayloadMethod`)
decides what an entry stores, how it is updated and how pixels are shaded
from it. Once per frame the cache turns all viewers' G-buffers into
:class:`FrameRequests`; the payload updates every active entry once, from
the entry's own surface point, and shades every viewer's pixels from the
entries they map to.

What the cache gives a payload (:class:`FrameRequests`):

- ``active``: the unique entry slots requested by any viewer this frame,
  sorted ascending; ``si``: each one's own surface point; ``is_new``: the
  slot was (re)allocated since its last frame, so its payload is stale and
  must be reset (or seeded); ``seed_slot``: an existing, already updated
  entry of a coarser level covering a new entry (LOD seed), else INVALID;
  ``keys``: a viewer-independent 32-bit key per entry (random numbers keyed
  by it do not depend on who asked); ``texel_size``: the world-space edge of each
  entry's texel, the patch of surface it stands for (None when the cache does not
  provide it).
- per viewer: ``pixel_slot`` (entry slot of each pixel, INVALID where the
  G-buffer is invalid or nothing is cached) and ``pixel_index`` (the pixel's
  index into ``active``/``si``, INVALID likewise); optionally the same for all
  viewers' pixels in the order of the frame's layered G-buffer
  (:class:`slc.scene.gbuffer.Layers`): ``layer_slot``, ``layer_index`` (None when
  the cache does not provide them).

What the cache promises: slots index payload arrays of ``capacity`` entries
(``capacity`` may grow between frames; payloads grow their arrays to it and
keep the old contents); a slot that is not active keeps its payload until
its block is evicted; an evicted and reused slot comes back with
``is_new``. The payload must update every active entry in the frame that
requested it (the cache counts an active entry as "seen" from then on: it
may be a seed or a filter tap afterwards).

What each reports: the cache its own structures' memory
(:meth:`SurfaceCache.memory_bytes`: block table, surface points, flags) and
the number of allocated entry slots (:meth:`SurfaceCache.entries_allocated`);
the payload its storage per entry, so that a method's memory is
``cache.memory_bytes() + entries_allocated() x payload bytes per entry``.

Optional capabilities are declared in ``capabilities``, never probed:
``"bilinear_taps"`` (:meth:`bilinear_taps`: the 4 entries around a pixel's
cache coordinate with bilinear weights) and ``"entry_texels"``
(``entry_info(slots)``: island, level, texel of entries, for tests and
notebooks) and ``"entry_topology"`` (:class:`EntryTopology`: where entries
sit on the surface, for payloads that read an entry's neighbours or its finer
entries, as osc-gi's spatial filter and finer-level seeding do). A payload
that needs a capability the cache lacks refuses at set-up with a one-line
error. The reset / LOD-seeding rule of a new entry is :func:`entry_start`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID

BILINEAR_TAPS = "bilinear_taps"
ENTRY_TEXELS = "entry_texels"
ENTRY_TOPOLOGY = "entry_topology"


@dataclass
class FrameRequests:
    """What :meth:`SurfaceCache.begin_frame` gives the payload (see the module)."""
    frame: int
    active: mi.UInt32
    si: mi.SurfaceInteraction3f
    is_new: mi.Bool
    seed_slot: mi.UInt32
    keys: mi.UInt32
    pixel_slot: list = field(default_factory=list)
    pixel_index: list = field(default_factory=list)
    layer_slot: mi.UInt32 | None = None      # pixel_slot of all viewers laid out as the frame's layers
    layer_index: mi.UInt32 | None = None     # pixel_index likewise (slc.scene.gbuffer.Layers order)
    texel_size: mi.Float | None = None       # per active entry: the world-space edge of its texel (its footprint)
    extra_slot: mi.UInt32 | None = None      # slots of the entries requested besides the pixels (begin_frame's extra)

    @property
    def n_active(self) -> int:
        return dr.width(self.active)

    @classmethod
    def empty(cls, frame: int, gbuffers) -> "FrameRequests":
        """No entry requested: every pixel INVALID."""
        inv = [dr.full(mi.UInt32, INVALID, gb.size) for gb in gbuffers]
        return cls(frame=frame, active=mi.UInt32(), si=dr.zeros(mi.SurfaceInteraction3f, 0),
                   is_new=mi.Bool(), seed_slot=mi.UInt32(), keys=mi.UInt32(),
                   pixel_slot=inv, pixel_index=[mi.UInt32(x) for x in inv])


@runtime_checkable
class SurfaceCache(Protocol):
    """A cache of surface points shared by all viewers (see the module)."""

    capabilities: frozenset

    @property
    def capacity(self) -> int: ...

    def begin_frame(self, frame: int, gbuffers, timer=None) -> FrameRequests: ...

    def entries_allocated(self) -> int: ...

    def memory_bytes(self) -> int: ...

    def stats(self) -> dict: ...

    def reset(self) -> None: ...


@runtime_checkable
class EntryTopology(Protocol):
    """The ``"entry_topology"`` capability: what a payload may ask of where its entries sit.

    Entries are texels ``(tx, ty)`` of a level of an island (a chart of the surface; level
    l + 1 has half the texels per side of level l, so the 2 x 2 texels (2 tx + {0, 1}, 2 ty +
    {0, 1}) of level l - 1 cover texel (tx, ty) of level l). All arguments and results are
    Dr.Jit arrays, one lane per entry."""

    def entry_texels(self, slots: mi.UInt32) -> tuple:
        """(island, level, tx, ty) of the entries ``slots`` (``mi.UInt32`` each)."""

    def entry_keys(self, slots: mi.UInt32) -> mi.UInt32:
        """The entries' viewer-independent 32-bit keys (those of ``FrameRequests.keys``)."""

    def slot_at(self, island: mi.UInt32, level: mi.UInt32, tx: mi.Int32, ty: mi.Int32,
                active: mi.Bool = True) -> mi.UInt32:
        """The slot of texel (tx, ty) of ``island``'s ``level``; INVALID where inactive, outside
        the level's texels, not allocated, or not requested in an earlier frame yet."""

    def entry_points(self, slots: mi.UInt32, island: mi.UInt32) -> mi.SurfaceInteraction3f:
        """The entries' own surface points (``island``: theirs, from :meth:`entry_texels`)."""


@dataclass(frozen=True)
class EntryStart:
    """Where each active entry's previous value comes from (:func:`entry_start`)."""
    seeded: mi.Bool      # new, and a coarser entry covers it: start from that entry
    keep: mi.Bool        # the previous value counts (the entry is not new, or it is seeded)
    src: mi.UInt32       # the slot holding the previous value: the seed where seeded, else ``slots``


def entry_start(is_new, seed_slot, slots) -> EntryStart:
    """The reset / LOD-seeding rule of every payload: an entry that is not new continues
    from its own value; a new entry starts from its coarser seed (``seed_slot``, see
    :class:`slc.osc.protocol.FrameRequests`) when it has one, else from nothing."""
    seeded = mi.Bool(is_new) & (mi.UInt32(seed_slot) != INVALID)
    return EntryStart(seeded, ~mi.Bool(is_new) | seeded, dr.select(seeded, mi.UInt32(seed_slot), slots))
