"""ReSTIR's reservoirs: the per-pixel state (:class:`Reservoir`), a reservoir
being filled by weighted streaming selection (:class:`Stream`) and the
balance-heuristic share used by the pairwise MIS weights."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.structs import drjit_struct


@drjit_struct
@dataclass
class Reservoir:
    """Per-pixel reservoirs (structure of arrays).

    ``y``: point on a local light (area or point/spot), or the world
    direction towards an infinite light (environment, directional);
    ``n``: light surface normal (area lights); ``light``: index into
    ``scene.emitters()``; ``W``: unbiased contribution weight; ``M``:
    confidence (number of candidates the reservoir stands for)."""
    y: mi.Point3f = field(default_factory=mi.Point3f)
    n: mi.Vector3f = field(default_factory=mi.Vector3f)
    light: mi.UInt32 = field(default_factory=mi.UInt32)
    W: mi.Float = field(default_factory=mi.Float)
    M: mi.Float = field(default_factory=mi.Float)


class Stream:
    """A reservoir being filled by weighted streaming selection:
    candidate sample (y, n, light), its target value ``p_hat`` at the
    reservoir's own shading point, running weight sum and confidence.
    A Dr.Jit struct of the fields a symbolic loop carries (all but ``M``)."""
    DRJIT_STRUCT = {"y": mi.Point3f, "n": mi.Vector3f, "light": mi.UInt32, "p_hat": mi.Float, "w_sum": mi.Float}

    def __init__(self, n: int = 0):
        self.y = dr.zeros(mi.Point3f, n)
        self.n = dr.zeros(mi.Vector3f, n)
        self.light = dr.zeros(mi.UInt32, n)
        self.p_hat = dr.zeros(mi.Float, n)
        self.w_sum = dr.zeros(mi.Float, n)
        self.M = dr.zeros(mi.Float, n)

    def update(self, y, n, light, p_hat, w, u, active):
        """Add one candidate of resampling weight ``w`` (selection by ``u``)."""
        w = dr.select(active & (w > 0.0) & dr.isfinite(w), w, 0.0)
        self.w_sum += w
        take = (w > 0.0) & (u * self.w_sum < w)
        self.y = dr.select(take, y, self.y)
        self.n = dr.select(take, n, self.n)
        self.light = dr.select(take, light, self.light)
        self.p_hat = dr.select(take, p_hat, self.p_hat)

    def finalize(self, Z, M, valid) -> Reservoir:
        """W = w_sum / (Z p_hat(y)), every division guarded."""
        ok = valid & (self.p_hat > 0.0) & (Z > 0.0) & (self.w_sum > 0.0)
        W = dr.select(ok, self.w_sum / dr.select(ok, Z * self.p_hat, 1.0), 0.0)
        W = dr.select(dr.isfinite(W), W, 0.0)
        return Reservoir(mi.Point3f(self.y), mi.Vector3f(self.n), mi.UInt32(self.light), W,
                         dr.select(valid, M, 0.0))


def share(a, b):
    """a / (a + b) for non-negative a, b: the balance-heuristic share of the
    technique weighted a (0 where a = 0)."""
    ok = a > 0.0
    return dr.select(ok, a / dr.select(ok, a + b, 1.0), 0.0)
