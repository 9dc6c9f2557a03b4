"""The uniform CRC grid and its 4x finer binary geometry volume.

Cells are cubes of side ``h`` (the longest side of the scene box divided by
the resolution ``r``), with one cell of margin on each side so that the
dilation and the trilinear stencil never leave the grid. The cache point of
a cell is its centre. Flat cell index: ``(z * ny + y) * nx + x``.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

#: geometry voxels per cell along each axis (the paper's "quadruple resolution")
GEOMETRY_FACTOR = 4


@dataclass
class Grid:
    lo: np.ndarray      # world position of the corner of cell (0, 0, 0)
    h: float            # cell size
    dims: tuple         # (nx, ny, nz)

    @classmethod
    def around(cls, bbox_min, bbox_max, resolution: int = 16) -> "Grid":
        """A grid over the box with ``resolution`` cells along its longest
        side, plus one cell of margin on each side."""
        bmin, bmax = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
        ext = np.maximum(bmax - bmin, 1e-6)
        h = float(ext.max()) / max(int(resolution), 1)
        n = np.maximum(np.ceil(ext / h - 1e-6).astype(int), 1) + 2
        center = 0.5 * (bmin + bmax)
        lo = center - 0.5 * n * h
        return cls(lo=lo, h=h, dims=tuple(int(x) for x in n))

    @property
    def n_cells(self) -> int:
        nx, ny, nz = self.dims
        return nx * ny * nz

    def finer(self, factor: int = GEOMETRY_FACTOR) -> "Grid":
        return Grid(lo=self.lo.copy(), h=self.h / factor, dims=tuple(d * factor for d in self.dims))

    # ---------------------------- Dr.Jit helpers ----------------------------
    def origin(self) -> mi.Vector3f:
        """``lo`` as an opaque kernel input, not a literal: a moving volume
        changes it without recompiling the kernels that use it."""
        return mi.Vector3f(*(dr.opaque(mi.Float, float(x)) for x in self.lo))

    def coords(self, p: mi.Point3f) -> mi.Vector3f:
        """Continuous cell coordinates of world points (cell i spans [i, i+1))."""
        return (p - self.origin()) / self.h

    def flat(self, i: mi.Vector3i) -> mi.UInt32:
        nx, ny, _ = self.dims
        return mi.UInt32((i.z * ny + i.y) * nx + i.x)

    def inside(self, i: mi.Vector3i) -> mi.Bool:
        nx, ny, nz = self.dims
        return (i.x >= 0) & (i.y >= 0) & (i.z >= 0) & (i.x < nx) & (i.y < ny) & (i.z < nz)

    def cell_of(self, p: mi.Point3f):
        """(flat index, inside mask) of the cell containing each point."""
        i = mi.Vector3i(dr.floor(self.coords(p)))
        ok = self.inside(i)
        return dr.select(ok, self.flat(i), 0), ok

    def unflat(self, idx: mi.UInt32) -> mi.Vector3i:
        nx, ny, _ = self.dims
        x = idx % nx
        y = (idx // nx) % ny
        z = idx // (nx * ny)
        return mi.Vector3i(mi.Int32(x), mi.Int32(y), mi.Int32(z))

    def center(self, idx: mi.UInt32) -> mi.Point3f:
        i = self.unflat(idx)
        return mi.Point3f(self.origin() + (mi.Vector3f(i) + 0.5) * self.h)

    def stencil_inside(self, q: mi.Point3f) -> mi.Bool:
        """The 8 cache points interpolated at ``q`` all lie in the grid
        (trilinear() clamps otherwise)."""
        nx, ny, nz = self.dims
        u = self.coords(q) - 0.5
        return ((u.x >= 0.0) & (u.y >= 0.0) & (u.z >= 0.0)
                & (u.x <= nx - 1) & (u.y <= ny - 1) & (u.z <= nz - 1))

    def trilinear(self, q: mi.Point3f):
        """The 8 (flat index, weight) pairs interpolating cache points (cell
        centres) at world points ``q``."""
        nx, ny, nz = self.dims
        u = self.coords(q) - 0.5
        hi = mi.Vector3f(nx - 2, ny - 2, nz - 2)
        i0f = dr.clip(dr.floor(u), 0.0, hi)
        f = dr.clip(u - i0f, 0.0, 1.0)
        i0 = mi.Vector3i(i0f)
        out = []
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    w = ((f.x if dx else 1.0 - f.x) * (f.y if dy else 1.0 - f.y) * (f.z if dz else 1.0 - f.z))
                    out.append((self.flat(i0 + mi.Vector3i(dx, dy, dz)), w))
        return out


def lookup(grid: Grid, vol: mi.Float, n_coeffs: int, q: mi.Point3f, active: mi.Bool) -> list:
    """Trilinearly interpolated coefficients of ``vol`` (``n_coeffs`` dense volumes over ``grid``,
    coefficient-major) at points q."""
    n = grid.n_cells
    acc = [mi.Float(0.0) for _ in range(n_coeffs)]
    for idx, w in grid.trilinear(q):
        for c in range(n_coeffs):
            acc[c] += w * dr.gather(mi.Float, vol, idx + c * n, active)
    return acc
