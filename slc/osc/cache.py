"""The on-surface cache (OSC): a virtual texture of blocks over per-island
texture spaces, shared by all viewers; implements :class:`.protocol.SurfaceCache`.

Per frame (:meth:`OnSurfaceCache.begin_frame`), all in Dr.Jit:

1. requests: each valid pixel of each viewer -> (island, mip level, texel)
   -> virtual block + texel within the block (:mod:`.layout`); requested
   virtual blocks are flagged in a flag array (one ``dr.scatter``).
2. allocate: evict blocks unused for ``evict_after`` frames, compress the
   flag array to the sorted unique requested blocks, map the unmapped ones
   to free physical blocks (:mod:`.blocks`); every pixel gets its entry slot
   (``phys_block * B^2 + texel_in_block``); slots are deduped over viewers
   (:func:`.requests.dedupe`), which also measures the viewer overlap.
3. queue: new entries get their LOD seed (:func:`.requests.lod_seeds`) and
   their own surface point (a triangle lookup once per entry,
   :mod:`.surface`); every active entry's ``SurfaceInteraction3f``.

How many rays an entry gets is its payload's decision
(:class:`slc.methods.cache_method.PayloadMethod`). See ``docs/osc.md``.
"""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene import gbuffer as gbuf
from slc.core.keys import INVALID
from slc.core.timing import NullTimer
from slc.osc.blocks import BlockPool, widen
from slc.osc.islands import DEFAULT_MAX_ANGLE, DEFAULT_MAX_TRIANGLES
from slc.osc.layout import CacheLayout
from slc.osc.protocol import BILINEAR_TAPS, ENTRY_TEXELS, ENTRY_TOPOLOGY, FrameRequests
from slc.osc.requests import bilinear_taps, dedupe, lod_seeds, requested_blocks
from slc.osc.surface import EntryInteractions, TexelPoints

DEFAULT_CAPACITY_ENTRIES = 2 ** 20   # default initial pool: 1M entries (16384 blocks of 8x8), at most the virtual size


