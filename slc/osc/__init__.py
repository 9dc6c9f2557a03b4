"""On-surface cache (OSC): the shared cache structure that cache methods
(Surface Light Cones, SH caches) store their per-entry payloads in.

Status: complete -- islands (vectorised normal-cone + triangle-count
clustering, no xatlas), per-island texture spaces and shelf-packed per-mesh
atlases, per-pixel mip level from footprint and bias, virtual texture of
8x8 (or 2x2) blocks with a two-level block table, allocation on first
request, eviction after K unused frames (pool growth, or LRU eviction +
overflow report, when the pool is full), dedupe with scatter + compress,
update queue (8 rays while new / after motion, 1 settled), LOD seeds from
coarser entries, the texel's own surface point (triangle lookup once per
entry, Dr.Jit), memory, fill ratio and overlap stats.
Not done: non-mesh shapes (analytic spheres etc.) get INVALID slots; the
back side of a triangle shares the front side's entries; new entries are
seeded from coarser entries only (not from finer ones).
Design and numbers: docs/osc.md.

Usage::

    from slc.osc import OnSurfaceCache, INVALID
    cache = OnSurfaceCache(scene, block_size=8, bias=1.0, evict_after=60)
    fr = cache.begin_frame(frame, gbuffers, timer)
    fr.pixel_slot[v], fr.active, fr.si, fr.rays, fr.is_new, fr.seed_slot
"""
from .cache import INVALID, FrameRequests, OnSurfaceCache
from .islands import MeshIslands, build_mesh_islands, charts_overlap, cluster_faces, island_deviation

__all__ = ["OnSurfaceCache", "FrameRequests", "INVALID", "MeshIslands", "build_mesh_islands",
           "charts_overlap", "cluster_faces", "island_deviation"]


def cache_for(scene, cache=None, block_size: int = 8, bias: float = 1.0, evict_after: int = 60,
              entry_bytes: int = 0):
    """The cache a payload method (cones, SH) stores its entries in: ``cache``
    when one is given (tests pass stand-ins), else a new :class:`OnSurfaceCache`;
    ``entry_bytes`` is the payload's packed size, used for memory reports."""
    if cache is None:
        cache = OnSurfaceCache(scene, block_size=block_size, bias=bias, evict_after=evict_after)
    cache.set_entry_bytes(entry_bytes)
    return cache
