"""Sparse point octrees: the common form of the scene and the view hierarchy.

Points are quantised into a cube at ``depth`` levels, keyed by their Morton
code, and every occupied cell of every level becomes a node. Nodes are
stored breadth-first (root first), each level sorted by Morton code, so

* the children of a node are contiguous (``first_child``, ``child_count``),
* the points of a node are contiguous in the Morton-sorted point order
  (``first_point``, ``point_count``),

which is what the vectorised traversal needs (a child is ``first + k``).
Set-up is numpy, vectorised over points and nodes; the only Python loop
runs over the (at most ~12) levels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SQRT3 = float(np.sqrt(3.0))


def _spread3(x: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of ``x`` (uint64) so that there are two zero
    bits between consecutive bits (the Morton interleave)."""
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


def morton(q: np.ndarray) -> np.ndarray:
    """Morton codes of integer cell coordinates ``q`` (N, 3)."""
    return _spread3(q[:, 0]) | (_spread3(q[:, 1]) << np.uint64(1)) | (_spread3(q[:, 2]) << np.uint64(2))


def bounding_cube(points: np.ndarray, pad: float = 1e-3):
    """(corner, edge) of a cube enclosing ``points`` with a relative pad."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    edge = float(max(np.max(hi - lo), 1e-6)) * (1.0 + 2.0 * pad)
    centre = 0.5 * (lo + hi)
    return centre - 0.5 * edge, edge


@dataclass
class Octree:
    """Topology of a sparse octree over points (see module docstring).

    Per node: ``level``, ``code`` (Morton code at its level), ``cell_centre``,
    ``cell_radius`` (radius of the sphere enclosing the cubic cell),
    ``first_child``/``child_count`` (children are contiguous; 0 children for
    a leaf), ``first_point``/``point_count`` (into ``order``), ``parent``.
    ``order`` sorts the input points by leaf; ``leaf_of_point[i]`` is the
    leaf node that holds input point ``i``. ``level_start[l]`` is the first
    node of level ``l`` (``level_start[depth + 1]`` = node count)."""
    depth: int
    corner: np.ndarray
    edge: float
    level: np.ndarray
    code: np.ndarray
    cell_centre: np.ndarray
    cell_radius: np.ndarray
    first_child: np.ndarray
    child_count: np.ndarray
    first_point: np.ndarray
    point_count: np.ndarray
    parent: np.ndarray
    order: np.ndarray
    leaf_of_point: np.ndarray
    level_start: np.ndarray

    @property
    def size(self) -> int:
        return int(self.level.shape[0])

    def reduce(self, values: np.ndarray, op=np.add) -> np.ndarray:
        """Per-node reduction (``np.add``, ``np.minimum``, ``np.maximum``) of
        per-point ``values`` (given in input order) over each node's points:
        the leaves reduce their points, every other level its children
        (contiguous), so the points are read once, not once per level."""
        v = np.asarray(values)[self.order]
        out = np.empty((self.size,) + v.shape[1:], v.dtype)
        a, b = self.level_start[self.depth], self.level_start[self.depth + 1]
        out[a:b] = op.reduceat(v, self.first_point[a:b], axis=0)
        for l in range(self.depth - 1, -1, -1):   # children of a level are contiguous and in order
            a, b = self.level_start[l], self.level_start[l + 1]
            ca = self.level_start[l + 1]
            out[a:b] = op.reduceat(out[ca:self.level_start[l + 2]], self.first_child[a:b] - ca, axis=0)
        return out


def build(points: np.ndarray, depth: int, corner=None, edge=None) -> Octree:
    """Sparse octree of ``depth`` levels below the root over ``points`` (N, 3)."""
    points = np.asarray(points, np.float64)
    if points.shape[0] == 0:
        raise ValueError("octree: no points")
    depth = int(max(depth, 0))
    if corner is None or edge is None:
        corner, edge = bounding_cube(points)
    corner = np.asarray(corner, np.float64)
    res = 1 << depth
    q = np.floor((points - corner) / max(edge, 1e-12) * res).astype(np.int64)
    q = np.clip(q, 0, res - 1)
    code = morton(q)
    order = np.argsort(code, kind="stable")
    code_sorted = code[order]

    # ------------------- occupied cells per level (bottom-up) -------------------
    levels_codes = [None] * (depth + 1)
    levels_first = [None] * (depth + 1)
    c, first = np.unique(code_sorted, return_index=True)
    levels_codes[depth], levels_first[depth] = c, first
    for l in range(depth - 1, -1, -1):
        shifted = levels_codes[l + 1] >> np.uint64(3)
        c, idx = np.unique(shifted, return_index=True)
        levels_codes[l], levels_first[l] = c, levels_first[l + 1][idx]

    # --------------------------- breadth-first layout ---------------------------
    counts = np.array([len(c) for c in levels_codes])
    level_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n = int(level_start[-1])
    level = np.repeat(np.arange(depth + 1), counts).astype(np.int32)
    codes = np.concatenate(levels_codes)
    first_point = np.concatenate(levels_first).astype(np.int64)
    point_count = np.empty(n, np.int64)
    first_child = np.zeros(n, np.int64)
    child_count = np.zeros(n, np.int64)
    parent = np.full(n, -1, np.int64)
    N = points.shape[0]
    for l in range(depth + 1):
        a, b = level_start[l], level_start[l + 1]
        fp = first_point[a:b]
        point_count[a:b] = np.diff(np.append(fp, N))
        if l < depth:
            ca, cb = level_start[l + 1], level_start[l + 2]
            par_codes = codes[ca:cb] >> np.uint64(3)
            # children's parents in the sorted parent list of this level
            pidx = np.searchsorted(codes[a:b], par_codes)
            parent[ca:cb] = a + pidx
            cnt = np.bincount(pidx, minlength=b - a)
            child_count[a:b] = cnt
            first_child[a:b] = ca + np.concatenate([[0], np.cumsum(cnt)[:-1]])

    # ------------------------------ cell geometry ------------------------------
    cells = np.zeros((n, 3), np.int64)
    for l in range(depth + 1):
        a, b = level_start[l], level_start[l + 1]
        cc = codes[a:b]
        for axis in range(3):
            v = np.zeros(b - a, np.int64)
            for bit in range(l):
                v |= (((cc >> np.uint64(3 * bit + axis)) & np.uint64(1)).astype(np.int64) << bit)
            cells[a:b, axis] = v
    cell_edge = edge / (2.0 ** level)
    cell_centre = corner + (cells + 0.5) * cell_edge[:, None]
    cell_radius = 0.5 * SQRT3 * cell_edge

    leaf_of_point = np.empty(N, np.int64)
    la = level_start[depth]
    leaf_sorted = la + np.searchsorted(levels_codes[depth], code_sorted)
    leaf_of_point[order] = leaf_sorted
    return Octree(depth, corner, float(edge), level, codes, cell_centre, cell_radius, first_child,
                  child_count, first_point, point_count, parent, order, leaf_of_point, level_start)
