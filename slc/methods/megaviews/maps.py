"""The depth maps of the MegaViews traversal and what follows it: :class:`Maps` (one
dual-paraboloid mip pyramid per view node) with the traversal's counts
(:class:`TraversalStats`), the push pass that fills a pyramid's holes from its coarser levels,
the top-down fusion along the view hierarchy, and the visibility queries through the maps (one
lookup in the fused leaf map, or every ancestor's map without fusion)."""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.structs import drjit_struct
from slc.methods.megaviews import paraboloid as pb
from slc.methods.megaviews.hierarchy import ViewHierarchy

PAIR_BYTES = 8          # two 32-bit node ids, as in the paper (64 bits per pair)


@dataclass
class TraversalStats:
    pairs: int = 0            # pairs processed (all levels, all passes)
    culled: int = 0
    rendered: int = 0
    multi_pixel: int = 0      # leaf pairs splatted into a coarser mip level
    shared_views: int = 0     # sum over rendered pairs of the views in v_j
    peak_pairs: int = 0       # pair-queue peak (live pairs, all pending chunks)
    passes: int = 1           # passes/chunks processed (1 = no multi-pass split)
    levels: int = 0
    split_level: int = 0      # deepest view level a pass started from (paper's multi-pass level)
    wasted_pairs: int = 0     # pairs of passes stopped for exceeding the budget (view split)

    @property
    def views_per_render(self) -> float:
        return self.shared_views / max(self.rendered, 1)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["views_per_render"] = self.views_per_render
        d["pair_queue_mb"] = self.peak_pairs * PAIR_BYTES / 2 ** 20
        return d


@dataclass
class Maps:
    """Depth maps (dual paraboloid, mip pyramid per map) of ``slots`` view
    nodes. ``slot_of_view``/``centre_of_view``: where view ``k`` reads."""
    layout: pb.Layout
    depth: mi.Float
    slots: int
    view_h: ViewHierarchy
    fused: bool = False
    stats: TraversalStats = field(default_factory=TraversalStats)
    record: list | None = None

    def memory_bytes(self) -> int:
        return 4 * self.slots * self.layout.texels

    def leaf_maps_bytes(self) -> int:
        """Fused single-level maps of the leaf view nodes (paper's figure)."""
        n_leaf = int(np.sum(self.view_h.child_count_np == 0))
        return 4 * n_leaf * self.layout.base

    def level0(self) -> np.ndarray:
        """(slots, 2, R, R) numpy copy of level 0 (tests, figures)."""
        R = self.layout.R
        d = np.array(self.depth, np.float32).reshape(self.slots, self.layout.texels)
        return d[:, :2 * R * R].reshape(self.slots, 2, R, R)


# -----------------------------------------------------------------------------
# Push (mipmap hole filling) and fusion
# -----------------------------------------------------------------------------

def push(maps: Maps) -> None:
    """Push-only pyramid pass: every texel of level m-1 takes the minimum of
    itself and its parent texel of level m (coarse to fine)."""
    lay, n = maps.layout, maps.slots
    for m in range(lay.levels - 1, 0, -1):
        Rf = lay.res[m - 1]
        per = 2 * Rf * Rf
        j = dr.arange(mi.UInt32, n * per)
        slot, t = j // per, j % per
        face, rem = t // (Rf * Rf), t % (Rf * Rf)
        ty, tx = rem // Rf, rem % Rf
        Rc = lay.res[m]
        fine = slot * lay.texels + lay.offset[m - 1] + t
        coarse = slot * lay.texels + lay.offset[m] + (face * Rc + (ty >> 1)) * Rc + (tx >> 1)
        v = dr.minimum(dr.gather(mi.Float, maps.depth, fine), dr.gather(mi.Float, maps.depth, coarse))
        dr.scatter(maps.depth, v, fine)
        dr.eval(maps.depth)


def fuse(maps: Maps) -> None:
    """Top-down fusion of the level-0 maps along the view hierarchy, with the
    parent's depth re-measured from the child's centre of projection."""
    V, lay = maps.view_h, maps.layout
    if V.flat:
        maps.fused = True
        return
    R, base = lay.R, lay.base
    for l in range(1, V.depth + 1):
        a, b = int(V.level_start[l]), int(V.level_start[l + 1])
        j = dr.arange(mi.UInt32, (b - a) * base)
        node = dr.opaque(mi.UInt32, a) + j // base   # opaque: one kernel whatever the level sizes
        t = j % base
        par = dr.gather(mi.UInt32, V.parent, node)
        dp = dr.gather(mi.Float, maps.depth, par * lay.texels + t)
        dc_i = node * lay.texels + t
        dc = dr.gather(mi.Float, maps.depth, dc_i)
        has = dp < 0.5 * pb.EMPTY
        face, rem = t // (R * R), t % (R * R)
        d = pb.direction(face, rem % R, rem // R, R)
        q = dr.gather(mi.Point3f, V.centre, par) + d * dp
        corrected = dr.norm(q - dr.gather(mi.Point3f, V.centre, node))
        dr.scatter(maps.depth, dr.minimum(dc, corrected), dc_i, has)
        dr.eval(maps.depth)
    maps.fused = True


# -----------------------------------------------------------------------------
# Queries
# -----------------------------------------------------------------------------

@drjit_struct
@dataclass
class AncestorLoop:
    """The state of the walk up the view hierarchy in :func:`lookup` (one lane per query): ``i``
    the levels passed, ``node`` the view node whose map is read next, ``vis`` the point seen in
    every map read so far, ``alive`` the walk not yet past the root."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    node: mi.UInt32 = field(default_factory=mi.UInt32)
    vis: mi.Bool = field(default_factory=mi.Bool)
    alive: mi.Bool = field(default_factory=mi.Bool)


def lookup(maps: Maps, view: mi.UInt32, x: mi.Point3f, active, bias: mi.Float, fused: bool = True):
    """Visibility of points ``x`` from views ``view`` through the maps:
    ``|x - p| <= depth(texel) + bias``. With ``fused`` one lookup in the
    leaf map; otherwise every ancestor's map is read (no fusion needed)."""
    V, lay = maps.view_h, maps.layout
    node = dr.gather(mi.UInt32, V.leaf_of_view, view, active)
    if fused or V.flat:
        p = dr.gather(mi.Point3f, V.centre, node, active)
        vs = x - p
        face, tx, ty = pb.texel(vs, lay.R)
        d = dr.gather(mi.Float, maps.depth, node * lay.texels + (face * lay.R + ty) * lay.R + tx, active)
        return active & (dr.norm(vs) <= d + bias)
    vis = mi.Bool(active)
    alive = mi.Bool(active)
    steps = dr.opaque(mi.UInt32, V.depth + 1)

    def cond(st: AncestorLoop):
        return st.alive & (st.i < steps)

    def body(st: AncestorLoop):
        p = dr.gather(mi.Point3f, V.centre, st.node, st.alive)
        vs = x - p
        face, tx, ty = pb.texel(vs, lay.R)
        d = dr.gather(mi.Float, maps.depth, st.node * lay.texels + (face * lay.R + ty) * lay.R + tx, st.alive)
        st.vis &= ~st.alive | (dr.norm(vs) <= d + bias)
        st.alive &= st.node != 0
        st.node = dr.gather(mi.UInt32, V.parent, st.node, st.alive)
        st.i = st.i + 1
        return (st,)

    st, = dr.while_loop(state=(AncestorLoop(mi.UInt32(0), node, vis, alive),), cond=cond, body=body)
    return st.vis
