r"""Spatial filter of the primary caches (the slides: "spatial blur of radius 3 inside islands,
angle-error detection, parallax-corrected directions").

For an active entry x at texel (t_x, t_y) of its island and level, the neighbours are the entries
y at (t_x + dx, t_y + dy), |dx|, |dy| <= ``radius``, of the **same island and level** (never across
an island border), whose block is mapped and which hold a value (update count > 0), and whose
mirror offset (-dx, -dy) is such a neighbour too (**point-symmetric support**: where an island
border or an unmapped block truncates the kernel on one side, the other side is truncated alike,
so the kernel stays centred and a linear gradient across the texels is reproduced, not pulled
towards the island's inside; ``symmetric``). Texel k of x
(direction :math:`\omega_k`, the texel's centre in x's frame) is filtered as

.. math:: \tilde L_k(x) = \frac{\sum_y w_y\, a_{y,k}\, L_{k'(y)}(y)}{\sum_y w_y\, a_{y,k}},
          \qquad w_y = e^{-(dx^2 + dy^2) / (2\sigma^2)},\ \sigma = \max(r/2, 1/2),

with the **parallax-corrected** direction seen from y: the radiance of texel k comes from about
:math:`q = x + \omega_k\,\bar t_x` (:math:`\bar t_x` the entry's harmonic-mean hit distance,
stored as the EMA of :math:`1/t` over its rays, 0 for rays that miss), so from y it arrives along
:math:`\omega'_y = \mathrm{normalize}(\omega_k + (x - y)/\bar t_x)`, read from y's texel
:math:`k'(y)` containing it. **Angle-error detection** (:math:`a_{y,k}` = 0 or 1): a neighbour
texel is rejected when the normals of x and y differ by more than ``angle`` degrees, when the
parallax correction itself turns the direction by more than ``angle`` (the single mean distance
is then a poor estimate of the texel's hit), or when :math:`\omega'_y` is below y's horizon. The
centre (dx = dy = 0) always contributes with weight 1, so the weights never sum to 0. The
irradiance is re-summed from the filtered texels, :math:`\tilde E = \frac{\pi}{R^2}\sum_k \tilde
L_k`.

The filter reads the temporally filtered texels and its result is used for display only: the
temporal EMA keeps running on the unfiltered values (filtering feedback would blur further every
frame). Cost: (2r+1)^2 gathers per texel of every active entry.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID


class SpatialFilter:
    """Radius-``radius`` island-local blur of primary cache entries (see the module);
    ``angle`` (degrees) bounds the normal difference and the parallax correction."""

    def __init__(self, radius: int = 3, angle: float = 25.0, parallax: bool = True, symmetric: bool = True):
        self.r, self.angle, self.parallax, self.symmetric = int(radius), float(angle), bool(parallax), bool(symmetric)
        self.cos_max = math.cos(math.radians(self.angle))

    def apply(self, m, fr) -> mi.Float:
        """One function because its stages (neighbour pairs, texel gathers, the filtered copy)
        hand each other the pair arrays of one filter pass; its stages are marked by banner
        comments.

        The osc-gi method ``m``'s storage with the texels and irradiance of the active entries
        ``fr.active`` replaced by their filtered values (a copy: ``m.storage`` is left as it is);
        neighbours from the cache's entry topology (:class:`slc.osc.protocol.EntryTopology`)."""
        topo, storage, G = m.cache, m.storage, m.grid
        D, N = G.n, fr.n_active
        if self.r <= 0 or N == 0:
            return storage
        side = 2 * self.r + 1
        M = side * side
        sigma = max(self.r / 2.0, 0.5)

        # ------------------- neighbour pairs (entry, offset): slot, weight, offset -------------------
        isl, lvl, tx, ty = topo.entry_texels(fr.active)
        dr.eval(isl, lvl, tx, ty)
        p = dr.arange(mi.UInt32, N * M)
        e, j = p // M, p % M
        dx, dy = mi.Int32(j % side) - self.r, mi.Int32(j // side) - self.r
        x2, y2 = mi.Int32(dr.gather(mi.UInt32, tx, e)) + dx, mi.Int32(dr.gather(mi.UInt32, ty, e)) + dy
        sy = topo.slot_at(dr.gather(mi.UInt32, isl, e), dr.gather(mi.UInt32, lvl, e), x2, y2)
        ok = sy != INVALID
        ok &= m.read(sy, m.count_word, ok) > 0.0       # holds a value
        dr.eval(sy, ok)
        if self.symmetric:
            # point-symmetric support: offset (dx, dy) counts only with (-dx, -dy), index M-1-j
            ok_mirror = dr.gather(mi.Bool, ok, e * M + (M - 1 - j))
            ok &= ok_mirror
            dr.eval(ok)
        # neighbours' points and normals (the cache's own surface points), valid pairs only
        pv = dr.compress(ok)
        siy = topo.entry_points(dr.gather(mi.UInt32, sy, pv), dr.gather(mi.UInt32, isl, dr.gather(mi.UInt32, e, pv)))
        ey = dr.gather(mi.UInt32, e, pv)
        px = mi.Point3f(*[dr.gather(mi.Float, fr.si.p[c], ey) for c in range(3)])
        nx = mi.Vector3f(*[dr.gather(mi.Float, fr.si.sh_frame.n[c], ey) for c in range(3)])
        ny = siy.sh_frame.n
        keep = dr.dot(nx, ny) >= self.cos_max
        jj = dr.gather(mi.UInt32, j, pv)
        ddx, ddy = mi.Float(mi.Int32(jj % side) - self.r), mi.Float(mi.Int32(jj // side) - self.r)
        w = dr.select(keep, dr.exp(-(ddx * ddx + ddy * ddy) / (2.0 * sigma * sigma)), 0.0)
        off = px - siy.p
        pair_slot = dr.full(mi.UInt32, INVALID, N * M)
        pair_w = dr.zeros(mi.Float, N * M)
        pair_off = [dr.zeros(mi.Float, N * M) for _ in range(3)]
        pair_n = [dr.zeros(mi.Float, N * M) for _ in range(3)]
        dr.scatter(pair_slot, dr.select(keep, dr.gather(mi.UInt32, sy, pv), INVALID), pv)
        dr.scatter(pair_w, w, pv)
        for c in range(3):
            dr.scatter(pair_off[c], off[c], pv)
            dr.scatter(pair_n[c], ny[c], pv)
        dr.eval(pair_slot, pair_w, *pair_off, *pair_n)

        # ---------------- texels: parallax-corrected gathers from every neighbour ----------------
        lane = dr.arange(mi.UInt32, N * D)
        te, k = lane // D, lane % D
        slot_x = dr.gather(mi.UInt32, fr.active, te)
        n_x = mi.Vector3f(*[dr.gather(mi.Float, fr.si.sh_frame.n[c], te) for c in range(3)])
        omega = mi.Frame3f(n_x).to_world(G.direction(k, mi.Point2f(0.5, 0.5)))
        invd = m.read(slot_x, m.inv_t_word) if self.parallax else mi.Float(0.0)
        n_taps = dr.opaque(mi.UInt32, M)

        def cond(i, acc, wsum):
            return i < n_taps

        def body(i, acc, wsum):
            q = te * M + i
            sy = dr.gather(mi.UInt32, pair_slot, q)
            okq = sy != INVALID
            wq = dr.gather(mi.Float, pair_w, q, okq)
            o = mi.Vector3f(*[dr.gather(mi.Float, pair_off[c], q, okq) for c in range(3)])
            ny = mi.Vector3f(*[dr.gather(mi.Float, pair_n[c], q, okq) for c in range(3)])
            wy = dr.normalize(omega + o * invd)
            loc = mi.Frame3f(ny).to_local(wy)
            okq &= (loc.z > 0.0) & (dr.dot(wy, omega) >= self.cos_max) & dr.all(dr.isfinite(wy))
            Ly = mi.Color3f(*m.read(sy, G.texel(loc) * 3, okq, n=3))
            return i + 1, acc + dr.select(okq, wq * Ly, 0.0), wsum + dr.select(okq, wq, 0.0)

        _, acc, wsum = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), mi.Float(0.0)), cond=cond,
                                     body=body, labels=("i", "acc", "wsum"))
        Lf = acc * dr.select(wsum > 0.0, dr.rcp(dr.maximum(wsum, 1e-20)), 0.0)
        dr.eval(Lf)
        E = [dr.block_sum(Lf[c], D) * G.texel_weight for c in range(3)]

        # ------------------------- the filtered copy of the storage -------------------------
        out = dr.copy(storage)       # the scatters below must not touch ``storage``
        m.write([Lf[c] for c in range(3)], slot_x, k * 3, storage=out)
        m.write(E, fr.active, m.irr_word, storage=out)
        dr.eval(out)
        return out
