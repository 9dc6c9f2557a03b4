"""Global illumination with on-surface radiance caches (``osc-gi``).

Primary caches (incoming radiance over an R x R cosine-weighted hemisphere grid per on-surface
cache entry, :mod:`.hemisphere`) and secondary caches (outgoing diffuse radiance in a hashed world
grid of coarse cells, :mod:`.secondary`), after Tatzgern et al., "Radiance Caching with On-Surface
Caches for Real-Time Global Illumination" (2024). See ``docs/osc-gi.md``."""
from slc.methods.oscgi.hemisphere import HemiGrid
from slc.methods.oscgi.secondary import SecondaryCache

__all__ = ["HemiGrid", "SecondaryCache"]
