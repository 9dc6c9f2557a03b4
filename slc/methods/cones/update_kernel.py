"""The cone update kernel on the packed storage: the active entries gathered in ray order, one
update cycle each (:func:`slc.lib.cones.cycle.update_cycle`), their words written back
(:func:`update_entries`, the ``slc`` method's update); :class:`ConeUpdate` traces that kernel
once and replays it (``dr.freeze``), one instance per method instance (:func:`updater_for`)."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core.freeze import FrozenFunction
from slc.lib.cones.cycle import CycleEntries, constant_area_emitters, update_cycle
from slc.lib.cones.packing import gather_words, scatter_words, unpack
from slc.lib.cones.update import ConeParams, frame_u32
from slc.osc.protocol import entry_start
from slc.scene.lights import light_inputs, sampler


@dataclass
class UpdateBatch:
    """The per-lane inputs of :func:`_update_kernel`: the entries' ``slot`` in the
    storage, the ``seed_slot`` of their LOD seed (``INVALID``: none) and their
    :class:`CycleEntries`."""
    slot: mi.UInt32
    seed_slot: mi.UInt32
    entries: CycleEntries


def update_entries(scene: mi.Scene, storage: mi.UInt32, active: mi.UInt32, si: mi.SurfaceInteraction3f,
                   rays: mi.UInt32, unsettled: mi.Bool, is_new: mi.Bool, seed_slot: mi.UInt32, keys: mi.UInt32,
                   frame: int, seed: int, p: ConeParams, stats: dict | None = None,
                   moving: mi.Bool | None = None, first_sample: mi.UInt32 | None = None,
                   strata: mi.Bool | None = None, updater: "ConeUpdate | None" = None):
    """One update cycle of every active entry (one lane per entry, samples processed
    sequentially in a loop so no update is lost). Reads and writes the packed
    ``storage`` (``capacity * words_per_entry`` UInt32). ``rays`` and ``unsettled``
    come from the ray policy; ``keys`` seed each entry's random numbers and
    shrink-test schedule (the OSC's viewer-independent texel keys make an entry's
    history independent of which other viewers exist). ``moving`` (default:
    none) marks the entries whose C is capped (see
    :func:`slc.lib.cones.update.end_cycle`); ``first_sample`` (default 0) is the index of the cycle's
    first sample in the entry's stratified sequence where ``strata`` (default:
    not ``moving``) holds; elsewhere the cycle's samples continue a second
    per-entry sequence at ``frame x rays``. ``updater`` (a :class:`ConeUpdate`,
    default: none) runs the kernel traced once and replayed; without it the
    kernel is traced on every call. Returns (storage, motion mask per active entry)."""
    if dr.width(active) == 0:
        return storage, mi.Bool()
    N = dr.width(active)
    moving = dr.zeros(mi.Bool, N) if moving is None else mi.Bool(moving)
    first_sample = dr.zeros(mi.UInt32, N) if first_sample is None else mi.UInt32(first_sample)
    strata = ~moving if strata is None else mi.Bool(strata)
    # Entries with 8 samples side by side, so that a SIMD packet's loop does not
    # run 8 iterations for 1-sample lanes (random numbers are keyed by slot, so
    # the order changes nothing in the results). Outside the frozen kernel:
    # dr.argsort bakes the array's length into its kernels.
    order = dr.argsort(mi.UInt32(rays), descending=True)
    kernel = updater if updater is not None else _update_kernel
    batch = UpdateBatch(mi.UInt32(active), mi.UInt32(seed_slot),
                        CycleEntries(mi.UInt32(keys), si, mi.UInt32(rays), mi.Bool(unsettled), moving,
                                     mi.Bool(is_new), first_sample, strata))
    words, act, motion_o, shrunk_o, dropped_o = kernel(
        scene, light_inputs(scene), storage, order, batch, frame_u32(frame), int(seed), p,
        updater.area_only(scene) if updater is not None else constant_area_emitters(scene))
    # The words are written here, not in the frozen kernel: a replay copies an input it scatters
    # into (the whole storage, 38 MB on the atrium, every frame); here ``storage`` has no other
    # reference and the scatter writes in place.
    scatter_words(storage, words, act, p.max_cones)
    motion = dr.zeros(mi.Bool, N)
    dr.scatter(motion, motion_o, order)
    if stats is not None:
        stats["shrunk"] = shrunk_o
        stats["dropped"] = dropped_o
    return storage, motion


def _update_kernel(scene, lights, storage, order, batch: UpdateBatch, frame, seed, p: ConeParams,
                   area_only: bool = False):
    """The update proper, in the lane order ``order``: gather the inputs,
    :func:`_updated_words` (reading ``storage``, not writing it). Every
    argument that changes from frame to frame is a Dr.Jit array (``frame``
    an opaque ``mi.UInt32``), and nothing here reads an array's width, so
    that :class:`ConeUpdate` can trace it once and replay it for any number
    of entries. ``lights`` (:func:`light_inputs`) is not read here: it declares
    the emitter table's arrays, which :func:`slc.scene.lights.sample_light` reads, as
    inputs of the frozen function. ``area_only`` (a Python bool, part of the recording's
    key) see :func:`slc.lib.cones.cycle.shrink_test`. Returns (words, slots, motion, shrunk,
    dropped), all in lane order: the new words of the entries at ``slots``."""
    act = dr.gather(mi.UInt32, batch.slot, order)
    e = batch.entries
    entries = CycleEntries(
        dr.gather(mi.UInt32, e.key, order), dr.gather(type(e.si), e.si, order), dr.gather(mi.UInt32, e.rays, order),
        dr.gather(mi.Bool, e.unsettled, order), dr.gather(mi.Bool, e.moving, order),
        dr.gather(mi.Bool, e.fresh, order), dr.gather(mi.UInt32, e.first_sample, order),
        dr.gather(mi.Bool, e.strata, order))
    words, motion_o, shrunk_o, dropped_o = _updated_words(
        scene, storage, act, entries, dr.gather(mi.UInt32, batch.seed_slot, order), frame, seed, p, area_only)
    dr.eval(act)
    return words, act, motion_o, shrunk_o, dropped_o


def _updated_words(scene, storage, active, entries: CycleEntries, seed_slot, frame, seed, p: ConeParams,
                   area_only: bool = False):
    """The update kernel proper on the packed ``storage``: unpack the active
    entries (a new entry with an LOD seed: the seed's record), :func:`update_cycle`, pack.
    Returns the evaluated (words, motion, shrunk, dropped)."""
    K = p.max_cones
    start = entry_start(entries.fresh, seed_slot, active)
    state = unpack(gather_words(storage, start.src, K), K)
    words, motion, shrunk, dropped, _ = update_cycle(scene, state, entries, frame, seed, p, seeded=start.seeded,
                                                     area_only=area_only)
    dr.eval(*words, motion, shrunk, dropped)
    return words, motion, shrunk, dropped


class ConeUpdate(FrozenFunction):
    r"""The cone update kernel (:func:`_update_kernel`) traced once and replayed
    (``dr.freeze``): tracing the update (the sample loop, cases A-D, the shrink
    test, packing) costs tens of milliseconds of Python per frame whatever the
    number of entries; a replay launches the recorded kernels on the frame's
    arrays. Images are those of the traced kernel bit for bit.

    Parameters (defaults): ``freeze=True`` (False: trace on every call),
    ``max_recordings=4``.

    A recording is reused while its inputs keep their layout: the frame number is
    an opaque ``mi.UInt32`` input and the number of active entries, the storage's
    size (it grows with the cache) may change between calls without a new recording;
    what forces one is a change of which inputs share a width (e.g. an input of
    width 1: one active entry, or as many entries as a mesh has vertex
    coordinates: such calls run on a free width, see :mod:`slc.core.freeze`), or a
    change of the scene's traversed state. As
    :class:`slc.lib.cones.shading.ConeShading`: a function recorded more than
    ``max_recordings`` times is dropped (traced from then on; :mod:`slc.core.freeze`)."""

    def __init__(self, freeze: bool = True, max_recordings: int = 4):
        # per-lane: the order and the batch (a lane count equal to a scene array's width runs
        # on a free width; the extra lanes repeat the last one: same words, same slot)
        super().__init__(_update_kernel, freeze, max_recordings, lanes=("order", "batch"))
        self._area_only = None      # ((id of the scene, table builds), constant_area_emitters)

    def area_only(self, scene) -> bool:
        """:func:`constant_area_emitters` of ``scene``, read again when its emitter table is
        read again (:meth:`slc.scene.emitter_table.EmitterTable.rebuild`, e.g. after a light's
        radiance changed: a light switched off makes it false, so that the shrink test sees
        the dark light); no reference to the scene kept. A change of the flag costs the
        frozen update one new recording."""
        ms = getattr(scene, "mi_scene", scene)
        table = sampler(ms)
        key = (id(ms), None if table is None else table.builds)
        if self._area_only is None or self._area_only[0] != key:
            flag = constant_area_emitters(scene)
            if self._area_only is not None and self._area_only[1] != flag:
                self.restart()       # the shrink test's code changes: record it anew
            self._area_only = (key, flag)
        return self._area_only[1]


def updater_for(owner) -> ConeUpdate:
    """The :class:`ConeUpdate` of ``owner`` (a method instance), made on first use."""
    up = getattr(owner, "_cone_update", None)
    if up is None:
        up = ConeUpdate(freeze=bool(getattr(owner, "freeze", True)))
        owner._cone_update = up
    return up
