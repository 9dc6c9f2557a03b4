"""Registers ``crc``: the Compressed Radiance Caching grid cache
(:class:`slc.crc.cache.CRCCache`), a method whose ``output`` is indirect
light, so the pipeline compares it with the indirect reference
(:func:`slc.references.reference_for`)."""
from ..methods import register
from .cache import CRCCache

register("crc", CRCCache, help="CRC grid radiance cache, SH with YCoCg chroma compression (indirect light)")
