"""Surface Light Cones: the cone lobes of a cache entry, their update (insertion cases A-D,
accumulation count, shrink) and update cycle, their shading (closed forms and quadrature) and
286-bit packing. Used by the ``slc`` method (:mod:`slc.methods.cones`) and the adaptive cache's cone
pool (:mod:`slc.methods.adaptive.cones_rep`); see docs/cones.md.
"""
from slc.lib.cones.packing import bytes_per_entry, pack, unpack, words_per_entry
from slc.lib.cones.update import ConeParams, angle_between

__all__ = ["ConeParams", "angle_between", "bytes_per_entry", "pack", "unpack", "words_per_entry"]
