"""The contract of the adaptive cache's representations (docs/adaptive.md).

A representation is one way to hold an entry's incoming light: VISIBILITY
(:mod:`slc.methods.adaptive.visibility`), CONES (:mod:`slc.methods.adaptive.cones_rep`), SH
(:mod:`slc.methods.adaptive.sh_rep`). Each keeps its records in a pool of its own
(:class:`~slc.methods.adaptive.pool.Pool`) and writes what differs:

- :meth:`Representation.words`: its record's size;
- :meth:`Representation.update`: one update cycle of its entries (:class:`Entries`), returning the
  new records, the entries' motion and the choice rule's statistics (:class:`Updated`);
- :meth:`Representation.shade`: the outgoing light at the pixels whose entry it holds
  (:class:`Pixels`);
- the switch into and out of it: :meth:`Representation.lobes` (its records as lobes: local
  direction, half-angle, integrated radiance, mask), :meth:`Representation.irradiance` (its
  records' irradiance at the entry's normal) and :meth:`Representation.convert` (a record holding
  the light of another representation's records).

:class:`~slc.methods.adaptive.method.AdaptiveCache` runs the frame: it hands every representation
its entries, gathers the statistics, chooses, and converts the entries that switch. A new
representation is a module with a subclass and a tag (:mod:`slc.methods.adaptive.choice`).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.methods.adaptive.pool import Pool
from slc.methods.adaptive.sampling import SampleStats


@dataclass
class Entries:
    """One representation's entries in a frame's update, one lane per entry (sorted by rays,
    most first): ``rec`` their records' words, ``si`` their own surface points, ``key`` their
    keys, ``rays`` the ray policy's rays, ``moving`` / ``unsettled`` / ``first_sample`` the
    policy's state (motion detected, not yet settled, the stratified sequence's next sample),
    ``fresh`` a new record (its words are stale), ``s_delta`` the statistics' listed share,
    ``texel`` the world-space edge of their texels (None: not given), ``on`` the live lanes,
    ``frame`` the frame number."""
    rec: list
    si: mi.SurfaceInteraction3f
    key: mi.UInt32
    rays: mi.UInt32
    moving: mi.Bool
    unsettled: mi.Bool
    first_sample: mi.UInt32
    fresh: mi.Bool
    s_delta: mi.Float
    texel: mi.Float | None
    on: mi.Bool
    frame: int


@dataclass
class Updated:
    """What an update returns: the new ``words``, the entries' ``motion`` (None: no motion
    seen), the choice rule's statistics ``stats`` and ``rays``, the rays each entry traced
    (None: the policy's)."""
    words: list
    motion: mi.Bool | None
    stats: SampleStats
    rays: mi.UInt32 | None = None


@dataclass
class Pixels:
    """The pixels whose entry a representation holds, of one viewer or of every viewer one
    after another: ``slot`` each pixel's record in the pool, ``active`` those pixels, ``si``
    their interactions (the G-buffer's), ``tf`` the local frame of each pixel's entry, ``frame``,
    ``viewer`` (the viewer's index, for random streams: an int, or per pixel a ``mi.UInt32`` of
    ``n_viewers`` viewers) and ``pid`` (each pixel's index within its own viewer, which keys its
    random numbers; None: its index in the arrays, one viewer)."""
    slot: mi.UInt32
    active: mi.Bool
    si: mi.SurfaceInteraction3f
    tf: mi.Frame3f
    frame: int
    viewer: int | mi.UInt32
    pid: mi.UInt32 | None = None
    n_viewers: int = 1


def lobe_irradiance(lobes: list, side: float = 1.0) -> mi.Color3f:
    """Irradiance at the entry's normal (local z; ``side`` -1: the reversed normal) of lobes
    (local direction d, half-angle a, integrated radiance L, mask): sum L (n.d)(1 + cos a)/2."""
    E = mi.Color3f(0.0)
    for d, a, Lr, m in lobes:
        E += dr.select(m, Lr * (dr.maximum(d.z * side if side != 1.0 else d.z, 0.0) * 0.5 * (1.0 + dr.cos(a))), 0.0)
    return E


class Representation(ABC):
    """One representation of the adaptive cache (see the module). ``cache`` is the
    :class:`~slc.methods.adaptive.method.AdaptiveCache` (its settings, scene and light tables);
    ``pool`` holds the records. Subclasses set ``tag`` and ``name`` and write the methods below.
    Their frozen functions are made on first use by :meth:`frozen`."""

    tag: int = 0
    name: str = ""

    def __init__(self, cache):
        self.cache = cache
        self.pool = Pool(self.name, self.words())

    @abstractmethod
    def words(self) -> int:
        """Words (32-bit) of a record."""

    @abstractmethod
    def update(self, e: Entries) -> Updated:
        """One update cycle of the entries ``e``."""

    @abstractmethod
    def shade(self, px: Pixels) -> mi.Color3f:
        """Outgoing direct light at the pixels ``px`` (0 elsewhere)."""

    @abstractmethod
    def lobes(self, rec: list, si: mi.SurfaceInteraction3f, active: mi.Bool) -> list:
        """The records ``rec`` (entries ``si``) as lobes: (local direction, half-angle,
        integrated radiance, mask) each."""

    @abstractmethod
    def convert(self, src: "Representation", rec: list, lobes: list, n: int) -> list:
        """Records (``n`` lanes) holding the light of ``src``'s records ``rec`` (as ``lobes``)."""

    def irradiance(self, rec: list, lobes: list, side: float) -> mi.Color3f:
        """The records' irradiance at the entry's normal (``side`` -1: at the reversed normal),
        from their ``lobes``; a representation with a closed form overrides it."""
        return lobe_irradiance(lobes, side)

    def frozen(self, attr: str, make):
        """The frozen function kept in ``attr``, made on first use by ``make(freeze)`` (frozen
        unless the cache's ``freeze`` setting is off)."""
        f = getattr(self, attr, None)
        if f is None:
            f = make(bool(getattr(self.cache, "freeze", True)))
            setattr(self, attr, f)
        return f
