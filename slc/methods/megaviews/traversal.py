r"""Concurrent scene-view hierarchy traversal (Sec. 3.2), and the baselines.

``render_maps(scene_h, view_h, R)`` renders one dual-paraboloid depth map
per view node. The pair queue ``(s_i, v_j)`` starts at the roots and is
processed breadth-first, one Dr.Jit kernel set per level; every pair is,
in one step, either

1. **culled** (Fig. 4/5): with ``vs = c_s - p_v``, ``alpha = angle(vs, n_v)``
   and ``psi = theta_v + phi_v < pi``, the pair is culled when
   ``alpha > psi`` and ``f_s = |vs| sin(min(alpha - psi, pi/2)) > r_s + r_v``
   (distance to the cone of directions, enlarged by the view-node radius:
   every child view lies within ``r_v`` of ``p_v``, so this never culls
   what a child sees);
2. **rendered shared** (Fig. 6): the conservative projected size
   (:func:`.paraboloid.projected_size`, distance shortened by ``r_v``) is
   below one texel and ``r_v <= r_s``; the node's mean point is splatted
   (``scatter_reduce`` min of the distance to ``p_v``) into the map of
   ``v_j``, shared by all its views. Pairs of two leaves are always
   rendered; when they project to more than a texel they are splatted into
   a coarser mip level (multi-pixel filling, mipmap splatting,
   pushed down afterwards; the level is chosen from the voxel's half edge
   seen from ``p_v``, rounded down);
3. **subdivided** (Fig. 8): the view node if the children of ``s_i`` are
   smaller than ``v_j`` (or ``s_i`` is a leaf), else the scene node; the
   children of the chosen node are paired with the other node
   (``dr.compress`` compacts the queue).

Multi-pass (Sec. 4.2), ``split``:

* ``"view"`` (default, the paper's): the work is split at the view
  hierarchy. Passes start from ``(s_0, v)`` for view nodes ``v`` of the
  multi-pass level ``split_level``; with ``split_level=None`` the level is
  found as the paper does, starting from the view root: a pass whose pair
  queue would exceed ``budget_pairs`` is stopped and replaced by one pass
  per child of its view node ("split the children again until the pair
  queue fits"). What a stopped pass already rendered stays (every render
  is valid for all views of its view node; min-depth splats are
  idempotent), the pairs it processed are counted in ``pairs`` and
  ``wasted_pairs``. Shared rendering above the multi-pass level is lost,
  as in the paper. A pass from a view leaf that still exceeds the budget
  falls back to chunking.
* ``"chunk"``: the subdivided pairs of a level are cut into chunks that fit
  and processed depth-first: exactly the same pairs and maps as one pass.

``scene_start="leaves"`` is the view-hierarchy-only traversal of Sec. 4.1
(no scene hierarchy: every scene leaf is paired with the view root).

Fusion (Sec. 3.2, Image Queries): top-down over the view levels every
child map takes the minimum of its own depth and its parent's, whose depth
is re-measured from the child's centre (the paper's rectification).
Direct queries without fusion walk the leaf's ancestors instead. The maps, push, fusion and the
queries are in :mod:`slc.methods.megaviews.maps`.

Baselines on the same kernels: **ManyLoDs** [HREB11] is the same traversal
with a flat view set (every view its own leaf, radius 0), so it only ever
subdivides the scene node, one step per iteration; **brute force** pairs
every scene leaf with every view (frustum culling per pair, multi-pixel
filling for leaves larger than a texel), chunked by the budget.
"""
from __future__ import annotations

import math
from contextlib import nullcontext
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods.megaviews import paraboloid as pb
from slc.methods.megaviews.hierarchy import SceneHierarchy, ViewHierarchy, as_u32
from slc.methods.megaviews.maps import Maps, TraversalStats, fuse, push

INV_SQRT3 = 1.0 / math.sqrt(3.0)  # sphere radius -> half edge of the cubic voxel
DEFAULT_BUDGET = 1 << 25  # pairs (256 MB of pair queue at 8 bytes per pair; ~2 GB of Dr.Jit work arrays)


