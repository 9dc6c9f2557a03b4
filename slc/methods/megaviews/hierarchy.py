"""The two hierarchies of MegaViews (Sec. 3.1): scene and views.

Both are sparse octrees (:mod:`.octree`) whose node attributes live in
Dr.Jit arrays indexed by node id, so that the traversal gathers them per
scene-view pair.

Scene node ``s_i``: average colour (diffuse reflectance of the BSDF at the
sample points), position (mean sample point), normal (mean) and normal-cone
half angle, and a bounding sphere enclosing the cubic voxel.

View node ``v_j = (p_j, n_j, theta_j, phi_j)``: centre of projection ``p_j``
(centre of the views' bounding box, also the centre of the bounding
sphere), view direction ``n_j`` with the half angle ``theta_j`` of the cone
of the children's directions, and the half field of view ``phi_j``
(``pi`` for omnidirectional views, ``pi/2`` for VPL hemispheres). A single
view has a zero bounding radius.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.methods.megaviews import octree as oct

SCENE_DEPTH = 7       # CPU default (the paper uses 11 levels on a GPU)
VIEW_DEPTH = 7
EMPTY_COUNT = 0


def _f(a):
    return mi.Float(aligned(a, np.float32))


def _p3(a):
    a = np.asarray(a, np.float32)
    return mi.Point3f(_f(a[:, 0]), _f(a[:, 1]), _f(a[:, 2]))


def as_u32(a):
    return mi.UInt32(aligned(a, np.uint32))


def as_bool(a):
    return mi.Bool(aligned(a, np.bool_))


def to_np3(v, k: int) -> np.ndarray:
    """(k, 3) numpy copy of a 3-vector Dr.Jit array (broadcast if width 1)."""
    cols = [np.broadcast_to(np.array(v[i], np.float64).ravel(), (k,)) for i in range(3)]
    return np.stack(cols, axis=1)


def _cone(dirs: np.ndarray, tree: oct.Octree, weights=None):
    """Per-node mean direction and half angle of the cone around it
    (``atan2(|a x b|, a.b)``, robust for near-parallel directions)."""
    w = np.ones(len(dirs)) if weights is None else weights
    s = tree.reduce(dirs * w[:, None])
    nrm = np.linalg.norm(s, axis=1, keepdims=True)
    mean = np.where(nrm > 1e-12, s / np.maximum(nrm, 1e-12), np.array([[0.0, 0.0, 1.0]]))
    # angle of every point to the mean of each of its ancestors: one pass per level
    half = np.zeros(tree.size)
    node_of = tree.leaf_of_point.copy()
    for _ in range(tree.depth + 1):
        m = mean[node_of]
        ang = np.arctan2(np.linalg.norm(np.cross(dirs, m), axis=1), np.sum(dirs * m, axis=1))
        np.maximum.at(half, node_of, ang)
        node_of = np.where(tree.parent[node_of] >= 0, tree.parent[node_of], node_of)
    return mean, np.minimum(half, math.pi)


# -----------------------------------------------------------------------------
# Scene hierarchy
# -----------------------------------------------------------------------------

def sample_surface(mi_scene: mi.Scene, n_points: int, seed: int = 1):
    """Area-uniform points on all non-emitting shapes: (P, N, albedo, area per
    point) as numpy arrays. Albedo is ``bsdf.eval_diffuse_reflectance``."""
    shapes = [s for s in mi_scene.shapes() if not s.is_emitter()]
    areas = np.array([float(dr.slice(s.surface_area())) if dr.width(s.surface_area()) else 0.0 for s in shapes])
    total = float(areas.sum())
    if total <= 0.0:
        raise ValueError("scene has no surface area")
    rs = np.random.default_rng(seed)
    P, N, A = [], [], []
    for s, a in zip(shapes, areas):
        k = int(max(8, round(n_points * a / total)))
        u = rs.random((k, 2))
        ps = s.sample_position(0.0, mi.Point2f(u[:, 0].astype(np.float32), u[:, 1].astype(np.float32)))
        si = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f))
        si.wi = mi.Vector3f(0.0, 0.0, 1.0)
        si.sh_frame = mi.Frame3f(si.n)
        alb = s.bsdf().eval_diffuse_reflectance(si)
        P.append(to_np3(ps.p, k))
        N.append(to_np3(ps.n, k))
        A.append(to_np3(mi.Color3f(alb), k))
    P, N, A = np.concatenate(P), np.concatenate(N), np.concatenate(A)
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    return P, N, np.clip(A, 0.0, 1.0), total / max(len(P), 1)


class SceneHierarchy:
    """Sparse voxel octree of the scene's surfaces (Sec. 3.1).

    Built once from ``points_per_leaf`` area-uniform samples per expected
    leaf voxel on every non-emitting triangle mesh. Parameters: ``depth``
    (levels below the root, default 7 on a CPU; the paper uses 11).
    Dr.Jit node arrays: ``centre``/``radius`` (bounding sphere of the voxel),
    ``pos`` (mean surface point), ``normal``/``cone`` (normal cone),
    ``colour`` (mean diffuse reflectance), ``first_child``/``child_count``.
    """

    def __init__(self, mi_scene: mi.Scene, depth: int = SCENE_DEPTH, points_per_leaf: float = 3.0,
                 seed: int = 1, max_points: int = 8_000_000):
        self.depth = int(depth)
        bb = mi_scene.bbox()
        shapes = [s for s in mi_scene.shapes() if not s.is_emitter()]
        area = sum(float(dr.slice(s.surface_area())) for s in shapes)
        lo = np.array([min(float(s.bbox().min[i]) for s in shapes) for i in range(3)]) if shapes else np.array(bb.min)
        hi = np.array([max(float(s.bbox().max[i]) for s in shapes) for i in range(3)]) if shapes else np.array(bb.max)
        edge = float(np.max(hi - lo)) * 1.002
        corner = 0.5 * (lo + hi) - 0.5 * edge
        leaf_edge = edge / (1 << self.depth)
        n_pts = int(min(max_points, max(20_000, points_per_leaf * area / max(leaf_edge ** 2, 1e-12))))
        P, N, A, self.area_per_point = sample_surface(mi_scene, n_pts, seed)
        t = oct.build(P, self.depth, corner, edge)
        self.tree = t
        cnt = t.point_count.astype(np.float64)[:, None]
        pos = t.reduce(P) / np.maximum(cnt, 1.0)
        col = t.reduce(A) / np.maximum(cnt, 1.0)
        nrm, cone = _cone(N, t)
        self.points, self.normals_np = P, N
        self.pos_np, self.colour_np, self.radius_np = pos, col, t.cell_radius
        # --------------------------- Dr.Jit node arrays ---------------------------
        self.centre = _p3(t.cell_centre)
        self.radius = _f(t.cell_radius)
        self.pos = _p3(pos)
        self.normal = _p3(nrm)
        self.cone = _f(cone)
        self.colour = mi.Color3f(*[_f(col[:, i]) for i in range(3)])
        self.first_child = as_u32(t.first_child)
        self.child_count = as_u32(t.child_count)
        self.leaf_radius = float(t.cell_radius[-1])

    @property
    def size(self) -> int:
        return self.tree.size

    @property
    def leaves(self) -> np.ndarray:
        return np.arange(self.tree.level_start[self.depth], self.tree.size)

    def memory_bytes(self) -> int:
        """512 bits per node (paper's accounting: 512 non-leaf / 256 leaf)."""
        n_leaf = self.tree.size - int(self.tree.level_start[self.depth])
        return 64 * (self.tree.size - n_leaf) + 32 * n_leaf


# -----------------------------------------------------------------------------
# View hierarchy
# -----------------------------------------------------------------------------

class ViewHierarchy:
    """Views grouped in an octree, rebuilt every frame (Sec. 3.1, 4).

    ``positions`` (N, 3), ``directions`` (N, 3) unit, ``phi`` the half field
    of view of all views (``pi/2`` hemispherical VPLs, ``pi`` omnidirectional
    particles). ``depth`` levels below the root (default 7). With
    ``flat=True`` every view is its own root leaf (no view hierarchy: the
    ManyLoDs and brute-force layouts).

    Node arrays (Dr.Jit): ``centre`` (p_j), ``radius`` (bounding sphere of
    the contained view positions, 0 for a single view), ``dir`` (n_j),
    ``theta``, ``phi``, ``first_child``/``child_count``, ``n_views``;
    ``leaf_of_view`` maps every input view to its leaf node (whose map it
    reads). ``roots`` are the nodes the traversal starts from.
    """

    def __init__(self, positions, directions, phi: float = math.pi / 2, depth: int = VIEW_DEPTH,
                 flat: bool = False, corner=None, edge=None):
        P = np.asarray(positions, np.float64)
        D = np.asarray(directions, np.float64)
        D = D / np.maximum(np.linalg.norm(D, axis=1, keepdims=True), 1e-12)
        self.n = len(P)
        self.phi_value = float(phi)
        self.flat = bool(flat)
        self.positions_np, self.directions_np = P, D
        if flat:
            n = self.n
            centre, radius, dirs, theta = P, np.zeros(n), D, np.zeros(n)
            first_child, child_count = np.zeros(n, np.int64), np.zeros(n, np.int64)
            n_views, level = np.ones(n, np.int64), np.zeros(n, np.int64)
            self.leaf_of_view_np = np.arange(n)
            self.roots_np = np.arange(n)
            self.parent_np = np.full(n, -1)
            self.level_start = np.array([0, n])
            self.depth = 0
        else:
            t = oct.build(P, depth, corner, edge)
            lo = t.reduce(P, np.minimum)
            hi = t.reduce(P, np.maximum)
            centre = 0.5 * (lo + hi)
            radius = 0.5 * np.linalg.norm(hi - lo, axis=1)
            dirs, theta = _cone(D, t)
            first_child, child_count = t.first_child, t.child_count
            n_views, level = t.point_count, t.level
            self.leaf_of_view_np = t.leaf_of_point
            self.roots_np = np.array([0])
            self.parent_np = t.parent
            self.level_start = t.level_start
            self.depth = t.depth
            self.tree = t
        self.size = len(centre)
        self.centre_np, self.radius_np, self.level_np = centre, radius, level
        self.n_views_np, self.child_count_np = n_views, child_count
        # --------------------------- Dr.Jit node arrays ---------------------------
        self.centre = _p3(centre)
        self.radius = _f(radius)
        self.dir = _p3(dirs)
        self.theta = _f(theta)
        self.phi = _f(np.full(len(centre), phi))
        self.first_child = as_u32(first_child)
        self.child_count = as_u32(child_count)
        self.n_views = as_u32(n_views)
        self.parent = as_u32(np.maximum(self.parent_np, 0))
        self.leaf_of_view = as_u32(self.leaf_of_view_np)

    def memory_bytes(self) -> int:
        """256 bits per node (ManyLoDs: 256 bits per view)."""
        return 32 * self.size
