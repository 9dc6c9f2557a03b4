"""The moving volume of the CRC cache (``volume="camera"``, the paper's Sec. 7;
:class:`MovingWindow`, a base of :class:`slc.methods.crc.cache.CRCCache`): the window's corner
from the first viewer's camera, the shaded points it serves, the random-stream key of a window
cell (its world cell's), the geometry occupancy read from the world's, and the scroll of the
coefficients and blend history when the window moves by whole cells."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods.crc.grid import Grid


class MovingWindow:
    """The moving window of :class:`~slc.methods.crc.cache.CRCCache`; a base of that class,
    reading its settings, world lattice and coefficient volumes."""

    def _window_offset(self, gbuffers) -> np.ndarray:
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

    def _key(self, cell: mi.UInt32) -> mi.UInt32:
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

    def _world_occupancy(self) -> mi.UInt32:
        """The (dilated) geometry occupancy of the window's cells, read from
        the world's."""
        if not self.moving:
            return self.geo_occ
        j = self.grid.unflat(dr.arange(mi.UInt32, self.grid.n_cells)) + self._cell_offset()
        ok = self.world.inside(j)
        return dr.gather(mi.UInt32, self.geo_occ, dr.select(ok, self.world.flat(j), 0), ok)

    def _scroll(self, delta: np.ndarray) -> None:
        """Move the window by ``delta`` whole cells: every coefficient (and
        the blend history) is copied from the cell that held the same world
        position; cells entering the window start empty. Gathers only (no
        recomputation), the shift an opaque input (no kernel build per move)."""
        n, nc = self.grid.n_cells, self.enc.n
        d = mi.Vector3i(*(dr.opaque(mi.Int32, int(x)) for x in delta))
        lane = dr.arange(mi.UInt32, nc * n)
        c, idx = lane // n, lane % n
        j = self.grid.unflat(idx) + d
        ok = self.grid.inside(j)
        src = dr.select(ok, self.grid.flat(j), 0)
        self.cache = dr.gather(mi.Float, self.cache, src + c * n, ok)
        jh = self.grid.unflat(dr.arange(mi.UInt32, n)) + d
        okh = self.grid.inside(jh)
        self.hist = dr.gather(mi.UInt32, self.hist, dr.select(okh, self.grid.flat(jh), 0), okh)

    def place(self, offset) -> None:
        """Put the window's corner at world cell ``offset``, scrolling the
        coefficients when the cache holds any."""
        offset = np.asarray(offset, dtype=np.int64)
        delta = offset - self.offset
        if not np.any(delta):
            return
        self.offset = offset
        if self._placed:
            self._scroll(delta)
            self.moves += 1
        self.grid = self._window_grid()

    def _window_grid(self) -> Grid:
        return Grid(lo=self.world.lo + self.offset * self.world.h, h=self.world.h, dims=(self.window,) * 3)