# -----------------------------------------------------------------------------
# Pair classification (one step)
# -----------------------------------------------------------------------------

def cull_test(cs, rs, pv, rv, nv, psi):
    """Conservative frustum culling of scene spheres against view nodes (Fig. 4)."""
    vs = cs - pv
    d = dr.norm(vs)
    alpha = dr.atan2(dr.norm(dr.cross(vs, nv)), dr.dot(vs, nv))
    fs = d * dr.sin(dr.minimum(alpha - psi, 0.5 * math.pi))
    return (psi < math.pi) & (alpha > psi) & (fs > rs + rv)


def _splat(depth, layout: pb.Layout, slot, p, pv, r_surf, active, multi_pixel: bool = True):
    """Splat point ``p`` (a node of surface half-extent ``r_surf``) into the
    map ``slot`` (centre ``pv``): level 0 when it projects below a texel,
    else (multi-pixel filling) mip level floor(log2 size) of its projected
    size seen from ``pv``, capped so that a splat never covers more than a
    quarter of a face side. Returns the mip level used."""
    vs = p - pv
    dist = dr.norm(vs)
    if multi_pixel:
        size = pb.projected_size(vs, r_surf, mi.Float(0.0), layout.R)
        top = max(layout.levels - 3, 0)
        m = dr.clip(dr.floor(dr.log2(dr.maximum(size, 1.0))), 0.0, float(top))
        m = dr.select(size >= 1e8, 0.0, m)  # view inside the node's extent: a point splat
        mu = mi.UInt32(m)
    else:
        mu = dr.zeros(mi.UInt32, dr.width(dist))
    Rm = mi.UInt32(layout.R) >> mu
    face, tx, ty = pb.texel(vs, Rm)
    off = dr.gather(mi.UInt32, mi.UInt32(layout.offset[:-1]), mu)
    idx = slot * layout.texels + off + (face * Rm + ty) * Rm + tx
    # Direct atomics: the LLVM default (Expand, below dr.expand_threshold() texels) bakes the map
    # array's size into the kernel (one build per view count) and keeps a copy of the maps per core
    dr.scatter_reduce(dr.ReduceOp.Min, depth, dist, idx, active, mode=dr.ReduceMode.Direct)
    return mu