class OnSurfaceCache:
    """Shared on-surface cache of a scene (see module and ``docs/osc.md``).

    Parameters
    ----------
    scene: :class:`slc.scene.scenes.Scene` (its triangle meshes and analytic
        spheres, disks and cylinders get islands; other shapes are named in
        one warning, not cached, and their pixels get INVALID slots).
    block_size: texels per block edge (8 as in OSC, 2 as in the slides);
        power of two.
    bias: mip bias; level = round(log2(footprint * bias / texel_size)).
    evict_after: a block unused for more than this many frames is freed.
    texel_size: world size of a level-0 texel; default
        ``sqrt(total cached area / 2**24)`` (about 16M level-0 texels).
    max_blocks: physical blocks in the pool; default
        ``min(virtual blocks, 2**20 / block_size**2)`` (1M entries).
    max_angle, max_triangles: island bounds (degrees, triangles).
    grow: when the pool is full, double it (default; ``capacity`` changes
        and payload arrays follow it). With ``grow=False`` the least recently
        used blocks not requested this frame are evicted early, and what
        still does not fit is reported (``stats()['overflow_blocks']``, a
        warning) and its pixels get INVALID slots.
    freeze: the entries' interactions traced once and replayed (``dr.freeze``,
        :class:`slc.osc.surface.EntryInteractions`; default), or traced every frame.
    front_only: only pixels whose surface faces the viewer (``si.wi.z > 0``)
        request entries; the others get INVALID slots (default off: every valid
        pixel). For payloads that shade back faces black anyway (osc-gi): a
        viewer looking at the back of one-sided walls (the overlap rig's views
        of the cornell box from behind) then asks for no entries.
    """

    capabilities = frozenset({BILINEAR_TAPS, ENTRY_TEXELS, ENTRY_TOPOLOGY})

    def __init__(self, scene, block_size: int = 8, bias: float = 1.0, evict_after: int = 60,
                 texel_size: float | None = None, max_blocks: int | None = None,
                 max_angle: float = DEFAULT_MAX_ANGLE, max_triangles: int = DEFAULT_MAX_TRIANGLES,
                 grow: bool = True, front_only: bool = False, freeze: bool = True):
        self.scene = scene
        self.freeze = bool(freeze)
        self.front_only = bool(front_only)
        self.mi_scene = scene.mi_scene if hasattr(scene, "mi_scene") else scene
        self.layout = CacheLayout(self.mi_scene, block_size, bias, texel_size, max_angle, max_triangles)
        self.evict_after = int(evict_after)
        if max_blocks is None:
            max_blocks = max(1, min(self.layout.n_vblocks, DEFAULT_CAPACITY_ENTRIES // self.layout.block_texels))
        self.pool = BlockPool(self.layout, int(max_blocks), grow)
        self.reset()

    # ------------------------------------------------------------------ state
    @property
    def capacity(self) -> int:
        return self.pool.capacity

    @property
    def texel_size(self) -> float:
        return self.layout.texel_size

    def reset(self) -> None:
        """Forget every entry (all blocks free, stats cleared)."""
        self.pool.reset()
        self.points = TexelPoints(self.layout, self.capacity)
        self.tick = 0
        self._stats = dict(blocks=0, entries_allocated=0, entries_requested=0, fill_ratio=0.0,
                           measured_overlap=0.0, evicted=0, new_entries=0, new_blocks=0,
                           overflow_blocks=0, pixels=0, capacity=self.capacity)
        self._warned = False
        self._pending = None
        self._interactions = EntryInteractions(freeze=self.freeze)

    def entries_allocated(self) -> int:
        return self.pool.n_blocks * self.layout.block_texels

    def memory_bytes(self) -> int:
        """The cache's own structures: the block table, and per allocated
        entry its surface point (triangle + barycentrics, 12 B) and its
        seen flag (4 B). Payload storage is reported by the payload."""
        return self.pool.table_bytes() + 16 * self.entries_allocated()

    def stats(self) -> dict:
        p = self._pending
        if p is not None:      # the last frame's counts, read back here (not in the timed stages)
            self._pending = None
            n_multi = int(dr.count(p["multi"])[0]) if dr.width(p["multi"]) else 0
            self._stats["measured_overlap"] = 100.0 * n_multi / max(p["n_active"], 1)
            self._stats["pixels"] = int(dr.count(p["valid"])[0]) if dr.width(p["valid"]) else 0
        return dict(self._stats, cache_bytes=self.memory_bytes())

    # ------------------------------------------------------------------ frame
    def begin_frame(self, frame: int, gbuffers, timer=None, extra=None) -> FrameRequests:
        """Requests from every viewer's G-buffer, dedupe, allocation, update
        queue; timed as stages "requests", "allocate", "queue". ``extra``: more
        entries by :meth:`entry_address`, their slots in ``FrameRequests.extra_slot``."""
        timer = timer if timer is not None else NullTimer()
        L, pool = self.layout, self.pool
        # all viewers' pixels as one array: the frame's layered G-buffer (no copy
        # when attached, as the pipeline does; one viewer's own arrays)
        src = gbuf.layered(list(gbuffers)) if gbuffers else None

        # ---------------------------------------------------------- 1. requests (one launch for all viewers)
        with timer.stage("requests") as st:
            if src is None:
                req = (mi.Bool(), mi.UInt32(), mi.UInt32(), mi.UInt32())
            else:
                req = L.pixel_texels(src)
                if self.front_only:
                    req = (req[0] & (src.si.wi.z > 0.0),) + tuple(req[1:])
                dr.eval(req[0], req[1], req[2])    # once: both passes of requested_blocks read them
            reqs = [req] + ([_address_request(L, extra)] if extra is not None and dr.width(extra) > 0 else [])
            req_vb = requested_blocks(reqs, L.n_vblocks)
            st.outputs(req_vb)

        # ---------------------------------------------------------- 2. allocate + slot dedupe
        with timer.stage("allocate") as st:
            self.tick += 1
            evicted = pool.evict(self.tick, self.evict_after)
            if dr.width(req_vb) == 0:      # nothing cacheable in view (or no viewer)
                self._frame_stats(evicted=evicted)
                return FrameRequests.empty(frame, gbuffers)
            n_new_blocks, overflow, grown = pool.allocate(req_vb)
            if grown:
                self.points.resize(self.capacity)
            if overflow and not self._warned:
                warnings.warn(f"OSC pool full ({pool.max_blocks} blocks): {overflow} requested blocks "
                              f"not allocated this frame (pixels get INVALID); pass max_blocks or grow=True")
                self._warned = True
            req_phys = pool.touch(req_vb, self.tick)
            active, slots, index, multi = dedupe(pool, reqs, req_phys, [src.viewer] + [len(gbuffers)] * (len(reqs) - 1))
            dr.eval(active)    # apart: n_active may equal a viewer's pixel count (same-sized values fuse)
            st.outputs(slots[0], index[0], multi, pool.blk_vb, pool.blk_last)
        pixel_slot, pixel_index = self._per_viewer(slots[0], src), self._per_viewer(index[0], src)

        # ---------------------------------------------------------- 3. queue: new entries, surface points
        with timer.stage("queue") as st:
            n_active = dr.width(active)
            is_new = dr.gather(mi.UInt32, pool.slot_seen, active) == 0
            isl, lvl, tx, ty = pool.entry_texels(active)
            seed = dr.full(mi.UInt32, INVALID, n_active)
            # evaluated here whether or not there are new entries: a frame without any (a still
            # camera) would otherwise fuse them into other kernels than a frame with some
            dr.make_opaque(seed)
            dr.eval(is_new, isl, lvl, tx, ty)
            new_idx = dr.compress(is_new)
            n_new = dr.width(new_idx)
            if n_new:
                new_idx = widen(new_idx)   # a repeated entry computes and writes the same values
                g = [dr.gather(mi.UInt32, a, new_idx) for a in (active, isl, lvl, tx, ty)]
                dr.scatter(seed, lod_seeds(L, pool, *g[1:]), new_idx)
                self.points.place(*g)
                # apart from the n-sized values below: a kernel must not depend on
                # whether n_new happens to equal n_active (same-sized values fuse)
                dr.eval(seed, self.points.slot_tri, self.points.slot_b)
            dr.eval(seed, is_new, isl)
            si = self.points.interactions(active, isl, self._interactions)
            keys = self._keys(isl, lvl, tx, ty)
            dr.scatter(pool.slot_seen, mi.UInt32(1), active)
            st.outputs(si, is_new, seed, keys, pool.slot_seen)

        # counts are read back in stats(), outside the timed stages
        self._frame_stats(evicted=evicted, entries_requested=n_active, new_entries=n_new,
                          new_blocks=n_new_blocks, overflow_blocks=overflow, requested_blocks=dr.width(req_vb))
        self._pending = dict(multi=multi, n_active=n_active, valid=req[0])
        texel = mi.Float(mi.UInt32(1) << lvl) * L.texel_size      # islands are charted at world scale
        return FrameRequests(frame=frame, active=active, si=si, is_new=is_new, seed_slot=seed, keys=keys,
                             pixel_slot=pixel_slot, pixel_index=pixel_index,
                             layer_slot=slots[0], layer_index=index[0], texel_size=texel,
                             extra_slot=slots[1] if len(reqs) > 1 else None)

    @staticmethod
    def _per_viewer(values, src) -> list:
        """Per viewer, its part of a value over the layered pixels (unevaluated
        gathers; the value itself for one viewer)."""
        if len(src.sizes) == 1:
            return [values]
        return gbuf.per_viewer(mi.UInt32(values), src.sizes, src.offsets)

    def _frame_stats(self, **kw):
        self._pending = None
        alloc = self.entries_allocated()
        self._stats = dict(blocks=self.pool.n_blocks, entries_allocated=alloc, entries_requested=0,
                           new_entries=0, new_blocks=0, overflow_blocks=0, requested_blocks=0, pixels=0,
                           measured_overlap=0.0, evicted_early=self.pool.evicted_early,
                           capacity=self.capacity)
        self._stats.update(kw)
        self._stats["fill_ratio"] = self._stats["entries_requested"] / max(alloc, 1)

    # ------------------------------------------------------------------ entries
    def _keys(self, isl, lvl, tx, ty) -> mi.UInt32:
        k0, _ = mi.sample_tea_32(isl * self.layout.levels + lvl, (ty << 16) | tx, 4)
        return k0

    def entry_address(self, slots) -> mi.UInt32:
        """Each slot's texel as ``virtual block * B^2 + texel in block``: unique, the same on every
        render node, whatever physical block holds it (a key of 32 bits while the virtual texture
        holds fewer than 2^32 texels)."""
        slots = mi.UInt32(slots)
        B2 = self.layout.block_texels
        return dr.gather(mi.UInt32, self.pool.blk_vb, slots // B2) * B2 + (slots & (B2 - 1))

    def address_slots(self, address, active=True) -> mi.UInt32:
        """The slots holding the texels ``address`` (:meth:`entry_address`) where their block is
        mapped, else INVALID."""
        a = mi.UInt32(address)
        L = self.layout
        ph = self.pool.phys(a >> (2 * L.block_shift), active)
        return dr.select(ph != INVALID, ph * L.block_texels + (a & (L.block_texels - 1)), INVALID)

    def entry_keys(self, slots) -> mi.UInt32:
        """A 32-bit hash of each slot's (island, level, tx, ty): the same for a
        texel whatever physical block it landed in, so payload random numbers
        keyed by it do not depend on which viewers asked for what."""
        return self._keys(*self.pool.entry_texels(mi.UInt32(slots)))

    # ------------------------------------------------------------------ entry topology (EntryTopology)
    def entry_texels(self, slots) -> tuple:
        """(island, level, tx, ty) of the entries ``slots``."""
        return self.pool.entry_texels(mi.UInt32(slots))

    def slot_at(self, island, level, tx, ty, active=True) -> mi.UInt32:
        """The slot of texel (tx, ty) of ``island``'s ``level``; INVALID where inactive, outside
        the level, not mapped or never requested before this frame."""
        L = self.layout
        key = island * L.levels + level
        wl, hl = L.key_extent(key, active)
        x, y = mi.Int32(tx), mi.Int32(ty)
        inside = mi.Bool(active) & (x >= 0) & (y >= 0) & (x < wl) & (y < hl)
        ux, uy = mi.UInt32(dr.maximum(x, 0)), mi.UInt32(dr.maximum(y, 0))
        return self.pool.slot(L.vblock(key, ux, uy, inside), L.within(ux, uy), inside)

    def entry_points(self, slots, island) -> mi.SurfaceInteraction3f:
        """The entries' own surface points (their texel centres on their own triangles)."""
        return self.points.interactions(slots, island)

    def entry_info(self, slots) -> dict:
        """numpy (island, level, tx, ty, texel_world) of slots: a viewer-independent key."""
        isl, lvl, tx, ty = self.pool.entry_texels(mi.UInt32(slots))
        lv = np.array(lvl)
        return dict(island=np.array(isl), level=lv, tx=np.array(tx), ty=np.array(ty),
                    texel_world=self.layout.texel_size * np.exp2(lv.astype(np.float64)))

    def bilinear_taps(self, gb, own_slots=None):
        """See :func:`.requests.bilinear_taps`."""
        return bilinear_taps(self.layout, self.pool, gb, own_slots)

    def pixel_levels(self, gb) -> mi.UInt32:
        """Mip level of every pixel of a G-buffer (0 where nothing is cached)."""
        valid, _, _, lvl = self.layout.pixel_texels(gb)
        return dr.select(valid, lvl, 0)


def _address_request(layout: CacheLayout, address) -> tuple:
    """A request (valid, virtual block, texel in block, level) of the entries ``address``
    (:meth:`OnSurfaceCache.entry_address`; the level is not read by the allocation)."""
    a = mi.UInt32(address)
    return (dr.full(mi.Bool, True, dr.width(a)), a >> (2 * layout.block_shift), a & (layout.block_texels - 1),
            dr.zeros(mi.UInt32, dr.width(a)))
