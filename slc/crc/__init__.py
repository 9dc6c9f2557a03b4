"""Compressed Radiance Caching (CRC): a uniform grid of SH radiance cache
points with YCoCg chrominance compression, occupancy from a binary geometry
volume, ray-marched visibility, secondary bounces and temporal blending
(Vardis, Papaioannou and Gkaravelis, JCGT 2014)."""
from .cache import CRCCache
from .grid import Grid

__all__ = ["CRCCache", "Grid"]