class Traversal:
    """Runs the concurrent traversal of ``scene_h`` x ``view_h`` into maps of
    resolution ``R`` (see module docstring). Parameters: ``cull`` (default
    True), ``budget_pairs`` (multi-pass threshold, default 32M pairs),
    ``record`` (keep every processed pair, for tests), ``multi_pixel``
    (mip splats of leaf pairs larger than a texel, default True), ``split``
    (``"view"``, default, or ``"chunk"``), ``split_level`` (None: found from
    the budget; else the fixed multi-pass level), ``scene_start``
    (``"root"``, default, or ``"leaves"``: the view-only traversal)."""

    def __init__(self, scene_h: SceneHierarchy, view_h: ViewHierarchy, R: int = 16, cull: bool = True,
                 budget_pairs: int = DEFAULT_BUDGET, record: bool = False, multi_pixel: bool = True,
                 split: str = "view", split_level: int | None = None, scene_start: str = "root"):
        if split not in ("view", "chunk"):
            raise ValueError(f"split must be 'view' or 'chunk', got {split!r}")
        if scene_start not in ("root", "leaves"):
            raise ValueError(f"scene_start must be 'root' or 'leaves', got {scene_start!r}")
        self.S, self.V = scene_h, view_h
        self.multi_pixel = bool(multi_pixel)
        self.layout = pb.Layout(R)
        self.cull = bool(cull)
        self.budget = int(max(budget_pairs, 64))
        self.record = [] if record else None
        self.split = "chunk" if view_h.flat else split
        self.split_level = split_level
        self.scene_start = scene_start

    # ---------------- one level: classify, render, collect subdivisions ----------------
    def _step(self, depth, qs, qv, st: TraversalStats):
        S, V, lay = self.S, self.V, self.layout
        cs = dr.gather(mi.Point3f, S.centre, qs)
        rs = dr.gather(mi.Float, S.radius, qs)
        ps = dr.gather(mi.Point3f, S.pos, qs)
        s_cnt = dr.gather(mi.UInt32, S.child_count, qs)
        pv = dr.gather(mi.Point3f, V.centre, qv)
        rv = dr.gather(mi.Float, V.radius, qv)
        nv = mi.Vector3f(dr.gather(mi.Point3f, V.dir, qv))
        psi = dr.gather(mi.Float, V.theta, qv) + dr.gather(mi.Float, V.phi, qv)
        v_cnt = dr.gather(mi.UInt32, V.child_count, qv)

        # ------------------------------- Culling -------------------------------
        culled = cull_test(cs, rs, pv, rv, nv, psi) if self.cull else dr.zeros(mi.Bool, dr.width(qs))

        # --------------------------- Shared rendering ---------------------------
        size = pb.projected_size(cs - pv, rs, rv, lay.R)
        s_leaf, v_leaf = s_cnt == 0, v_cnt == 0
        render = ~culled & (((size < 1.0) & (rv <= rs)) | (s_leaf & v_leaf))
        mu = _splat(depth, lay, qv, ps, pv, rs * INV_SQRT3, render, self.multi_pixel)

        # ------------------------------ Subdivision ------------------------------
        subdiv = ~culled & ~render
        sub_v = ~v_leaf & (s_leaf | (0.5 * rs < rv))
        # one kernel classifies and splats; the counts then reduce its stored outputs (counting the
        # unevaluated masks made Dr.Jit recompute the whole classification once per count)
        share = dr.select(render, dr.gather(mi.UInt32, V.n_views, qv), 0)
        multi = render & (mu > 0)
        dr.eval(depth, culled, render, multi, share, subdiv, sub_v)
        c_cull = dr.count(culled)
        c_rend = dr.count(render)
        c_multi = dr.count(multi)
        c_share = dr.sum(mi.UInt64(share))
        c_sub = dr.count(subdiv)
        dr.eval(c_cull, c_rend, c_multi, c_share, c_sub)
        st.culled += int(c_cull[0])
        st.rendered += int(c_rend[0])
        st.multi_pixel += int(c_multi[0])
        st.shared_views += int(c_share[0])
        if int(c_sub[0]) == 0:
            return None
        sel = dr.compress(subdiv)
        ss, sv, sub = dr.gather(mi.UInt32, qs, sel), dr.gather(mi.UInt32, qv, sel), dr.gather(mi.Bool, sub_v, sel)
        first = dr.select(sub, dr.gather(mi.UInt32, V.first_child, sv), dr.gather(mi.UInt32, S.first_child, ss))
        cnt = dr.select(sub, dr.gather(mi.UInt32, V.child_count, sv), dr.gather(mi.UInt32, S.child_count, ss))
        dr.eval(ss, sv, sub, first, cnt)
        return ss, sv, sub, first, cnt

    @staticmethod
    def _expand(ss, sv, sub, first, cnt):
        m = dr.width(ss)
        j = dr.arange(mi.UInt32, 8 * m)
        p, k = j >> 3, j & 7
        valid = k < dr.gather(mi.UInt32, cnt, p)
        sel = dr.compress(valid)
        p, k = dr.gather(mi.UInt32, p, sel), dr.gather(mi.UInt32, k, sel)
        child = dr.gather(mi.UInt32, first, p) + k
        is_v = dr.gather(mi.Bool, sub, p)
        ns = dr.select(is_v, dr.gather(mi.UInt32, ss, p), child)
        nv = dr.select(is_v, child, dr.gather(mi.UInt32, sv, p))
        dr.eval(ns, nv)
        return ns, nv

    def _start(self, views: np.ndarray):
        """Initial pairs of a pass: (scene root or every scene leaf) x ``views``."""
        S = self.S
        if self.scene_start == "leaves":
            sn = np.arange(int(S.tree.level_start[S.depth]), S.size, dtype=np.uint32)
        else:
            sn = np.zeros(1, np.uint32)
        qs = np.repeat(sn[None, :], len(views), 0).ravel()
        qv = np.repeat(np.asarray(views, np.uint32), len(sn))
        return qs, qv

    def run(self) -> Maps:
        V, lay = self.V, self.layout
        st = TraversalStats(passes=0)
        depth = dr.full(mi.Float, pb.EMPTY, V.size * lay.texels)
        if self.split == "chunk" or V.flat:
            self._run_pass(depth, np.asarray(V.roots_np), st, abort=False)
        else:
            lvl = 0 if self.split_level is None else int(min(self.split_level, V.depth))
            a, b = int(V.level_start[lvl]), int(V.level_start[lvl + 1])
            todo = list(range(b - 1, a - 1, -1))   # a stack of pass roots (view nodes)
            cc, fc = V.child_count_np, V.tree.first_child
            floor = lvl   # the multi-pass level: raised when a pass does not fit
            while todo:
                v = todo.pop()
                lv = int(V.level_np[v])
                can_split = self.split_level is None and cc[v] > 0
                if can_split and lv < floor:   # a pass at this level did not fit: start deeper
                    todo.extend(range(int(fc[v] + cc[v]) - 1, int(fc[v]) - 1, -1))
                    continue
                st.split_level = max(st.split_level, lv)
                done = self._run_pass(depth, np.array([v]), st, abort=can_split)
                if not done:   # over budget: one pass per child of v (Sec. 4.2)
                    floor = max(floor, lv + 1)
                    todo.extend(range(int(fc[v] + cc[v]) - 1, int(fc[v]) - 1, -1))
        st.passes = max(st.passes, 1)
        return Maps(lay, depth, V.size, V, stats=st, record=self.record)

    def _run_pass(self, depth, views: np.ndarray, st: TraversalStats, abort: bool) -> bool:
        """One pass from ``(scene start, views)``. With ``abort`` it stops
        (returns False) as soon as a level's pairs would exceed the budget;
        otherwise levels over the budget are chunked. True when finished."""
        qs_np, qv_np = self._start(views)
        n0 = len(qs_np)
        st.passes += 1
        # work stack: ("queue", qs, qv) or ("expand", ss, sv, sub, first, cnt)
        chunks = [(a, min(a + self.budget, n0)) for a in range(0, n0, self.budget)]
        stack = []
        for a, b in reversed(chunks):
            qs, qv = as_u32(qs_np[a:b]), as_u32(qv_np[a:b])   # aligned: see hierarchy.aligned
            dr.make_opaque(qs, qv)   # a one-pair start (a pass root) must not become a kernel literal
            stack.append(("queue", qs, qv))
        live, processed = n0, 0
        while stack:
            item = stack.pop()
            if item[0] == "expand":
                _, ss, sv, sub, first, cnt = item
                live -= dr.width(ss)
                qs, qv = self._expand(ss, sv, sub, first, cnt)
                live += dr.width(qs)
            else:
                _, qs, qv = item
            st.peak_pairs = max(st.peak_pairs, live)
            n = dr.width(qs)
            st.pairs += n
            processed += n
            st.levels += 1
            if self.record is not None:
                self.record.append(np.stack([np.array(qs, np.int64), np.array(qv, np.int64)], 1))
            out = self._step(depth, qs, qv, st)
            live -= n
            if out is None:
                continue
            ss, sv, sub, first, cnt = out
            m = dr.width(ss)
            pre = np.cumsum(np.array(cnt, np.int64))
            total = int(pre[-1])
            if live + m + total > self.budget and abort:
                st.wasted_pairs += processed
                return False
            live += m
            st.peak_pairs = max(st.peak_pairs, live + total)
            if total <= self.budget:
                stack.append(("expand", ss, sv, sub, first, cnt))
                continue
            # ------------------- chunking: split a level that does not fit -------------------
            k = int(math.ceil(total / self.budget))
            bounds = np.searchsorted(pre, np.arange(1, k) * (total / k))
            bounds = np.unique(np.concatenate([[0], bounds, [m]]))
            parts = []
            for a, b in zip(bounds[:-1], bounds[1:]):
                if b <= a:
                    continue
                r = dr.arange(mi.UInt32, int(a), int(b))
                parts.append(("expand",) + tuple(dr.gather(type(x), x, r) for x in (ss, sv, sub, first, cnt)))
            st.passes += len(parts) - 1
            stack.extend(reversed(parts))
        return True


