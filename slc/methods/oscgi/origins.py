"""Where the cache rays of primary entries start, measured: each entry's rays start from its own
surface point (the texel centre on its own triangle, :meth:`slc.osc.surface.TexelPoints.lookup`),
offset along its normal by ``spawn_ray``. A ray that starts inside closed geometry or behind a wall
meets a surface from behind first; :func:`backface_share` counts such rays (``OSCGI.probe_origins``,
tests). One plane standing for a whole island (its first triangle) instead puts origins off a bent
island's surface: +2-3% FLIP on the atrium, no change on the Cornell box (``docs/osc-gi.md``)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def backface_share(n: mi.Vector3f, d: mi.Vector3f, valid: mi.Bool) -> tuple[int, int]:
    """(rays whose hit is the back of a surface, valid hits): a ray that starts inside closed
    geometry (or behind a wall) first meets a surface from behind."""
    back = valid & (dr.dot(n, d) > 0.0)
    return int(dr.count(back)[0]), int(dr.count(valid)[0])
