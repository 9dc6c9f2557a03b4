r"""Instant radiosity with MegaViews shadow maps (Sec. 5.1).

VPLs
    ``generate(scene, n, bounces)``: ``n / bounces`` light paths from
    ``scene.sample_emitter_ray``; one VPL is left at every hit (1-bounce:
    the first hit only; multi-bounce: the path continues by BSDF sampling).
    A VPL keeps its surface interaction (for its BSDF) and its flux
    :math:`\Phi_k` = path weight / paths. Its view is the hemisphere
    (``phi = pi/2``) around the normal on the side the light came from.

Gathering (per pixel, subsampled, hierarchical culling)
    .. math:: L(x) \approx \frac{C(x)}{S}\sum_{s=1}^{S}
              f_x(\omega_{xk})\cos\theta_x\, f_k(\omega_{kx})\cos\theta_k\,
              \frac{\Phi_k}{\max(d^2, d_{min}^2)}\, V_k(x)

    The view hierarchy is walked depth first (stackless, skip pointers)
    down to level ``cull_level`` (the paper: 6); a node whose cone (with its
    radius, the culling test of the traversal) cannot see ``x``, or whose
    bound lies beyond the distance cut-off ``cutoff`` (optional), is culled
    with its subtree; ``C(x)`` counts the VPLs of the nodes reached and
    the ``S`` samples are drawn systematically (one random offset per
    pixel) from them, so the estimate is unbiased over the VPLs that can
    contribute. ``V_k(x)`` is the depth test in VPL ``k``'s dual-paraboloid
    map (:func:`.maps.lookup`) with a bias of
    ``bias_leaf * r_leaf + bias_slope * |x - p_k| * 2 / R``.

Filtering
    A cross-bilateral filter (spatial Gaussian, depth and normal edge stops
    from the G-buffer) on the demodulated estimate (divided by the diffuse
    reflectance, multiplied back after).

Reference
    :func:`slc.reference.references.reference_for` (``"indirect"``, the methods'
    ``bounces``): the one indirect estimator of every indirect method.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.structs import drjit_struct
from slc.scene.gbuffer import to_image  # noqa: F401  (callers use vpl.to_image)
from slc.scene.lights import rng
from slc.methods.megaviews import traversal as tv
from slc.methods.megaviews.hierarchy import ViewHierarchy, as_bool, as_u32, to_np3
from slc.methods.megaviews.maps import lookup


@dataclass
class VPLSet:
    si: mi.SurfaceInteraction3f   # one per VPL (its BSDF is evaluated at gathering)
    flux: mi.Color3f
    position: np.ndarray          # (N, 3)
    normal: np.ndarray            # (N, 3): the side the light arrived from
    bounce: np.ndarray            # (N,) 1 = first hit from the light

    @property
    def n(self) -> int:
        return len(self.position)


def generate(mi_scene: mi.Scene, n: int, bounces: int = 1, seed: int = 0) -> VPLSet:
    """Exactly ``n`` VPLs when the light paths hit enough surfaces (paths are
    traced with a margin for escaping rays and the first ``n`` valid VPLs
    kept), one VPL per bounce. The flux stays normalised by the number of
    paths traced, so the estimate is unbiased whatever is dropped."""
    if bounces > 1:  # VPLs are ordered by bounce: keep them all
        return _generate(mi_scene, n, bounces, seed)
    vs = _generate(mi_scene, int(n * 1.5) + 16, bounces, seed)
    if vs.n <= n:
        return vs
    idx = dr.arange(mi.UInt32, n)
    keep = vs.position.shape[0]
    frac = float(keep) / float(n)   # drop VPLs uniformly: rescale the flux of the kept ones
    return VPLSet(dr.gather(mi.SurfaceInteraction3f, vs.si, idx),
                  dr.gather(mi.Color3f, vs.flux, idx) * dr.opaque(mi.Float, frac),
                  vs.position[:n], vs.normal[:n], vs.bounce[:n])


def _generate(mi_scene: mi.Scene, n: int, bounces: int = 1, seed: int = 0) -> VPLSet:
    bounces = max(int(bounces), 1)
    paths = max(int(n) // bounces, 1)
    sampler = rng(paths, seed, stream=31)
    u = [sampler.next_float32() for _ in range(5)]
    ray, w, _ = mi_scene.sample_emitter_ray(mi.Float(0.0), u[0], mi.Point2f(u[1], u[2]), mi.Point2f(u[3], u[4]),
                                           mi.Bool(True))
    thr = mi.Color3f(w) / dr.opaque(mi.Float, float(paths))   # opaque: no kernel per VPL count
    active = dr.isfinite(thr[0] + thr[1] + thr[2])
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    sis, fluxes, valids = [], [], []
    for b in range(bounces):
        si = mi_scene.ray_intersect(ray, active)
        ok = active & si.is_valid()
        ok &= ~si.shape.is_emitter()
        sis.append(si)
        fluxes.append(thr)
        valids.append(ok)
        if b + 1 < bounces:
            bsdf = si.bsdf()
            bs, bw = bsdf.sample(ctx, si, sampler.next_float32(), mi.Point2f(sampler.next_float32(),
                                                                             sampler.next_float32()), ok)
            active = ok & (bs.pdf > 0.0)
            thr = dr.select(active, thr * mi.Color3f(bw), 0.0)
            active &= dr.max(thr) > 0.0
            ray = si.spawn_ray(si.to_world(bs.wo))
    # ----------------------- compact the valid VPLs -----------------------
    all_si, all_flux, all_b = [], [], []
    for b, (si, fl, ok) in enumerate(zip(sis, fluxes, valids)):
        idx = dr.compress(ok)
        all_si.append(dr.gather(mi.SurfaceInteraction3f, si, idx))
        all_flux.append(dr.gather(mi.Color3f, fl, idx))
        all_b.append(np.full(dr.width(idx), b + 1))
    if len(all_si) == 1:
        si, flux = all_si[0], all_flux[0]
    else:
        sizes = [dr.width(f) for f in all_flux]
        idx_np = np.concatenate([np.arange(s) for s in sizes])
        src = np.concatenate([np.full(s, i) for i, s in enumerate(sizes)])
        si, flux = all_si[0], all_flux[0]
        # concatenate by scattering into fresh arrays
        total = int(sum(sizes))
        si = dr.zeros(mi.SurfaceInteraction3f, total)
        flux = dr.zeros(mi.Color3f, total)
        off = 0
        for s_, f_, k in zip(all_si, all_flux, sizes):
            dst = dr.arange(mi.UInt32, off, off + k)
            dr.scatter(si, s_, dst)
            dr.scatter(flux, f_, dst)
            off += k
        del idx_np, src
    wi_world = si.to_world(si.wi)
    dr.eval(si, flux, wi_world)
    # numpy copies one component at a time: converting a 3-vector whole runs a
    # kernel with the VPL count baked in (component strides), rebuilt per frame
    P, N, wi_world = to_np3(si.p, dr.width(flux)), to_np3(si.n, dr.width(flux)), to_np3(wi_world, dr.width(flux))
    side = np.sign(np.sum(N * wi_world, axis=1))
    N = N * np.where(side == 0, 1.0, side)[:, None]
    return VPLSet(si, flux, P, N, np.concatenate(all_b) if all_b else np.zeros(0))


# -----------------------------------------------------------------------------
# Gathering
# -----------------------------------------------------------------------------

def cull_walk(V: ViewHierarchy, cull_level: int):
    """Depth-first order of the view nodes of levels ``0..cull_level`` with
    skip pointers, for a stackless hierarchical walk: ``(nodes, skip, accept)``
    where ``skip[i]`` is the first DFS position after node ``i``'s subtree and
    ``accept[i]`` marks the nodes whose VPLs are gathered (level
    ``cull_level`` or a shallower leaf)."""
    t = V.tree
    lc = int(min(cull_level, V.depth))
    sel = np.flatnonzero(t.level <= lc)
    order = np.lexsort((t.level[sel], t.first_point[sel]))   # by first point, ancestors first
    nodes = sel[order]
    fp = t.first_point[nodes]
    end = fp + t.point_count[nodes]
    skip = np.searchsorted(fp, end, side="left")
    accept = (t.level[nodes] == lc) | (t.child_count[nodes] == 0)
    return nodes, skip, accept


@dataclass
class CullNodes:
    """The view nodes of the culling walk (:func:`cull_walk`) on the device, in DFS order: each
    node's first point in the hierarchy's point ``order`` and its point ``count``, its ``skip``
    pointer, whether its VPLs are gathered (``accept``), its bounding sphere (``centre``,
    ``radius``) and cone (axis ``dir``, half-angle ``psi`` with the views' ``phi``); ``K`` the
    number of nodes (opaque)."""
    order: mi.UInt32
    first: mi.UInt32
    count: mi.UInt32
    skip: mi.UInt32
    accept: mi.Bool
    centre: mi.Point3f
    radius: mi.Float
    dir: mi.Vector3f
    psi: mi.Float
    K: mi.UInt32

    @staticmethod
    def build(V: ViewHierarchy, cull_level: int) -> "CullNodes":
        order = as_u32(V.tree.order)
        nodes_np, skip_np, accept_np = cull_walk(V, cull_level)
        nodes = as_u32(nodes_np)
        first = as_u32(V.tree.first_point[nodes_np])
        count = as_u32(V.tree.point_count[nodes_np])
        skip = as_u32(skip_np)
        accept = as_bool(accept_np)
        ncentre = dr.gather(mi.Point3f, V.centre, nodes)
        nradius = dr.gather(mi.Float, V.radius, nodes)
        ndir = mi.Vector3f(dr.gather(mi.Point3f, V.dir, nodes))
        npsi = dr.gather(mi.Float, V.theta, nodes) + V.phi_value
        return CullNodes(order, first, count, skip, accept, ncentre, nradius, ndir, npsi,
                         dr.opaque(mi.UInt32, len(nodes_np)))

    def visit(self, x: mi.Point3f, eps: mi.Float, cut: mi.Float | None, i: mi.UInt32):
        """(VPLs gathered from DFS node ``i`` for the points ``x``, next DFS position): a node
        culled (its cone cannot see ``x``, or with ``cut`` its bound lies farther) is skipped
        with its subtree."""
        c_ = dr.gather(mi.Point3f, self.centre, i)
        r_ = dr.gather(mi.Float, self.radius, i)
        culled = tv.cull_test(x, eps, c_, r_, dr.gather(mi.Vector3f, self.dir, i), dr.gather(mi.Float, self.psi, i))
        if cut is not None:
            culled |= dr.norm(c_ - x) - r_ > cut
        acc = dr.gather(mi.Bool, self.accept, i)
        n_i = dr.select(~culled & acc, dr.gather(mi.UInt32, self.count, i), 0)
        nxt = dr.select(culled | acc, dr.gather(mi.UInt32, self.skip, i), i + 1)
        return n_i, nxt

    def vpl_count(self, x: mi.Point3f, eps: mi.Float, cut: mi.Float | None, active: mi.Bool) -> mi.UInt32:
        """``C(x)``: the VPLs of the nodes the walk keeps for the points ``x``."""
        def c_cond(i, C):
            return active & (i < self.K)

        def c_body(i, C):
            n_i, nxt = self.visit(x, eps, cut, i)
            return nxt, C + n_i

        _, C = dr.while_loop(state=(mi.UInt32(0), mi.UInt32(0)), cond=c_cond, body=c_body)
        return C


@drjit_struct
@dataclass
class SampleWalk:
    """The state of :func:`gather`'s pass 2 (one lane per pixel): ``i`` the DFS position, ``s``
    the samples emitted, ``cum`` the VPLs of the nodes passed, ``L`` the sum of the samples."""
    i: mi.UInt32 = field(default_factory=mi.UInt32)
    s: mi.UInt32 = field(default_factory=mi.UInt32)
    cum: mi.UInt32 = field(default_factory=mi.UInt32)
    L: mi.Color3f = field(default_factory=mi.Color3f)


def gather(scene_h, vpls: VPLSet, maps, gb, samples: int = 64, seed: int = 0, cull_level: int = 6,
           cull_tree: ViewHierarchy | None = None, fused: bool = True, bias_leaf: float = 2.0,
           bias_slope: float = 2.0, d_min: float | None = None, shadows: bool = True,
           cutoff: float = 0.0) -> mi.Color3f:
    """Subsampled VPL gathering at the G-buffer points (see module docstring), one traced
    kernel whose two passes walk the same culled view nodes (:meth:`CullNodes.visit`).

    ``cull_level``: the view hierarchy is walked depth first down to this
    level (the paper: 6), skipping the subtree of every node culled for
    ``x``; the VPLs of the nodes reached at that level are sampled.
    ``cutoff`` (> 0, world units): distance cut-off, view nodes whose bounding
    sphere lies farther than ``cutoff`` from ``x`` are culled in the same
    walk and sampled VPLs farther than ``cutoff`` contribute nothing (the
    estimate is then of the VPLs within ``cutoff``: a bias, as in [OBS*15])."""
    # ----------------- the view nodes of the culling walk, on the device -----------------
    V = cull_tree if cull_tree is not None else maps.view_h
    if V.flat:
        raise ValueError("gathering needs an octree view hierarchy for culling")
    nodes = CullNodes.build(V, cull_level)
    K = nodes.K
    S = dr.opaque(mi.UInt32, int(samples))
    use_cut = cutoff > 0.0
    cut = dr.opaque(mi.Float, float(cutoff) if use_cut else 0.0)
    si, active = gb.si, gb.valid
    x = si.p
    eps = dr.opaque(mi.Float, scene_h.leaf_radius)
    R = maps.layout.R
    dmin = dr.opaque(mi.Float, float(d_min if d_min is not None else 0.05 * scene_h.tree.edge))
    bsdf_x = si.bsdf()
    ctx = mi.BSDFContext()
    cut_v = cut if use_cut else None

    # ----------------- pass 1: C(x), VPLs of the non-culled nodes -----------------
    C = nodes.vpl_count(x, eps, cut_v, active)

    # --------------- pass 2: systematic samples over the kept VPLs ---------------
    sampler = rng(gb.size, seed, stream=77)
    xi = sampler.next_float32()
    Cf = mi.Float(C)
    step = Cf / dr.maximum(mi.Float(S), 1.0)

    def cond(st: SampleWalk):
        return active & (C > 0) & (st.i < K) & (st.s < S)

    def body(st: SampleWalk):
        i, s, cum = st.i, st.s, st.cum
        n_i, nxt = nodes.visit(x, eps, cut_v, i)
        t = (mi.Float(s) + xi) * step
        inside = t < mi.Float(cum + n_i)
        # ---- emit sample s from node i ----
        local = dr.minimum(mi.UInt32(dr.maximum(t - mi.Float(cum), 0.0)), dr.maximum(n_i, 1) - 1)
        k = dr.gather(mi.UInt32, nodes.order, dr.gather(mi.UInt32, nodes.first, i) + local, inside)
        si_k = dr.gather(mi.SurfaceInteraction3f, vpls.si, k, inside)
        phi_k = dr.gather(mi.Color3f, vpls.flux, k, inside)
        d = si_k.p - x
        dist2 = dr.squared_norm(d)
        dist = dr.sqrt(dist2)
        w = d / dr.maximum(dist, 1e-12)
        fx = mi.Color3f(bsdf_x.eval(ctx, si, si.to_local(w), inside))
        bsdf_k = si_k.bsdf()
        fk = mi.Color3f(bsdf_k.eval(ctx, si_k, si_k.to_local(-w), inside))
        contrib = fx * fk * phi_k / dr.maximum(dist2, dmin * dmin)
        ok = inside & (dr.max(contrib) > 0.0)
        if use_cut:
            ok &= dist <= cut
        if shadows:
            bias = bias_leaf * eps + bias_slope * dist * (2.0 / R)
            ok = lookup(maps, k, x, ok, bias, fused)
        st.L += dr.select(ok, contrib, 0.0)
        st.s = dr.select(inside, s + 1, s)
        st.cum = dr.select(inside, cum, cum + n_i)
        st.i = dr.select(inside, i, nxt)
        return (st,)

    st, = dr.while_loop(state=(SampleWalk(mi.UInt32(0), mi.UInt32(0), mi.UInt32(0), mi.Color3f(0.0)),),
                        cond=cond, body=body)
    return dr.select(active, st.L * Cf / dr.maximum(mi.Float(S), 1.0), 0.0)


# -----------------------------------------------------------------------------
# Cross-bilateral filter
# -----------------------------------------------------------------------------

def bilateral(gb, L: mi.Color3f, radius: int = 4, sigma_s: float = 2.5, sigma_d: float = 0.05,
              normal_power: float = 16.0) -> mi.Color3f:
    """Cross-bilateral filter of ``L`` guided by the G-buffer (depth, normal),
    on the estimate demodulated by the diffuse reflectance."""
    W, H = gb.width, gb.height
    si, valid = gb.si, gb.valid
    rho = mi.Color3f(si.bsdf().eval_diffuse_reflectance(si, valid))
    demod = dr.max(rho) > 0.02
    E = dr.select(demod, L / dr.maximum(rho, 1e-3), L)
    idx = dr.arange(mi.UInt32, W * H)
    px, py = mi.Int32(idx % W), mi.Int32(idx // W)
    depth, n = gb.depth, mi.Vector3f(si.n.x, si.n.y, si.n.z)
    acc, wsum = mi.Color3f(0.0), mi.Float(0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            qx, qy = px + dx, py + dy
            inb = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H) & valid
            q = mi.UInt32(dr.clip(qy, 0, H - 1) * W + dr.clip(qx, 0, W - 1))
            vq = dr.gather(mi.Bool, valid, q, inb)
            dq = dr.gather(mi.Float, depth, q, inb)
            nq = dr.gather(mi.Vector3f, n, q, inb)
            Eq = dr.gather(mi.Color3f, E, q, inb)
            rel = (dq - depth) / dr.maximum(depth * sigma_d, 1e-6)
            wn = dr.power(dr.maximum(dr.dot(nq, n), 0.0), normal_power)
            w = math.exp(-(dx * dx + dy * dy) / (2 * sigma_s ** 2)) * dr.exp(-0.5 * rel * rel) * wn
            w = dr.select(inb & vq, w, 0.0)
            acc += w * Eq
            wsum += w
    Ef = dr.select(wsum > 1e-8, acc / dr.maximum(wsum, 1e-8), E)
    return dr.select(valid, dr.select(demod, Ef * rho, Ef), 0.0)
