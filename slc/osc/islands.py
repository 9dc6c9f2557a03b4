"""Islands, their 2D texture spaces and the per-mesh atlas (numpy set-up).

An *island* is a connected group of triangles whose face normals all lie in
a cone of half-angle ``max_angle`` (degrees) around the island's mean
normal, with at most ``max_triangles`` triangles. Each island is projected
orthographically onto the plane of its mean normal (2D axes rotated to the
principal axes of the projected corners, so that the bounding rectangle is
tight) and scaled so that one level-0 texel is ``texel_size`` world units.

Clustering is vectorised (no Python loop over triangles): start with one
cluster per triangle and repeat *mutual-best matching* rounds over the
cluster adjacency graph. In each round every cluster picks its best feasible
neighbour (the edge of smallest score; ties broken by a total order on
edges), and pairs that picked each other merge. The globally best edge is
always mutual, so every round makes progress; the number of clusters
roughly halves per round. A merge is feasible when the merged count is
<= ``max_triangles`` and a conservative bound on the merged normal
deviation is <= ``max_angle``: with ``m`` the merged mean normal,
``dev(A u B) <= max(angle(m, m_A) + dev(A), angle(m, m_B) + dev(B))``
(triangle inequality on the sphere), so the exact bound holds by
construction. Adjacency is over shared edges of the position-welded mesh
(duplicated vertices of OBJ-style meshes are merged by exact position);
non-manifold edges connect consecutive faces around the edge.

Analytic shapes (Mitsuba's ``sphere``, ``disk``, ``cylinder``) have no
triangles: their islands are built from a grid in the shape's own (u, v)
parameter space (:mod:`slc.osc.analytic`).

Nothing here calls xatlas (its Python binding segfaults on large closed
meshes); the packing is a simple shelf packer.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_MAX_ANGLE = 30.0      # degrees: normal cone half-angle around the island mean normal
DEFAULT_MAX_TRIANGLES = 128   # triangles per island
ATLAS_GUTTER = 1              # texels between charts in the per-mesh atlas


# -----------------------------------------------------------------------------
# Clustering
# -----------------------------------------------------------------------------

def face_adjacency(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 2) int64 pairs of faces sharing an edge (vertices welded by exact
    position). Non-manifold edges link consecutive faces around the edge."""
    nf = len(F)
    if nf == 0:
        return np.zeros((0, 2), np.int64)
    V = np.ascontiguousarray(V, dtype=np.float32)
    # weld by exact position: view each row as one void scalar for a fast unique
    row = V.view(np.dtype((np.void, V.dtype.itemsize * 3))).ravel()
    _, inv = np.unique(row, return_inverse=True)
    Fw = inv.reshape(-1)[F.astype(np.int64)]
    nv = int(inv.max()) + 1
    a = Fw.reshape(-1)
    b = Fw[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    face = np.repeat(np.arange(nf, dtype=np.int64), 3)
    keep = lo != hi
    key = lo[keep] * nv + hi[keep]
    face = face[keep]
    order = np.argsort(key, kind="stable")
    ks, fs = key[order], face[order]
    same = ks[1:] == ks[:-1]
    pairs = np.stack([fs[:-1][same], fs[1:][same]], axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return pairs


def _norm(u: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", u, u))


def _angle(u: np.ndarray, v: np.ndarray, nu=None, nv=None) -> np.ndarray:
    """Angle between rows of u and v (radians), robust (atan2 form); 0 when
    either vector is zero."""
    ang = np.arctan2(_norm(np.cross(u, v)), np.einsum("ij,ij->i", u, v))
    nu = _norm(u) if nu is None else nu
    nv = _norm(v) if nv is None else nv
    return np.where((nu == 0) | (nv == 0), 0.0, ang)


def cluster_faces(V: np.ndarray, F: np.ndarray, max_angle: float = DEFAULT_MAX_ANGLE,
                  max_triangles: int = DEFAULT_MAX_TRIANGLES, max_rounds: int = 400,
                  exact: bool = True) -> np.ndarray:
    """Island id (0..n-1, numbered by first face) of every face."""
    nf = len(F)
    if nf == 0:
        return np.zeros(0, np.int64)
    V64 = np.asarray(V, np.float64)
    F64 = np.asarray(F, np.int64)
    p0, p1, p2 = V64[F64[:, 0]], V64[F64[:, 1]], V64[F64[:, 2]]
    S = np.cross(p1 - p0, p2 - p0)            # area-weighted normal sums (2 x area)
    a2 = np.linalg.norm(S, axis=1)
    n_unit = np.where(a2[:, None] > 0, S / np.maximum(a2, 1e-300)[:, None], 0.0)
    SL = a2.copy()                            # |S| per cluster
    cnt = np.ones(nf, np.int64)
    dev = np.zeros(nf, np.float64)            # bound on the max deviation from the cluster mean normal
    label = np.arange(nf, dtype=np.int64)     # face -> cluster (cluster id = a face id)
    E = face_adjacency(V, F)
    theta = math.radians(max_angle)
    for _ in range(max_rounds):
        if len(E) == 0:
            break
        E = np.sort(E, axis=1)
        E = E[E[:, 0] != E[:, 1]]
        if len(E) == 0:
            break
        E = np.unique(E[:, 0] * nf + E[:, 1])
        E = np.stack([E // nf, E % nf], axis=1)
        a, b = E[:, 0], E[:, 1]
        Sa, Sb = S[a], S[b]
        Sm = Sa + Sb
        cm = cnt[a] + cnt[b]
        la, lb, lm = SL[a], SL[b], _norm(Sm)
        devm = np.maximum(_angle(Sm, Sa, lm, la) + dev[a], _angle(Sm, Sb, lm, lb) + dev[b])
        # a pair of opposite normals sums to ~0: the merged mean is meaningless
        degenerate = (lm <= 1e-9 * (la + lb)) & (la > 0) & (lb > 0)
        ok = (cm <= max_triangles) & (devm <= theta * (1 - 1e-9)) & ~degenerate
        E, a, b, Sm, lm, cm, devm = E[ok], a[ok], b[ok], Sm[ok], lm[ok], cm[ok], devm[ok]
        if len(E) == 0:
            break
        score = devm / max(theta, 1e-9) + cm / float(max_triangles)
        m = len(E)
        # total order on edges: (score, edge index); every cluster picks its
        # smallest incident edge; an edge picked by both ends merges
        rank = np.empty(m, np.int64)
        rank[np.lexsort((np.arange(m), score))] = np.arange(m)
        best = np.full(nf, m, np.int64)
        np.minimum.at(best, a, rank)
        np.minimum.at(best, b, rank)
        mutual = (best[a] == rank) & (best[b] == rank)
        if not mutual.any():
            break
        ma, mb = a[mutual], b[mutual]
        S[ma] = Sm[mutual]
        SL[ma] = lm[mutual]
        cnt[ma] = cm[mutual]
        dev[ma] = devm[mutual]
        parent = np.arange(nf, dtype=np.int64)
        parent[mb] = ma
        label = parent[label]
        E = parent[E]
        if exact:
            # tighten the bound of the merged clusters to their exact deviation
            # (O(F) per round); the next merge test is then only one step
            # conservative
            merged = np.zeros(nf, bool)
            merged[ma] = True
            fm = merged[label]
            lf = label[fm]
            ang = _angle(n_unit[fm], S[lf], a2[fm], SL[lf])
            d = np.zeros(nf)
            np.maximum.at(d, lf, ang)
            dev[ma] = d[ma]
    _, isl = np.unique(label, return_inverse=True)
    # number islands by their first face (deterministic, mesh order)
    first_face = np.full(isl.max() + 1, nf, np.int64)
    np.minimum.at(first_face, isl, np.arange(nf))
    rank = np.empty_like(first_face)
    rank[np.argsort(first_face, kind="stable")] = np.arange(len(first_face))
    return rank[isl]


def face_normals(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals (zero for degenerate faces) and twice the areas."""
    V64 = np.asarray(V, np.float64)
    F64 = np.asarray(F, np.int64)
    c = np.cross(V64[F64[:, 1]] - V64[F64[:, 0]], V64[F64[:, 2]] - V64[F64[:, 0]])
    a2 = np.linalg.norm(c, axis=1)
    n = np.where(a2[:, None] > 0, c / np.maximum(a2, 1e-300)[:, None], 0.0)
    return n, a2


def island_deviation(V, F, face_island) -> tuple[np.ndarray, np.ndarray]:
    """Exact max angle (degrees) between a face normal and its island's mean
    (area-weighted) normal, per island, and the unit mean normals."""
    n, a2 = face_normals(V, F)
    ni = int(face_island.max()) + 1 if len(face_island) else 0
    S = np.zeros((ni, 3))
    np.add.at(S, face_island, n * a2[:, None])
    L = np.linalg.norm(S, axis=1, keepdims=True)
    mean = np.where(L > 0, S / np.maximum(L, 1e-300), np.array([0.0, 0.0, 1.0]))
    ang = _angle(n, mean[face_island])
    ang = np.where(a2 > 0, ang, 0.0)
    dev = np.zeros(ni)
    np.maximum.at(dev, face_island, ang)
    return np.degrees(dev), mean


# -----------------------------------------------------------------------------
# Texture spaces and atlas
# -----------------------------------------------------------------------------

def _onb(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Branchless orthonormal basis (Duff et al. 2017) per row of unit n."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bb = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bb


def shelf_pack(sizes: np.ndarray, gutter: int = ATLAS_GUTTER) -> tuple[np.ndarray, tuple[int, int]]:
    """Place integer rectangles ``sizes`` (n, 2: width, height) on shelves.
    Returns offsets (n, 2) and the atlas size (width, height). Rectangles are
    sorted by decreasing height; the atlas width is about the square root of
    the total padded area (at least the widest rectangle)."""
    n = len(sizes)
    if n == 0:
        return np.zeros((0, 2), np.int64), (0, 0)
    w = sizes[:, 0].astype(np.int64) + gutter
    h = sizes[:, 1].astype(np.int64) + gutter
    W = int(max(w.max(), math.ceil(math.sqrt(float((w * h).sum())) * 1.05)))
    order = np.lexsort((np.arange(n), -h))
    off = np.zeros((n, 2), np.int64)
    x = y = shelf_h = 0
    wl, hl = w.tolist(), h.tolist()
    for i in order.tolist():
        if x + wl[i] > W:
            y += shelf_h
            x = shelf_h = 0
        off[i] = (x, y)
        x += wl[i]
        shelf_h = max(shelf_h, hl[i])
    return off, (W, y + shelf_h)


@dataclass
class MeshIslands:
    """Islands of one mesh and their texture spaces (all numpy).

    ``corner_uv`` (F, 3, 2): island-local level-0 texel coordinates of each
    triangle corner (a texel (i, j) covers [i, i+1) x [j, j+1)).
    ``corner_atlas`` (F, 3, 2): the same in the mesh's atlas (texels), i.e.
    ``corner_uv + atlas_offset[face_island]``; divide by ``atlas_size`` for
    [0, 1] texture coordinates.
    ``dims`` (I, 2): level-0 texel extent of each island.
    """
    shape_index: int
    face_island: np.ndarray      # (F,) local island id
    normal: np.ndarray           # (I, 3) unit mean normal
    axes: np.ndarray             # (I, 2, 3) 2D axes of the island's plane (world)
    origin: np.ndarray           # (I, 2) projected coordinate (world units) of local texel (0, 0)
    dims: np.ndarray             # (I, 2) int64 level-0 texels
    corner_uv: np.ndarray        # (F, 3, 2) float64
    atlas_offset: np.ndarray     # (I, 2) int64
    atlas_size: tuple
    max_deviation: np.ndarray    # (I,) degrees, exact
    counts: np.ndarray           # (I,) triangles per island

    @property
    def n_islands(self) -> int:
        return len(self.dims)

    @property
    def corner_atlas(self) -> np.ndarray:
        return self.corner_uv + self.atlas_offset[self.face_island][:, None, :]


def build_mesh_islands(V: np.ndarray, F: np.ndarray, texel_size: float, shape_index: int = 0,
                       max_angle: float = DEFAULT_MAX_ANGLE,
                       max_triangles: int = DEFAULT_MAX_TRIANGLES) -> MeshIslands:
    V = np.asarray(V, np.float64).reshape(-1, 3)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    fi = cluster_faces(V.astype(np.float32), F, max_angle, max_triangles)
    ni = int(fi.max()) + 1 if len(fi) else 0
    dev, mean = island_deviation(V, F, fi)
    t, b = _onb(mean)
    P = V[F]                                   # (F, 3, 3)
    tt, bb = t[fi], b[fi]
    x = np.einsum("fkj,fj->fk", P, tt)         # (F, 3) projected coordinates (world units)
    y = np.einsum("fkj,fj->fk", P, bb)
    # rotate each island's 2D axes to the principal axes of its corners
    w = np.ones_like(x)
    cnt = np.bincount(fi, weights=w.sum(1), minlength=ni)
    mx = np.bincount(fi, weights=x.sum(1), minlength=ni) / cnt
    my = np.bincount(fi, weights=y.sum(1), minlength=ni) / cnt
    dx, dy = x - mx[fi][:, None], y - my[fi][:, None]
    cxx = np.bincount(fi, weights=(dx * dx).sum(1), minlength=ni)
    cyy = np.bincount(fi, weights=(dy * dy).sum(1), minlength=ni)
    cxy = np.bincount(fi, weights=(dx * dy).sum(1), minlength=ni)
    phi = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    c, s = np.cos(phi), np.sin(phi)
    t2 = c[:, None] * t + s[:, None] * b
    b2 = -s[:, None] * t + c[:, None] * b
    x = np.einsum("fkj,fj->fk", P, t2[fi])
    y = np.einsum("fkj,fj->fk", P, b2[fi])
    xmin = np.full(ni, np.inf)
    ymin = np.full(ni, np.inf)
    xmax = np.full(ni, -np.inf)
    ymax = np.full(ni, -np.inf)
    np.minimum.at(xmin, fi, x.min(1))
    np.minimum.at(ymin, fi, y.min(1))
    np.maximum.at(xmax, fi, x.max(1))
    np.maximum.at(ymax, fi, y.max(1))
    ts = float(texel_size)
    u = (x - xmin[fi][:, None]) / ts
    v = (y - ymin[fi][:, None]) / ts
    dims = np.stack([np.maximum(1, np.ceil((xmax - xmin) / ts - 1e-9)),
                     np.maximum(1, np.ceil((ymax - ymin) / ts - 1e-9))], axis=1).astype(np.int64)
    corner_uv = np.stack([u, v], axis=2)
    off, size = shelf_pack(dims)
    return MeshIslands(shape_index=shape_index, face_island=fi, normal=mean,
                       axes=np.stack([t2, b2], axis=1), origin=np.stack([xmin, ymin], axis=1),
                       dims=dims, corner_uv=corner_uv, atlas_offset=off, atlas_size=size,
                       max_deviation=dev, counts=np.bincount(fi, minlength=ni))


def charts_overlap(mi_: MeshIslands) -> bool:
    """True when two islands' atlas rectangles overlap (should never be)."""
    off, d = mi_.atlas_offset, mi_.dims
    n = len(d)
    if n < 2:
        return False
    # sweep: sort by x, compare with candidates whose x-range intersects
    order = np.argsort(off[:, 0], kind="stable")
    x0, x1 = off[order, 0], off[order, 0] + d[order, 0]
    y0, y1 = off[order, 1], off[order, 1] + d[order, 1]
    for k in range(n):
        j = np.searchsorted(x0, x1[k], side="left")
        if j > k + 1:
            sl = slice(k + 1, j)
            if np.any((y0[sl] < y1[k]) & (y0[k] < y1[sl]) & (x0[sl] < x1[k])):
                return True
    return False
