"""Surface Light Cones: the cone payload of an on-surface cache entry, its update
(insertion cases A-D, accumulation count, shrink), shading and 286-bit packing.

The registered method ``slc`` lives in :mod:`slc.methods.cones.method`; see docs/cones.md.
"""
from slc.methods.cones.packing import bytes_per_entry, pack, unpack, words_per_entry
from slc.methods.cones.update import ConeParams, angle_between

__all__ = ["ConeParams", "angle_between", "bytes_per_entry", "pack", "unpack", "words_per_entry"]
