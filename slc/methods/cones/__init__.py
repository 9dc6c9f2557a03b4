"""Surface Light Cones on the on-surface cache: the registered method ``slc``
(:mod:`slc.methods.cones.method`), its update kernel over the cache entries
(:mod:`slc.methods.cones.update_kernel`) and a one-entry-per-pixel cache
(:mod:`slc.methods.cones.pixelcache`). The cone lobes, their update, shading and packing are in
:mod:`slc.lib.cones`; see docs/cones.md.
"""
