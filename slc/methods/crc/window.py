"""The cells the CRC cache covers (:class:`Region`, held by :class:`slc.methods.crc.cache.CRCCache`
as ``region``): the scene grid, or the moving volume (``volume="camera"``, the paper's Sec. 7): the
window's corner from the first viewer's camera, the shaded points it serves, the random-stream key
of a window cell (its world cell's), the geometry occupancy read from the world's, and the scroll of
the coefficients and blend history when the window moves by whole cells."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods.crc.grid import Grid


class Region:
    """The cache grid of :class:`~slc.methods.crc.cache.CRCCache`: the world lattice ``world``
    itself, or with ``moving`` a ``window``^3 window of it (cells per side) whose centre cell holds
    the first viewer's camera, moved ``ahead`` cells along its view (the ``window`` and ``ahead``
    settings). ``grid`` is the current cache grid, ``offset`` the window's corner in world cells,
    ``moves`` the whole-cell moves so far."""

    def __init__(self, world: Grid, moving: bool, window: int, ahead: float):
        self.world, self.moving, self.window, self.ahead = world, moving, window, ahead
        self.offset = np.zeros(3, dtype=np.int64)     # window corner in world cells
        self.moves = 0
        self.grid = self._window_grid() if moving else world

    def corner(self, gbuffers) -> np.ndarray:
        """World-cell corner of the window whose centre cell holds the first
        viewer's camera (moved ``ahead`` cells along its view)."""
        cam = gbuffers[0].camera
        f, _, _ = cam.basis()
        c = np.asarray(cam.origin, float) + f * (self.ahead * self.world.h)
        return np.floor((c - self.world.lo) / self.world.h).astype(np.int64) - self.window // 2

    def in_window(self, p: mi.Point3f, q: mi.Point3f) -> mi.Bool:
        """Shaded points the window serves: the lookup point q's trilinear
        stencil lies in the window and so does the point p's own cell (whose
        depth occupancy, dilated by one cell, marks that stencil)."""
        return self.grid.stencil_inside(q) & self.grid.cell_of(p)[1]

    def _cell_offset(self) -> mi.Vector3i:
        return mi.Vector3i(*(dr.opaque(mi.Int32, int(x)) for x in self.offset))

    def key(self, cell: mi.UInt32) -> mi.UInt32:
        """Random-stream key of a cache cell: its flat index; in a moving
        window, the flat index of its world cell (the same key as with
        volume=scene), or for a cell outside the scene's grid ``n_world`` +
        its index on the world lattice padded by the window. So a cell draws
        the same numbers wherever the window is, and as the scene grid's."""
        if not self.moving:
            return cell
        P = self.window
        nx, ny, _ = self.world.dims
        i = self.grid.unflat(cell) + self._cell_offset()
        ip = i + P
        outside = mi.UInt32(self.world.n_cells) + mi.UInt32((ip.z * (ny + 2 * P) + ip.y) * (nx + 2 * P) + ip.x)
        return dr.select(self.world.inside(i), self.world.flat(i), outside)

    def occupancy(self, geo_occ: mi.UInt32) -> mi.UInt32:
        """The (dilated) geometry occupancy ``geo_occ`` of the world's cells, read at the
        window's cells."""
        if not self.moving:
            return geo_occ
        j = self.grid.unflat(dr.arange(mi.UInt32, self.grid.n_cells)) + self._cell_offset()
        ok = self.world.inside(j)
        return dr.gather(mi.UInt32, geo_occ, dr.select(ok, self.world.flat(j), 0), ok)

    def _scroll(self, delta: np.ndarray, cache: mi.Float, hist: mi.UInt32, n_coeffs: int):
        """Move the window by ``delta`` whole cells: every coefficient of ``cache`` (``n_coeffs``
        volumes over the grid) and the blend history ``hist`` is copied from the cell that held
        the same world position; cells entering the window start empty. Gathers only (no
        recomputation), the shift an opaque input (no kernel build per move). (cache, hist)."""
        n, nc = self.grid.n_cells, n_coeffs
        d = mi.Vector3i(*(dr.opaque(mi.Int32, int(x)) for x in delta))
        lane = dr.arange(mi.UInt32, nc * n)
        c, idx = lane // n, lane % n
        j = self.grid.unflat(idx) + d
        ok = self.grid.inside(j)
        src = dr.select(ok, self.grid.flat(j), 0)
        cache = dr.gather(mi.Float, cache, src + c * n, ok)
        jh = self.grid.unflat(dr.arange(mi.UInt32, n)) + d
        okh = self.grid.inside(jh)
        hist = dr.gather(mi.UInt32, hist, dr.select(okh, self.grid.flat(jh), 0), okh)
        return cache, hist

    def place(self, offset, cache: mi.Float, hist: mi.UInt32, n_coeffs: int, scroll: bool):
        """Put the window's corner at world cell ``offset``; with ``scroll`` (the cache holds
        coefficients) scroll ``cache`` and ``hist`` (see :meth:`_scroll`) and count the move.
        (cache, hist)."""
        offset = np.asarray(offset, dtype=np.int64)
        delta = offset - self.offset
        if not np.any(delta):
            return cache, hist
        self.offset = offset
        if scroll:
            cache, hist = self._scroll(delta, cache, hist, n_coeffs)
            self.moves += 1
        self.grid = self._window_grid()
        return cache, hist

    def _window_grid(self) -> Grid:
        return Grid(lo=self.world.lo + self.offset * self.world.h, h=self.world.h, dims=(self.window,) * 3)
