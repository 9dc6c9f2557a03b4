"""Registers ``crc``: the Compressed Radiance Caching grid cache
(:class:`slc.methods.crc.cache.CRCCache`), a method whose ``output`` is indirect
light, so the pipeline compares it with the indirect reference
(:func:`slc.reference.references.reference_for`)."""
from slc.methods import register
from slc.methods.crc.cache import CRCCache

register("crc", CRCCache, help="CRC grid radiance cache, SH with YCoCg chroma compression (indirect light)")
