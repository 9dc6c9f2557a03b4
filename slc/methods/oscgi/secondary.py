r"""Secondary radiance caches: a hashed world grid of coarse cells on the surfaces that the
primary caches' rays hit (the slides' "secondary caches ... span ~30 cm x 30 cm, quantized to
allow for more reuse").

A cell is keyed by the hit's position, normal bin and shape (:func:`slc.methods.oscgi.cells.cell_key`);
its home slot is a second hash word. The table is open addressing with linear probing over
``slots`` entries, filled without races in ``probes`` rounds of gather / ``scatter_reduce(min)`` /
gather (the smallest key wins a contested empty slot, the others probe on): the same requests
give the same table on every run. A request that finds no slot within ``probes`` gets no cell
and counts as overflow.

*Eviction*: a cell not touched (hit by any cache ray) in ``evict_after`` whole frames is freed at
the start of the next one (touched last in frame u: freed at the start of frame u + K + 1).
Freeing slots of a linear-probing table would cut the probe chains of the cells behind them, so
the table is rebuilt instead: the surviving keys are inserted into an empty table (deterministic,
as above) and their data move with them; a freed slot is reused from a reset state. With eviction on, the table is also brought down to
``max_load`` (1/4) of its slots at the start of a frame by freeing the least recently touched
cells, so that the frame's new cells find slots within ``probes`` rounds.

*Budget*: at most ``budget`` cells are updated per frame (0: all requested), ranked by ring (the
cells primary rays read this frame first), then least-sampled, then oldest update, then slot;
the others keep their value (their EMA is not advanced this frame) and their ring requests lapse.

Each cell stores the *outgoing diffuse* radiance of its surface, :math:`L_o = \rho E / \pi`, in
``bounces`` layers: layer 1 holds direct light only, layer b adds light that arrived after b-1
further bounces,

.. math:: L^{(1)} = \frac{\rho}{\pi} E_{dir}, \qquad
          L^{(b)} = \rho\Big(\frac{E_{dir}}{\pi} + \frac{1}{n}\sum_{j=1}^{n} L^{(b-1)}(c_j)\Big),

with :math:`E_{dir}` from ``light_samples`` samples of the project's light sampling
(:func:`slc.scene.lights.sample_light`, shadow rays) and n = ``rays`` cosine-distributed rays whose hits
fall in cells :math:`c_j` (their layer b-1 of the previous update; an emitter or the environment
hit by such a ray adds nothing, since next-event estimation already counts that light). A primary
cache reads layer ``bounces``, so that the primary point receives light after exactly
1..``bounces`` reflections, the paths of :func:`slc.reference.references.indirect_light`. Bounces accumulate
over frames: layer b of a cell is at most b-1 updates behind.

Glossy hits (``glossy_hits``): a cell holds diffuse radiance only (0 for a metal); a secondary ray
whose hit has a glossy or delta BSDF reads instead one light sample with that BSDF towards the
ray's origin (:func:`~slc.methods.oscgi.cells.glossy_kernel`), the hit's layer 1 exactly (a lower bound
for layers >= 2). A cell is updated from a representative point, the hit (lowest lane) that
touched it last. Update set: every cell hit by a primary ray this frame (ring 1) and every cell hit by a ring-r
cell's rays in the previous frame (ring r+1 <= ``bounces``); ring ``bounces`` needs direct light only
and traces no rays. Temporal filter: exponential moving average with blend factor
1 / min(n, ``n_max``), n the cell's update count.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.scene.lights import light_inputs
from slc.core.freeze import FrozenFunction
from slc.core.keys import INVALID, stream_key
from slc.methods.oscgi.cells import (EMPTY, NO_RING, REP_WORDS, STREAM_SECONDARY, CacheHits, CellHits, GlossyHits, cell_key,
                    direct_kernel, glossy_kernel, ray_kernel, rep_kernel, trace_kernel)
from slc.methods.oscgi.laps import Laps
from slc.methods.oscgi.table import CellTable


class SecondaryCache(CellTable):
    """Hashed grid of secondary radiance cells (see the module).

    Parameters: ``cell`` (edge in scene units), ``bounces`` (layers), ``n_max`` (EMA cap),
    ``rays`` (cosine rays per cell update, 32), ``light_samples`` (per cell update, 4),
    ``slots`` (table size, a power of two), ``probes`` (linear-probing rounds), ``shape_key``,
    ``budget`` (cell updates per frame, 0: unlimited), ``evict_after`` (frames unused, 0: never),
    ``max_load`` (with eviction on: cells kept at the start of a frame, as a fraction of ``slots``),
    ``glossy_hits`` (True: :class:`GlossyHits` at non-diffuse hits), ``freeze`` (True: the kernels
    with shape, BSDF and emitter calls, the ray tracing with the cell keys, the representative
    albedo, the direct light, the secondary rays and the glossy hits, are traced once and replayed
    by :class:`slc.core.freeze.FrozenFunction`; same results as traced)."""

    def __init__(self, mi_scene: mi.Scene, cell: float, bounces: int = 2, n_max: int = 8, rays: int = 32,
                 light_samples: int = 4, slots: int = 1 << 16, probes: int = 32, shape_key: bool = True,
                 seed: int = 0, budget: int = 0, evict_after: int = 0, max_load: float = 0.25,
                 freeze: bool = True, glossy_hits: bool = True):
        if slots & (slots - 1):
            raise ValueError("slots must be a power of two")
        self.sc, self.h, self.B = mi_scene, float(cell), int(bounces)
        self.n_max, self.rays, self.light_samples = int(n_max), int(rays), int(light_samples)
        self.slots, self.probes, self.shape_key, self.seed = int(slots), int(probes), bool(shape_key), int(seed)
        self.budget, self.evict_after, self.max_load = int(budget), int(evict_after), float(max_load)
        self.laps = Laps(False)
        # the kernels with BSDF, shape and emitter calls, traced once and replayed (dr.freeze); calls
        # narrower than 2 lanes traced (``narrow``: the arguments whose width decides)
        self.freeze, self.glossy_hits = bool(freeze), bool(glossy_hits)
        self._k_trace = FrozenFunction(trace_kernel, self.freeze, max_recordings=6)
        # lanes: the winning lanes idx (a pure kernel), run on a free width when their number equals the
        # size of some scene array (the atrium: 2,880, recorded again in a timed frame; slc.core.freeze)
        self._k_rep = FrozenFunction(rep_kernel, self.freeze, max_recordings=6, lanes=(3,), narrow=(3,))
        self._k_direct = FrozenFunction(direct_kernel, self.freeze, max_recordings=6, narrow=(4,))
        self._k_ray = FrozenFunction(ray_kernel, self.freeze, max_recordings=6, narrow=(0, 3))
        self._k_glossy = FrozenFunction(glossy_kernel, self.freeze, max_recordings=6, narrow=(4,))
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._alloc()
        if self.evict_after > 0 and not getattr(self, "_warm", False):
            self._warm = True           # once per table (reset() is also the eviction's "nothing survives")
            self._warm_rebuild()
            self._alloc()

    def _alloc(self) -> None:
        cap = self.slots
        self.keys = dr.full(mi.UInt32, EMPTY, cap)
        self.home = dr.zeros(mi.UInt32, cap)                # home slot of the key (for rebuilds)
        self.used = dr.zeros(mi.UInt32, cap)                # last frame touched
        self.stamp = dr.zeros(mi.UInt32, cap)               # last frame updated
        self.count = dr.zeros(mi.UInt32, cap)
        self.pending = dr.full(mi.UInt32, NO_RING, cap)     # ring requested for the next update
        self.rep = dr.zeros(mi.Float, cap * REP_WORDS)
        self.layers = dr.zeros(mi.Float, cap * 3 * self.B)
        self._reuse_count = dr.zeros(mi.UInt32, self.slots)   # primary hits per cell, last frame
        self._overflow = mi.UInt32(0)                         # kept lazy: no sync inside a timed stage
        self.updated, self.requested, self.evicted, self.frame = 0, 0, 0, 0
        dr.eval(self.keys, self.home, self.used, self.stamp, self.count, self.pending, self.rep, self.layers)

    def words_per_slot(self) -> int:
        return 6 + REP_WORDS + 3 * self.B       # key, home, used, stamp, count, ring + rep. point + layers

    def memory_bytes(self) -> int:
        """The whole table (allocated up front)."""
        return 4 * self.words_per_slot() * self.slots

    def used_cells(self) -> int:
        return int(dr.count(self.keys != EMPTY)[0])

    def used_bytes(self) -> int:
        return 4 * self.words_per_slot() * self.used_cells()

    # ------------------------------------------------------------------ keys
    def key_of(self, si: mi.SurfaceInteraction3f, d: mi.Vector3f, shape_index: mi.UInt32):
        """(key, home slot, front normal) of hits ``si`` reached along ``d`` on the shapes
        ``shape_index`` (indices into ``scene.shapes()``: the same in every process, unlike the
        shape pointers)."""
        return cell_key(si, d, shape_index, self.h, self.slots, self.shape_key)

    def trace(self, ray: mi.Ray3f, active=True) -> CacheHits:
        """Hits of cache rays and their cells' keys (:func:`trace_kernel`, frozen): position,
        geometric normal and shape only (``RayFlags.Minimal``): the cell key needs no more, and
        the full interaction (for the albedo) is computed again for the one representative lane
        per cell."""
        active = dr.zeros(mi.Bool, dr.width(ray.d)) | mi.Bool(active)      # an array of the rays' width
        return CacheHits(*self._k_trace(self.sc, ray, active, self.h, self.slots, self.shape_key))

    def _set_rep(self, slots: mi.UInt32, ok: mi.Bool, hits: CacheHits, ray: mi.Ray3f) -> None:
        """Each touched cell's representative point: the lowest lane that touched it. The albedo
        (a BSDF call on the full interaction, computed from the lane's preliminary intersection)
        is evaluated on the winning lanes only (one per touched cell)."""
        lane = dr.arange(mi.UInt32, dr.width(slots))
        win = dr.full(mi.UInt32, INVALID, self.slots)
        dr.scatter_reduce(dr.ReduceOp.Min, win, lane, slots, ok)
        dr.eval(win)
        w = ok & (dr.gather(mi.UInt32, win, slots, ok) == lane)
        idx = dr.compress(w)
        if dr.width(idx) == 0:
            return
        sl, words = self._k_rep(self.sc, hits.pi, ray, idx, slots, hits.p, hits.front_n)
        for j, v in enumerate(words):
            dr.scatter(self.rep, v, sl * REP_WORDS + j)
        dr.eval(self.rep)

    def touch(self, hits: CacheHits, ray: mi.Ray3f, active: mi.Bool):
        """Cells of the hits (from :meth:`trace`) of ``ray`` (inserted when new, representative
        point refreshed). Returns (slots, valid mask)."""
        ok = mi.Bool(active) & hits.valid
        self.laps.lap("touch_key", ok)
        slots = self.find_or_insert(hits.key, hits.home, ok)
        self.laps.lap("touch_find")
        ok &= slots != INVALID
        dr.eval(ok)
        self._set_rep(slots, ok, hits, ray)
        self.laps.lap("touch_rep")
        return slots, ok

    def sample(self, ray: mi.Ray3f, active, lane_key: mi.UInt32, mix, lap: str, grazing: bool = True,
               bounce: bool = False) -> CellHits:
        """Cache rays to the cells they hit: :meth:`trace`, :meth:`touch` and, with
        ``glossy_hits``, the non-diffuse hits' own estimate (:func:`glossy_kernel`, random
        numbers keyed by ``lane_key`` per ray and the stream ``mix``); with ``bounce`` (and
        ``bounces`` > 1) the glossy hits' BSDF rays traced and touched too (their cells, ring 2,
        are the caller's to request). ``grazing`` False drops the hits with n . d = 0.
        ``lap``: the sub-stage clock's name for the tracing."""
        hits = self.trace(ray, active)
        self.laps.lap(lap, hits.p, hits.n, hits.t, hits.valid, hits.key, hits.home, hits.glossy)
        slots, ok = self.touch(hits, ray, active)
        if not grazing:
            ok &= dr.dot(hits.n, ray.d) != 0.0
        glossy = None
        if self.glossy_hits:
            gi = dr.compress(hits.glossy)
            if dr.width(gi) > 0:
                glossy = GlossyHits(gi, *self._k_glossy(self.sc, light_inputs(self.sc), hits.pi, ray, gi,
                                                        lane_key, mix))
                if bounce and self.B > 1:
                    h2 = self.trace(glossy.ray, glossy.ok)
                    glossy.slots, glossy.hit = self.touch(h2, glossy.ray, glossy.ok)
                    glossy.hit &= dr.dot(h2.n, glossy.ray.d) != 0.0
        return CellHits(hits, slots, ok, glossy)

    def hit_radiance(self, h: CellHits, glossy_L=None, layer: int | None = None) -> list:
        """Per ray (3 channels): the outgoing radiance (layer ``layer``, default ``bounces``) of
        the cell it hit, or ``glossy_L`` at the glossy hits ``h.glossy.lanes``."""
        L = self.radiance(h.slots, h.ok, layer)
        L = [mi.Float(L[c]) for c in range(3)]
        if h.glossy is not None and glossy_L is not None:
            for c in range(3):
                dr.scatter(L[c], glossy_L[c], h.glossy.lanes)
        return L

    def updated_once(self, slots: mi.UInt32, ok: mi.Bool) -> mi.Bool:
        """Whether cells hold a value (updated at least once)."""
        return ok & (dr.gather(mi.UInt32, self.count, slots, ok) > 0)

    def radiance(self, slots: mi.UInt32, ok: mi.Bool, layer: int | None = None) -> mi.Color3f:
        """Outgoing radiance of cells (layer ``bounces`` by default)."""
        b = (self.B if layer is None else layer) - 1
        base = (slots * self.B + b) * 3
        return mi.Color3f(*[dr.gather(mi.Float, self.layers, base + c, ok) for c in range(3)])

    # ------------------------------------------------------------------ update
    def begin_frame(self, frame: int | None = None) -> mi.UInt32:
        """Start a frame: evict cells unused for ``evict_after`` frames, then return the requests
        carried from the previous update (ring per slot); the caller adds ring 1."""
        if frame is not None:
            self.frame = int(frame)
        self.evicted = 0
        if self.evict_after > 0:
            self.evict()
        req, self.pending = self.pending, dr.full(mi.UInt32, NO_RING, self.slots)
        return req

    def request(self, req: mi.UInt32, slots: mi.UInt32, ok: mi.Bool, ring: int = 1) -> None:
        dr.scatter_reduce(dr.ReduceOp.Min, req, mi.UInt32(ring), slots, ok)

    def record_reuse(self, slots: mi.UInt32, ok: mi.Bool) -> None:
        """Primary hits per touched cell this frame (the reuse histogram)."""
        cnt = dr.zeros(mi.UInt32, self.slots)
        dr.scatter_reduce(dr.ReduceOp.Add, cnt, mi.UInt32(1), slots, ok)
        self._reuse_count = cnt

    @property
    def overflow(self) -> int:
        """Requests that found no slot, since the last reset."""
        return int(self._overflow[0])

    @property
    def reuse(self) -> mi.UInt32:
        """Primary hits of each cell touched in the last frame."""
        cnt = self._reuse_count
        return dr.gather(mi.UInt32, cnt, dr.compress(cnt > 0))

    def update(self, frame: int, req: mi.UInt32) -> mi.UInt32:
        """Update every requested cell once (see the module); returns the updated slots."""
        sc, B = self.sc, self.B
        cells = dr.compress(req <= B)
        self.requested = dr.width(cells)
        if 0 < self.budget < dr.width(cells):
            # ----------- budget: least-sampled first, then oldest update, then slot -----------
            c_np = np.asarray(cells, dtype=np.int64)
            rg = np.asarray(dr.gather(mi.UInt32, req, cells), dtype=np.int64)
            cnt = np.asarray(dr.gather(mi.UInt32, self.count, cells), dtype=np.int64)
            age = self.frame - np.asarray(dr.gather(mi.UInt32, self.stamp, cells), dtype=np.int64)
            order = np.lexsort((c_np, -age, cnt, rg))[: self.budget]
            cells = mi.UInt32(aligned(np.sort(c_np[order]), np.uint32))   # aligned: else another kernel
        n = dr.width(cells)
        self.updated = n
        if n == 0:
            return cells
        ring = dr.gather(mi.UInt32, req, cells)

        # ------------------- direct light at the representative point (NEE) -------------------
        L_dir, p, nrm, rho, keys, lit = self._k_direct(
            sc, light_inputs(sc), self.rep, self.keys, cells, stream_key(self.seed, frame, STREAM_SECONDARY),
            dr.opaque(mi.UInt32, self.light_samples), float(max(self.light_samples, 1)))
        self.laps.lap("sec_direct")

        # ------------- cosine rays to other cells: layers b-1 of their previous update -------------
        mean = [mi.Color3f(0.0) for _ in range(B - 1)]
        tl = mi.UInt32()
        if B > 1:
            R = self.rays
            lane = dr.arange(mi.UInt32, n * R)
            c_of = lane // R
            tracing = dr.gather(mi.UInt32, ring, c_of) < B
            tracing &= dr.gather(mi.Bool, lit, c_of)
            # ---- only the tracing lanes (cells of ring < B with albedo) from here on ----
            tl = dr.compress(tracing)
        if dr.width(tl) > 0:      # (none: no cell of ring < B has albedo and light, e.g. a black scene)
            c_of = tl // R
            ray = self._k_ray(p, nrm, keys, tl, stream_key(self.seed, frame, STREAM_SECONDARY + 1), R)
            # ---- rays hitting glossy/metal surfaces: NEE with the hit's BSDF towards the cell
            # (the light after one reflection there, layer 1 exactly; a lower bound for layers >= 2) ----
            h = self.sample(ray, True, dr.gather(mi.UInt32, keys, c_of) * R + tl % R,
                            stream_key(self.seed, frame, STREAM_SECONDARY + 2), "sec_rays", grazing=False)
            next_ring = dr.gather(mi.UInt32, ring, c_of) + 1
            dr.scatter_reduce(dr.ReduceOp.Min, self.pending, next_ring, h.slots, h.ok & (next_ring <= B))
            for b in range(1, B):
                Lh = self.hit_radiance(h, h.glossy.Ld if h.glossy is not None else None, layer=b)
                full = [dr.zeros(mi.Float, n * R) for _ in range(3)]
                for c in range(3):
                    dr.scatter(full[c], Lh[c], tl)
                mean[b - 1] = mi.Color3f(*[dr.block_sum(full[c], R) for c in range(3)]) * (1.0 / R)
            dr.eval(self.pending, *mean)
            Lh = None                     # an unevaluated reader of the layers (written below)
            self.laps.lap("sec_touch")
            traced = ring < B
        else:
            traced = dr.zeros(mi.Bool, n)

        # ----------------------------- new layers, EMA, write back -----------------------------
        new = [rho * L_dir]
        for b in range(1, B):
            new.append(dr.select(traced, rho * (L_dir + mean[b - 1]), new[0]))
        cnt = dr.minimum(dr.gather(mi.UInt32, self.count, cells) + 1, 0xFFFF)
        a = dr.rcp(mi.Float(dr.minimum(cnt, self.n_max)))
        vals = []
        for b in range(B):
            for c in range(3):
                idx = (cells * B + b) * 3 + c
                old = dr.gather(mi.Float, self.layers, idx)
                vals.append((idx, dr.fma(a, new[b][c] - old, old)))
        dr.eval(cnt, *[v for _, v in vals])
        # no unevaluated reader of the written arrays may survive (Dr.Jit would copy them whole)
        old = None
        for idx, v in vals:
            dr.scatter(self.layers, v, idx)
        dr.scatter(self.count, cnt, cells)
        dr.scatter(self.stamp, dr.opaque(mi.UInt32, frame), cells)
        dr.eval(self.layers, self.count, self.stamp)
        return cells

    # ------------------------------------------------------------------ reports
    def reuse_histogram(self, bins=(1, 2, 4, 8, 16, 32, 64, 128, 256, 1 << 30)) -> dict:
        """Touched cells by primary hits per cell, in bins [bins[i], bins[i+1])."""
        r = np.asarray(self.reuse, dtype=np.int64)
        h, _ = np.histogram(r, bins=list(bins))
        return {"bins": list(bins), "counts": h.tolist(), "cells": int(r.size),
                "mean": float(r.mean()) if r.size else 0.0, "max": int(r.max()) if r.size else 0}
