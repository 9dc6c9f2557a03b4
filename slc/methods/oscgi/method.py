"""The registered ``osc-gi`` method: global illumination from primary radiance caches in the
on-surface cache and secondary radiance caches in a hashed world grid (``docs/osc-gi.md``)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.lights import light_inputs
from slc.core.freeze import FrozenFunction
from slc.scene.gbuffer import layered, per_viewer, viewer_lanes
from slc.core.keys import INVALID, keyed_rng, stream_key
from slc.scene.lights import diffuse_flags
from slc.methods import MethodError, Param, create, register
from slc.osc.cache import OnSurfaceCache
from slc.methods.cache_method import PayloadMethod, RayPolicy
from slc.osc.protocol import ENTRY_TOPOLOGY
from slc.lib.sh.shading import diffuse_only, shade_radiance
from slc.methods.oscgi.hemisphere import HemiGrid
from slc.methods.oscgi.kernels import STREAM_PIXEL_DIRECT, STREAM_SHADE, pixel_direct_kernel
from slc.methods.oscgi.laps import Laps
from slc.methods.oscgi.primary import PrimaryUpdate
from slc.methods.oscgi.secondary import SecondaryCache
from slc.methods.oscgi.spatial import SpatialFilter

DIRECT_METHODS = {"cones": "slc", "restir": "restir"}   # direct=... -> the registered method run beside
INITIAL_ENTRIES = 1 << 14     # the pool starts small and doubles on demand (entries are ~0.8 KB)


def _cache_params():
    """The on-surface cache's settings: mip bias 2 as in the slides (one entry per about 2x2
    pixels) and 4x4 blocks (the slides: 2x2; the cache's per-frame request flag spans every
    virtual block, 4x more of them at 2x2: see docs/osc-gi.md)."""
    out = []
    for p in PayloadMethod.cache_params:
        if p.name == "block":
            p = Param("block", 4, p.help, choices=p.choices)
        elif p.name == "bias":
            p = Param("bias", 2.0, p.help, lo=p.lo, hi=p.hi)
        out.append(p)
    return tuple(out)


class OSCGI(PayloadMethod):
    r"""Radiance caching with on-surface caches (``osc-gi``, Tatzgern et al. 2024).

    *Primary caches*: every requested on-surface cache entry x (its own surface point, rays offset
    along its normal) keeps the incoming radiance over its hemisphere in ``hemi`` x ``hemi`` texels
    of the cosine-weighted concentric map (:class:`~slc.methods.oscgi.hemisphere.HemiGrid`, frame of the
    entry's shading normal). Each update traces one jittered cosine ray per texel; a ray's hit y
    falls in a secondary cell whose outgoing radiance :math:`L_o(y)` (layer ``bounces``) is the
    texel's new sample; with ``output=full, direct=cache``, ``direct_rays`` light samples (next-event
    estimation, :func:`slc.scene.lights.sample_light` + shadow ray) are binned into the texels of their
    directions, :math:`\hat L_k \mathrel{+}= \frac{L_e\cos\theta}{n\,p\,\pi/R^2}[\omega\in k]`.
    Temporal filter: :math:`L_k \leftarrow L_k + (\hat L_k - L_k)/\min(c, N_{max})`, c the
    entry's update count (an EMA over ``n_max`` samples once settled); a new entry starts from
    its LOD seed (a coarser entry) when the cache gives one.

    *Secondary caches*: :class:`~slc.methods.oscgi.secondary.SecondaryCache`, cells of
    ``secondary_cm`` cm keyed by position, normal bin and shape, storing outgoing diffuse radiance
    in ``bounces`` layers (direct light by ``light_samples`` light samples, indirect by
    ``secondary_rays`` cosine rays into other cells; EMA capped at ``secondary_n_max``), so the primary point receives light after
    1..``bounces`` reflections, the paths of the indirect reference. At most ``secondary_budget``
    cells are updated per frame (ring 1 first, then least-sampled, then oldest; the others keep
    their value, and a texel does not blend a sample from a cell never updated unless it has no
    value either); cells unused for ``secondary_evict`` frames are freed.
    The cell edge is max(``secondary_cm``, ``secondary_scene`` x the scene's bounding-box diagonal),
    fixed for the run.

    *Glossy hits*: a primary ray whose hit has a glossy or delta BSDF takes its
    sample at the hit, since a cell's diffuse radiance cannot hold view-dependent light (and is 0
    for a metal): one light sample with the hit's BSDF plus one BSDF-sampled ray whose hit cell's
    layer ``bounces`` - 1 is weighted by :math:`f\cos/p` (that cell requested as ring 2); a
    secondary ray hitting such a surface takes the light sample's term alone (layer 1 exactly).

    ``freeze`` (on): the kernels with shape, BSDF or emitter calls (cache rays and cell keys,
    representative albedo, direct light of cells and entries, secondary rays, glossy hits) are
    traced once and replayed (:class:`slc.core.freeze.FrozenFunction`); the same images as traced.

    *Shading* (no rays): diffuse-only BSDFs exactly from the texels,
    :math:`L_o = \frac{\rho}{\pi} E,\ E = \frac{\pi}{R^2}\sum_k L_k`; other BSDFs by
    ``glossy_samples`` BSDF samples of the hemisphere, :math:`\frac{1}{n}\sum_j w_j L_{k(\omega_j)}`.
    ``output``: ``indirect`` (light after at least one reflection) or ``full`` (direct + indirect;
    the emission seen directly is added by the pipeline).

    *Direct light* (``output=full``), ``direct``: ``rt`` (default) ``direct_n`` (16) light samples
    per pixel with shadow rays, :math:`\frac1n\sum_j f L_e G V/p` (RT-N, frozen; the n points of a
    pixel are a Hammersley set shifted by a random offset per pixel), added to the cached indirect
    light; ``cones`` / ``restir``: the registered ``slc`` / ``restir`` method run beside on the
    same G-buffers; ``cache``: light samples binned into the entries' texels (above). Except for
    ``cache`` the entries hold indirect light only, exactly as with ``output=indirect``.

    *Many viewers*: ``update_budget`` (2) caps the entries updated per frame at
    ``update_budget`` x (pixels of the largest viewer) / bias^2, about twice one viewer's entries
    (never reached by one viewer): every new entry, then the most due (fewest samples, oldest
    update); the others keep their value (:meth:`PrimaryUpdate._budgeted`). Only pixels facing the viewer
    request entries (back faces are shaded black). Several viewers are shaded in one launch
    (:meth:`shade_all`).

    *Spatial filter* (``filter_radius`` > 0, off): the entries are blurred inside their islands
    before display (:class:`~slc.methods.oscgi.spatial.SpatialFilter`).

    *Fixed choices*: the class attributes below (``shape_key``, ``seed_finer``, ``front_only``,
    ``glossy_hits``, ``direct_lds``, ``parallax``, ...) are not settings; each was measured
    against its alternative (``docs/osc-gi.md``), and a subclass may switch one to measure it
    again (the tests do).

    Storage per entry: 3 R^2 radiance words, the irradiance (3 words), the update count and the
    mean inverse hit distance of its rays (for the spatial filter's parallax).
    Ray budget (the ray policy): an entry's first update traces all R^2 texels, later updates
    ``texel_rays`` of them in rotation (texel k when k = c mod R^2/``texel_rays``, c the update
    number), each traced texel blended with 1/min(its own sample count, ``n_max``); light samples
    (``output=full``) only feed the traced texels.
    """

    name = "osc-gi"
    output = "full"
    params = (
        Param("output", "full", "what is returned: direct + indirect light, or indirect light only",
              choices=("full", "indirect")),
        Param("bounces", 2, "indirect bounces: layers of the secondary cells", lo=1, hi=8),
        Param("hemi", 8, "hemisphere texels per side of a primary cache entry (hemi^2 texels)", lo=2, hi=16),
        Param("texel_rays", 64, "texels traced per update of a settled entry (new entries: all); divides hemi^2",
              lo=1, hi=256),
        Param("n_max", 4, "temporal blend of the primary texels: factor 1/min(updates, n_max)", lo=1, hi=256),
        Param("secondary_n_max", 2, "temporal blend of the secondary cells: factor 1/min(updates, "
              "secondary_n_max); 0: n_max", lo=0, hi=256),
        Param("secondary_cm", 15.0, "smallest secondary cell edge [cm]", lo=1.0, hi=1000.0),
        Param("secondary_scene", 0.04, "smallest secondary cell edge as a fraction of the scene's bounding-box "
              "diagonal (0: off); the edge is the larger of the two", lo=0.0, hi=1.0),
        Param("secondary_rays", 16, "cosine rays per secondary cell update", lo=1, hi=1024),
        Param("light_samples", 4, "light samples per secondary cell update", lo=1, hi=1024),
        Param("glossy_samples", 16, "BSDF samples of the hemisphere texels per non-diffuse pixel", lo=1, hi=1024),
        Param("secondary_budget", 8192, "secondary cell updates per frame at most, least-sampled first (0: all)",
              lo=0, hi=1 << 24),
        Param("filter_radius", 0, "spatial filter radius in texels inside islands, display only (0: off)",
              lo=0, hi=8),
        Param("freeze", True, "kernels with shape/BSDF/emitter calls traced once and replayed (dr.freeze)"),
        Param("direct", "rt", "direct light of output=full: binned into the entries' texels (cache), per pixel by "
              "direct_n light samples with shadow rays (rt), or the slc or restir method run beside (cones, restir)",
              choices=("cache", "rt", "cones", "restir")),
        Param("direct_n", 16, "light samples per pixel with direct=rt", lo=1, hi=1024),
        Param("update_budget", 2.0, "primary entries updated per frame at most, in units of one viewer's share "
              "(pixels of the largest viewer / bias^2); new entries first, then the most due; 0: all requested",
              lo=0.0, hi=1e6),
    ) + _cache_params()
    storage_type = mi.Float
    needs = frozenset({ENTRY_TOPOLOGY})      # the finer-level seeds and the spatial filter
    # ---- fixed choices (see the class docstring; docs/osc-gi.md has their measurements) ----
    shape_key = True          # secondary cells keyed by shape too (no sharing across shapes)
    seed_finer = True         # a new entry without a coarser seed starts from its finer entries' mean
    front_only = True         # only pixels facing the viewer request entries
    glossy_hits = True        # primary rays hitting glossy/metal surfaces: NEE + one BSDF ray into a cell
    direct_lds = True         # direct=rt: a pixel's light samples are a randomly shifted Hammersley set
    parallax = True           # spatial filter: parallax-corrected directions
    filter_symmetric = True   # spatial filter: point-symmetric support (no bias along island borders)
    filter_angle = 25.0       # spatial filter: largest normal difference and parallax turn [deg]
    secondary_slots = 17      # log2 of the secondary hash table's size
    secondary_evict = 4       # secondary cells unused for this many frames are freed
    direct_rays = 8           # direct=cache: light samples per primary entry update
    probe_origins = False     # count the cache rays hitting a back face (origin_probe: back, valid)
    origin_probe = (0, 0)

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.grid = HemiGrid(self.hemi)
        # an entry's words: 3 per texel (radiance), then the irradiance (3), the update count, the mean 1/t
        D = self.grid.n
        self.words, self.irr_word, self.count_word, self.inv_t_word = 3 * D + 5, 3 * D, 3 * D + 3, 3 * D + 4
        self.filter = SpatialFilter(self.filter_radius, self.filter_angle, self.parallax, self.filter_symmetric)
        self.label = None if self.output == "full" else "osc-gi:output=indirect"
        # traced once and replayed (FrozenFunction): a new width of the inputs needs no recording;
        # a call narrower than 2 lanes is traced (narrow: the argument whose width decides)
        self._k_pixel = FrozenFunction(pixel_direct_kernel, bool(self.freeze), max_recordings=6, narrow=(5,))
        self.primary = PrimaryUpdate(self)      # the primary caches' update, stage by stage (primary.py)
        self._sub = None
        if self.output == "full" and self.direct in DIRECT_METHODS:
            self._sub = create(DIRECT_METHODS[self.direct], scene, seed=self.seed)

    def validate(self):
        if self.output not in ("full", "indirect"):
            raise MethodError(f"{self.name}: output must be full or indirect")
        if self.direct not in ("cache", "rt") + tuple(DIRECT_METHODS):
            raise MethodError(f"{self.name}: direct must be cache, rt, cones or restir")
        D = self.hemi * self.hemi
        if self.texel_rays > D or D % self.texel_rays:
            raise MethodError(f"{self.name}: texel_rays must divide hemi^2 = {D} (got {self.texel_rays})")

    def ray_policy(self) -> RayPolicy:
        """All texels for an entry's first update, ``texel_rays`` afterwards (texels in rotation)."""
        D = self.hemi * self.hemi
        return RayPolicy(new=D, new_updates=1, settled=self.texel_rays, moving=D, motion_updates=1)

    def update(self, ctx, fr, policy):
        """The primary caches' update, by the part :class:`PrimaryUpdate` (no entry reports motion)."""
        return self.primary.update(ctx, fr, policy)

    def update_limit(self, fr) -> int:
        """The most entries one frame's update may take (:meth:`PrimaryUpdate.update_limit`)."""
        return self.primary.update_limit(fr)

    def reset(self):
        super().reset()
        self.secondary = None
        # sub-stage clock of update (off unless an experiment sets _profile: no host syncs)
        self.laps = Laps(getattr(self, "_profile", False), getattr(self, "_profile_skip", 0))
        self.memory_log = []          # per frame: (primary bytes, secondary bytes in use)
        self.entries_updated = 0      # entries the last update took
        for part in (getattr(self, "primary", None), getattr(self, "_sub", None)):
            if part is not None:
                part.reset()

    def _cell_edge(self) -> float:
        """The secondary cells' edge (scene units): max(``secondary_cm``, ``secondary_scene`` x the
        scene's bounding-box diagonal); fixed for the run (a new edge would change every cell's key)."""
        unit = float(getattr(self.scene, "unit", 1.0) or 1.0)
        bb = self.scene.mi_scene.bbox()
        diag = float(np.linalg.norm(np.array(bb.max) - np.array(bb.min)))
        diag = diag if np.isfinite(diag) else 0.0
        return max(self.secondary_cm / 100.0 * unit, self.secondary_scene * diag)

    def make_cache(self):
        """The on-surface cache: a small pool that doubles on demand, front faces only."""
        return OnSurfaceCache(self.scene, block_size=self.block, bias=self.bias, evict_after=self.evict_after,
                              max_blocks=max(1, INITIAL_ENTRIES // (self.block * self.block)),
                              front_only=bool(self.front_only))

    def _make_secondary(self) -> SecondaryCache:
        sec = SecondaryCache(self.scene.mi_scene, self._cell_edge(), self.bounces,
                             self.secondary_n_max or self.n_max, self.secondary_rays, self.light_samples,
                             1 << self.secondary_slots, shape_key=self.shape_key, seed=self.seed,
                             budget=self.secondary_budget, evict_after=self.secondary_evict,
                             freeze=bool(self.freeze), glossy_hits=bool(self.glossy_hits))
        sec.laps = self.laps
        return sec

    # ------------------------------------------------------------------ shade
    def shade_all(self, ctx, fr, gbuffers):
        """Every viewer's pixels. Several viewers are shaded in one launch over the frame's
        layered G-buffer (:func:`slc.scene.gbuffer.layered`; the cache's slots laid out the same way,
        ``fr.layer_slot`` / ``fr.layer_index``), then split per viewer: each pixel keeps the
        random-number key it has per viewer (its index within its own viewer), so the images are
        those of :meth:`shade` bit for bit, and the shading (BSDF calls) is traced in Python once
        a frame instead of once per viewer. With the spatial filter on (``filter_radius`` > 0),
        from a filtered copy of the active entries (:class:`~slc.methods.oscgi.spatial.SpatialFilter`,
        timed with the display), the temporal state left unfiltered."""
        storage = self.filter.apply(self, fr) if self.filter.r > 0 else None
        if len(gbuffers) < 2 or fr.layer_slot is None or fr.layer_index is None:
            return [self._shade_viewer(ctx, fr, v, gb, storage) for v, gb in enumerate(gbuffers)]
        lay = layered(gbuffers)
        L = self._shade_pixels(ctx, fr, lay.si, lay.valid, mi.UInt32(fr.layer_slot), mi.UInt32(fr.layer_index),
                               lay.pixel, storage)
        return per_viewer(L, lay.sizes, lay.offsets)

    def shade(self, ctx, fr, v, gb):
        """One viewer's pixels (see :meth:`_shade_pixels`)."""
        return self._shade_viewer(ctx, fr, v, gb)

    def _shade_viewer(self, ctx, fr, v, gb, storage=None):
        if len(fr.pixel_slot) > 1 and fr.layer_slot is not None:
            # several viewers: the viewer's part of the layered values, gathered here rather than
            # through the cache's per-viewer views, whose unevaluated gathers (made in another
            # order) gave the fused shading kernel of all viewers another IR in some frames (a kernel
            # built in a timed frame of the 16-viewer row)
            at = viewer_lanes(gb.size, sum(dr.width(fr.pixel_slot[u]) for u in range(v)))
            slot = dr.gather(mi.UInt32, fr.layer_slot, at)
            idx = dr.gather(mi.UInt32, fr.layer_index, at)
        else:
            slot, idx = mi.UInt32(fr.pixel_slot[v]), mi.UInt32(fr.pixel_index[v])
        return self._shade_pixels(ctx, fr, gb.si, mi.Bool(gb.valid), slot, idx, dr.arange(mi.UInt32, gb.size),
                                  storage)

    def _shade_pixels(self, ctx, fr, si, valid, slot, idx, pid, storage=None):
        """Pixels ``si`` (G-buffer mask ``valid``) from their entries (``slot`` into the storage,
        ``idx`` into ``fr.si``); ``pid`` each pixel's index within its own viewer (the key of
        its random numbers); ``storage``: the entries' words (default ``self.storage``). Diffuse
        BSDFs from the irradiance words, others by BSDF samples of the hemisphere texels
        (:func:`slc.lib.sh.shading.shade_radiance`)."""
        G = self.grid
        ok = valid & (slot != INVALID) & (si.wi.z > 0.0)
        bsdf = si.bsdf()
        d_only = diffuse_only(bsdf)
        g = ok & ~d_only
        n_e = mi.Vector3f(*[dr.gather(mi.Float, fr.si.sh_frame.n[c], idx, g) for c in range(3)])
        frame_e = mi.Frame3f(n_e)

        def irradiance():
            # diffuse: E from the entry's irradiance words
            return mi.Color3f(*self.read(slot, self.irr_word, ok & d_only, n=3, storage=storage))

        def radiance(d, m):
            # glossy: the entry's hemisphere texel towards d (BSDF importance sampling)
            loc = frame_e.to_local(d)
            m = m & (loc.z > 0.0)
            return mi.Color3f(*self.read(slot, G.texel(loc) * 3, m, n=3, storage=storage)), m

        sampler = keyed_rng(pid, self.seed, ctx.frame, STREAM_SHADE)
        return shade_radiance(si, bsdf, ok, irradiance, radiance, sampler, self.glossy_samples)

    # ------------------------------------------------------------------ frame
    def update_frame(self, ctx, gbuffers, timer):
        if self.secondary is None:
            self.secondary = self._make_secondary()
        return super().update_frame(ctx, gbuffers, timer)

    def finish(self, ctx, fr, gbuffers, out, timer):
        """After shading the cached light: the direct light per pixel (stage "direct") or the
        per-pixel method ``_sub`` (its own frame) added to it; the memory log."""
        # ------- direct light per pixel (output=full, direct != cache): added to the cached indirect -------
        if self.output == "full" and self.direct == "rt":
            with timer.stage("direct") as st:
                sc = self.scene.mi_scene
                mix = stream_key(self.seed, ctx.frame, STREAM_PIXEL_DIRECT)
                n = dr.opaque(mi.UInt32, self.direct_n)
                # every viewer's pixels in one launch (the frame's layers); streams keyed by the pixel
                # index within its viewer (identical viewers: identical images)
                lay = layered(gbuffers)
                idx = lay.pixel if lay.pixel is not None else dr.arange(mi.UInt32, lay.size)
                L = self._k_pixel(sc, light_inputs(sc), diffuse_flags(sc), lay.si, mi.Bool(lay.valid), idx,
                                  mix, n, bool(self.direct_lds))
                if len(gbuffers) == 1:
                    out[0] = out[0] + L
                else:
                    out = [o + Lv for o, Lv in zip(out, per_viewer(L, lay.sizes, lay.offsets))]
                st.outputs(*out)
        elif self._sub is not None:
            sub = self._sub.render_stages(ctx, gbuffers, timer)
            out = [a + b for a, b in zip(out, sub)]
        if self.cache is not None:
            self._cells = self.secondary.used_cells()
            self.memory_log.append((int(self.cache.memory_bytes())
                                    + int(self.cache.entries_allocated()) * self.payload_bytes(),
                                    self._cells * 4 * self.secondary.words_per_slot()))
        return out

    # ------------------------------------------------------------------ reports
    def memory_bytes(self) -> int:
        """Primary caches (the on-surface cache and its payloads) + the secondary hash table."""
        return (super().memory_bytes() + (self.secondary.memory_bytes() if self.secondary is not None else 0)
                + (self._sub.memory_bytes() if self._sub is not None else 0))

    def stats(self) -> dict:
        out = super().stats()
        if self.secondary is not None:
            sec = self.secondary
            r = sec.reuse
            out.update({"secondary_cells": float(getattr(self, "_cells", 0)), "secondary_updated": float(sec.updated),
                        "entries_updated": float(self.entries_updated),
                        "secondary_overflow": float(sec.overflow), "secondary_requested": float(sec.requested),
                        "secondary_evicted": float(sec.evicted), "secondary_cell_m": float(sec.h),
                        "secondary_reuse_mean": float(dr.mean(mi.Float(r))[0]) if dr.width(r) else 0.0})
            if self.memory_log:
                out["primary_mb"] = self.memory_log[-1][0] / 2 ** 20
                out["secondary_mb"] = self.memory_log[-1][1] / 2 ** 20
        return out


register("osc-gi", OSCGI, help="GI from primary (on-surface, hemisphere) and secondary (world-grid) radiance caches")
