"""Binary volumes of the CRC cache: the geometry volume (scene triangles
voxelized at 4x the grid resolution), the occupancy volume (OR-downsampled
geometry volume), the depth occupancy volume (G-buffer points injected with
a pixel stride) and the one-cell dilation.

Voxelization (set-up, numpy): each triangle is sampled on a barycentric
lattice whose spacing is under half a voxel, so every voxel the triangle
crosses receives at least one sample (conservative up to that spacing).
Volumes are ``mi.UInt32`` arrays of 0/1 flags over the flat cell index.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods.crc.grid import GEOMETRY_FACTOR, Grid
from slc.osc.analytic import tessellate_analytic


def scene_triangles(mi_scene: mi.Scene) -> np.ndarray:
    """(T, 3, 3) world-space triangle vertices of every shape of the scene: a mesh's own
    triangles (Mitsuba's ``rectangle`` and ``cube`` are meshes, whose positions are not among
    their traversed parameters), an analytic ``sphere``, ``cylinder`` or ``disk`` through the
    grid of its parameter square (:func:`slc.osc.analytic.tessellate_analytic`). A shape of
    another type has no triangles (its voxels stay empty)."""
    tris = []
    for sh in mi_scene.shapes():
        if sh.is_mesh():
            V = np.array(sh.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
            F = np.array(sh.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        else:
            grid = tessellate_analytic(sh)
            if grid is None:
                continue
            V, F = grid.V, grid.F.astype(np.int64)
        if len(F):
            tris.append(V[F])
    return np.concatenate(tris, 0) if tris else np.zeros((0, 3, 3))


def voxelize(tris: np.ndarray, geo: Grid, chunk: int = 4_000_000) -> mi.UInt32:
    """Flags (0/1) of the geometry voxels touched by the triangles."""
    nx, ny, nz = geo.dims
    flags = np.zeros(nx * ny * nz, dtype=np.uint32)
    if len(tris) == 0:
        return mi.UInt32(flags)
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    edge = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                   np.linalg.norm(a - c, axis=1)], axis=0)
    k_all = np.maximum(np.ceil(edge / (0.5 * geo.h)).astype(np.int64), 1)
    for k in np.unique(k_all):
        sel = np.nonzero(k_all == k)[0]
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        m = (i + j) <= k
        bu, bv = (i[m] / k)[None, :, None], (j[m] / k)[None, :, None]
        per = int(m.sum())
        step = max(chunk // per, 1)
        for s in range(0, len(sel), step):
            t = sel[s:s + step]
            pts = a[t, None] + bu * (b[t, None] - a[t, None]) + bv * (c[t, None] - a[t, None])
            v = np.floor((pts.reshape(-1, 3) - geo.lo) / geo.h).astype(np.int64)
            ok = np.all((v >= 0) & (v < np.array(geo.dims)), axis=1)
            v = v[ok]
            flags[(v[:, 2] * ny + v[:, 1]) * nx + v[:, 0]] = 1
    return mi.UInt32(flags)


def occupancy_from_geometry(geometry: mi.UInt32, grid: Grid, factor: int = GEOMETRY_FACTOR) -> mi.UInt32:
    """A cell is occupied when any of its factor^3 geometry voxels is set."""
    geo = grid.finer(factor)
    vid = dr.compress(geometry != 0)
    iv = geo.unflat(vid)
    cell = grid.flat(mi.Vector3i(iv.x // factor, iv.y // factor, iv.z // factor))
    occ = dr.zeros(mi.UInt32, grid.n_cells)
    dr.scatter(occ, mi.UInt32(1), cell)
    return occ


def depth_occupancy(grid: Grid, gbuffers, stride: int = 2) -> mi.UInt32:
    """Cells holding the G-buffer points of every ``stride``-th pixel (in x
    and y) of every viewer: the cells that 1-bounce shading can read."""
    occ = dr.zeros(mi.UInt32, grid.n_cells)
    s = max(int(stride), 1)
    for gb in gbuffers:
        wx, wy = (gb.width + s - 1) // s, (gb.height + s - 1) // s
        k = dr.arange(mi.UInt32, wx * wy)
        pix = (k // wx) * s * gb.width + (k % wx) * s
        p = dr.gather(mi.Point3f, gb.si.p, pix)
        ok = dr.gather(mi.Bool, gb.valid, pix)
        cell, inside = grid.cell_of(p)
        dr.scatter(occ, mi.UInt32(1), cell, ok & inside)
    return occ


def dilate(occ: mi.UInt32, grid: Grid) -> mi.UInt32:
    """One-cell dilation: a cell is set when it or any of its 26 neighbours is."""
    idx = dr.arange(mi.UInt32, grid.n_cells)
    i = grid.unflat(idx)
    out = mi.UInt32(occ)
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                j = i + mi.Vector3i(dx, dy, dz)
                ok = grid.inside(j)
                out |= dr.gather(mi.UInt32, occ, dr.select(ok, grid.flat(j), 0), ok)
    return out
