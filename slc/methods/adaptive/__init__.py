"""The adaptive cache: per-entry representation (delta-light visibility,
cones, SH/YCoCg) chosen from the light each surface point receives.

The registered method ``adaptive`` lives in :mod:`slc.methods.adaptive.method`; see
docs/adaptive.md.
"""
