"""On-surface cache (OSC): the shared cache structure that cache methods
(Surface Light Cones, SH caches, your own) store their per-entry payloads in.
Their base class, :class:`slc.methods.cache_method.PayloadMethod`, lives in the
methods layer above this package, which imports nothing from it.

Modules, one concept each:

- :mod:`.protocol`: the contract between a surface cache and its payload
  (:class:`FrameRequests`, :class:`SurfaceCache`, declared capabilities, :class:`EntryTopology`);
- :mod:`.islands`: islands, their texture spaces, the per-mesh atlas (numpy set-up);
- :mod:`.analytic`: analytic shapes' (u, v) grids, from which their islands are built (numpy set-up);
- :mod:`.layout`: islands and levels as Dr.Jit tables, the virtual block space;
- :mod:`.blocks`: the two-level block table and the physical block pool (allocation, eviction);
- :mod:`.surface`: each entry's own surface point (triangle lookup, analytic (u, v));
- :mod:`.requests`: slot dedupe over viewers, LOD seeds, bilinear taps;
- :mod:`.cache`: :class:`OnSurfaceCache`, the per-frame stages.

Analytic spheres, disks and cylinders are cached through a (u, v) grid
used for their layout only; other non-mesh shapes get INVALID slots (one
warning names them). Not done: the back side of a triangle shares the front side's entries; new entries are
seeded from coarser entries only (not from finer ones).
Design and numbers: docs/osc.md.
"""
from slc.core import backend

backend.ensure()  # the modules of this package build Mitsuba types on import

from slc.core.keys import INVALID
from slc.osc.cache import OnSurfaceCache
from slc.osc.islands import MeshIslands, build_mesh_islands, charts_overlap, cluster_faces, island_deviation
from slc.osc.protocol import BILINEAR_TAPS, ENTRY_TEXELS, ENTRY_TOPOLOGY, EntryTopology, FrameRequests, SurfaceCache

__all__ = ["OnSurfaceCache", "FrameRequests", "SurfaceCache", "INVALID", "BILINEAR_TAPS", "ENTRY_TEXELS",
           "ENTRY_TOPOLOGY", "EntryTopology",
           "MeshIslands", "build_mesh_islands", "charts_overlap", "cluster_faces", "island_deviation"]
