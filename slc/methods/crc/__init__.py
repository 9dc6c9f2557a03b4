"""Compressed Radiance Caching (CRC): a uniform grid of SH radiance cache
points with YCoCg chrominance compression, occupancy from a binary geometry
volume, ray-marched visibility, secondary bounces and temporal blending
(Vardis, Papaioannou and Gkaravelis, JCGT 2014)."""
from slc.methods.crc.cache import CRCCache
from slc.methods.crc.grid import Grid

__all__ = ["CRCCache", "Grid"]