# -----------------------------------------------------------------------------
# Brute force: every scene leaf into every view
# -----------------------------------------------------------------------------

def brute_force(scene_h: SceneHierarchy, view_h: ViewHierarchy, R: int = 16, cull: bool = True,
                budget_pairs: int = DEFAULT_BUDGET, multi_pixel: bool = True) -> Maps:
    """Every scene leaf splatted into every (flat) view's map, with exact
    per-view frustum culling and multi-pixel filling (mip splats)."""
    if not view_h.flat:
        raise ValueError("brute force needs a flat view set")
    S, V = scene_h, view_h
    lay = pb.Layout(R)
    st = TraversalStats(passes=0)
    depth = dr.full(mi.Float, pb.EMPTY, V.size * lay.texels)
    leaf0 = int(S.tree.level_start[S.depth])
    nl = S.size - leaf0
    per = max(1, min(V.size, budget_pairs // max(nl, 1)))
    for v0 in range(0, V.size, per):
        nv_ = min(per, V.size - v0)
        j = dr.arange(mi.UInt32, nl * nv_)
        nl_ = dr.opaque(mi.UInt32, nl)   # opaque: one kernel for every chunk and scene
        qs = dr.opaque(mi.UInt32, leaf0) + j % nl_
        qv = dr.opaque(mi.UInt32, v0) + j // nl_
        cs = dr.gather(mi.Point3f, S.centre, qs)
        rs = dr.gather(mi.Float, S.radius, qs)
        ps = dr.gather(mi.Point3f, S.pos, qs)
        pv = dr.gather(mi.Point3f, V.centre, qv)
        nvd = mi.Vector3f(dr.gather(mi.Point3f, V.dir, qv))
        psi = dr.gather(mi.Float, V.phi, qv)
        culled = cull_test(cs, rs, pv, 0.0, nvd, psi) if cull else dr.zeros(mi.Bool, dr.width(qs))
        mu = _splat(depth, lay, qv, ps, pv, rs * INV_SQRT3, ~culled, multi_pixel)
        c_multi, c_cull = dr.count(~culled & (mu > 0)), dr.count(culled)
        dr.eval(depth, c_multi, c_cull)
        st.pairs += nl * nv_
        st.culled += int(c_cull[0])
        st.rendered += nl * nv_ - int(c_cull[0])
        st.multi_pixel += int(c_multi[0])
        st.peak_pairs = max(st.peak_pairs, nl * nv_)
        st.passes += 1
    st.shared_views = st.rendered
    st.levels = 1
    return Maps(lay, depth, V.size, V, stats=st)


def render_maps(scene_h: SceneHierarchy, view_h: ViewHierarchy, R: int = 16, mode: str = "megaviews",
                cull: bool = True, budget_pairs: int = DEFAULT_BUDGET, fusion: bool = True,
                record: bool = False, timer=None, multi_pixel: bool = True, split: str = "view",
                split_level: int | None = None) -> Maps:
    """Shadow/depth maps of all views: ``mode`` is ``megaviews`` (octree
    view hierarchy), ``viewonly`` (octree view hierarchy, no scene
    hierarchy: scene leaves x view root), ``manylods`` or ``brute`` (flat
    view sets)."""
    untimed = SimpleNamespace(outputs=lambda *values: None)   # no timer: no stage, nothing checked

    def stage(name):
        return timer.stage(name) if timer is not None else nullcontext(untimed)

    with stage("traverse") as st:
        if mode == "brute":
            maps = brute_force(scene_h, view_h, R, cull, budget_pairs, multi_pixel)
        else:
            maps = Traversal(scene_h, view_h, R, cull, budget_pairs, record, multi_pixel, split, split_level,
                             "leaves" if mode == "viewonly" else "root").run()
        st.outputs(maps.depth)
    with stage("push") as st:
        if maps.stats.multi_pixel > 0:
            push(maps)
        st.outputs(maps.depth)
    with stage("fuse") as st:
        if fusion:
            fuse(maps)
        st.outputs(maps.depth)
    return maps
