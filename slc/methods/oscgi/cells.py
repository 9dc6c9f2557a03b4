"""The secondary cells' kernels and named results (:mod:`.secondary` runs them): the cache rays'
hits and their cells' keys, the representative points, the cells' direct light and rays, the
estimate at glossy hits. Each kernel is a pure function of its inputs, traced once and replayed by
:class:`slc.core.freeze.FrozenFunction` in :class:`~slc.methods.oscgi.secondary.SecondaryCache`."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID, mixed_rng
from slc.scene.lights import sample_light, visible

EMPTY = INVALID
NO_RING = 0xFFFF
STREAM_SECONDARY = 0x05EC0001
REP_WORDS = 9          # representative point (3), front normal (3), diffuse albedo (3)


def front_normal(si: mi.SurfaceInteraction3f, d: mi.Vector3f) -> mi.Vector3f:
    """Geometric normal of a hit, on the side the ray ``d`` came from."""
    return dr.select(dr.dot(si.n, d) > 0.0, -si.n, si.n)


def take3(v, idx):
    """Components of the 3-vector ``v`` at ``idx`` (same type)."""
    return type(v)(*[dr.gather(mi.Float, v[c], idx) for c in range(3)])


@dataclass
class CacheHits:
    """The hits of cache rays (:meth:`SecondaryCache.trace`), one lane per ray."""
    p: mi.Point3f                 # hit position
    n: mi.Vector3f                # geometric normal
    t: mi.Float                   # hit distance (inf: a miss)
    shape: mi.UInt32              # shape index (into scene.shapes())
    pi: mi.PreliminaryIntersection3f
    valid: mi.Bool
    key: mi.UInt32                # the hit's cell key and home slot (:func:`cell_key`)
    home: mi.UInt32
    front_n: mi.Vector3f          # geometric normal on the ray's side
    glossy: mi.Bool               # the hit's BSDF has a glossy or delta lobe


@dataclass
class GlossyHits:
    """At the non-diffuse hits ``lanes`` of cache rays (:func:`glossy_kernel`): the NEE term
    ``Ld``, one BSDF-sampled ray ``ray`` (mask ``ok``, weight ``bw``) and, when traced, the
    cells that ray hit (``slots``, ``hit``)."""
    lanes: mi.UInt32
    Ld: mi.Color3f
    bw: mi.Color3f
    ray: mi.Ray3f
    ok: mi.Bool
    slots: mi.UInt32 | None = None
    hit: mi.Bool | None = None


@dataclass
class CellHits:
    """Cache rays traced to the cells they hit (:meth:`SecondaryCache.sample`)."""
    hits: CacheHits
    slots: mi.UInt32              # the hit cell of each ray (INVALID: none)
    ok: mi.Bool                   # the ray has a cell
    glossy: GlossyHits | None     # the non-diffuse hits' own estimate (None: none this frame)


def trace_kernel(sc, ray, active, h: float, slots: int, shape_key: bool):
    """Cache rays to their hits (``RayFlags.Minimal``) and the hits' cell keys: the fields of
    :class:`CacheHits` in order, evaluated. Frozen by :class:`SecondaryCache` (the rays of
    primary and secondary caches: two recordings)."""
    pi = sc.ray_intersect_preliminary(ray, coherent=False, active=active)
    si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
    sidx = mi.UInt32(pi.shape_index)
    ok = mi.Bool(active) & si.is_valid()
    key, home, nf = cell_key(si, ray.d, sidx, h, slots, shape_key)
    flags = pi.shape.bsdf().flags()
    glossy = ok & (mi.has_flag(flags, mi.BSDFFlags.Glossy) | mi.has_flag(flags, mi.BSDFFlags.Delta))
    out = (mi.Point3f(si.p), mi.Vector3f(si.n), mi.Float(si.t), sidx, pi, ok, key, home, nf, glossy)
    dr.eval(*out)
    return out


def cell_key(si, d, shape_index, h: float, slots: int, shape_key: bool):
    """(key, home slot, front normal) of hits ``si`` reached along ``d``: a 32-bit TEA hash of the
    hit's quantised position ``floor(p / h)`` (``h`` the cell edge), the dominant axis and sign of
    its front-facing geometric normal (6 bins: the two sides of a wall never share a cell) and,
    with ``shape_key``, the hit's shape (two rooms whose floors are separate shapes never share a
    cell even where a cell straddles the wall between them; the journal's secondary caches are
    on-surface texels of islands, which never straddle two islands either)."""
    nf = front_normal(si, d)
    level = mi.UInt32(0)           # one cell size: the key's bits 28-31 are 0
    hl = h * mi.Float(mi.UInt32(1) << level)
    c = mi.Vector3i(dr.floor(si.p / hl))
    a = dr.abs(nf)
    axis = dr.select((a.x >= a.y) & (a.x >= a.z), 0, dr.select(a.y >= a.z, 1, 2))
    neg = dr.select(axis == 0, nf.x < 0.0, dr.select(axis == 1, nf.y < 0.0, nf.z < 0.0))
    bin_ = mi.UInt32(axis * 2) + dr.select(neg, 1, 0)
    shape = mi.UInt32(shape_index) if shape_key else mi.UInt32(0)
    ux, uy, uz = (dr.reinterpret_array(mi.UInt32, v) for v in (c.x, c.y, c.z))
    k0, _ = mi.sample_tea_32(ux, uy, 4)
    key, home = mi.sample_tea_32(k0 ^ (uz * 0x9E3779B9), bin_ | (shape << 3) | (level << 28), 4)
    key = dr.minimum(key, EMPTY - 1)
    return key, home & (slots - 1), nf


def rep_kernel(sc, pi, ray, idx, slots, p, nf):
    """The representative points of the winning lanes ``idx``: (slots, the 9 words: position,
    front normal and the diffuse albedo: the full interaction from the preliminary one, a BSDF
    call), evaluated. The caller writes them (a frozen function copies an input it writes to).
    ``sc`` (the scene, unused) declares the scene's arrays as inputs (the free width of
    ``lanes``, :mod:`slc.core.freeze`)."""
    pw = dr.gather(type(pi), pi, idx)
    rw = dr.gather(mi.Ray3f, ray, idx)
    sw = pw.compute_surface_interaction(rw, mi.RayFlags.All, True)
    albedo = mi.Color3f(sw.bsdf().eval_diffuse_reflectance(sw, sw.is_valid()))
    pp, nw = take3(p, idx), take3(nf, idx)
    sl = dr.gather(mi.UInt32, slots, idx)
    words = [pp.x, pp.y, pp.z, nw.x, nw.y, nw.z, albedo.x, albedo.y, albedo.z]
    dr.eval(sl, *words)
    return sl, words


def direct_kernel(sc, lights, rep, keys_tab, cells, mix, ns, n_samples: float):
    r"""Direct light at the representative points of ``cells``: ``ns`` (opaque) light samples
    x_i (the project's light sampling, shadow rays), each weighted :math:`L_e \cos / p`;
    ``lights`` declares the emitter table as an input. Returns (E_dir/pi, the outgoing direct
    radiance before the albedo; point, normal, albedo, key and lit mask of each cell)."""
    rp = [dr.gather(mi.Float, rep, cells * REP_WORDS + j) for j in range(REP_WORDS)]
    p, nrm, rho = mi.Point3f(*rp[0:3]), mi.Vector3f(*rp[3:6]), mi.Color3f(*rp[6:9])
    keys = dr.gather(mi.UInt32, keys_tab, cells)
    si = dr.zeros(mi.SurfaceInteraction3f)     # width 1: a literal of the inputs' width would be baked
    si.p, si.n, si.sh_frame, si.wi = p, nrm, mi.Frame3f(nrm), mi.Vector3f(0, 0, 1)
    lit = dr.max(rho) > 0.0
    sampler = mixed_rng(keys, mix)

    def cond(i, E, sampler):
        return i < ns

    def body(i, E, sampler):
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        ds, w, ok = sample_light(sc, si, u, lit)
        cos = dr.dot(ds.d, nrm)
        ok &= (cos > 0.0) & dr.all(dr.isfinite(w))
        ok = visible(sc, si, ds, ok)
        return i + 1, E + dr.select(ok, w * cos, 0.0), sampler

    _, E_dir, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                labels=("i", "E", "sampler"))
    L_dir = (E_dir / n_samples) * (1.0 / math.pi)
    dr.eval(L_dir, p, nrm, rho, keys, lit)
    return L_dir, p, nrm, rho, keys, lit


def ray_kernel(p, nrm, keys, tl, mix, R: int):
    """The cosine rays of the tracing lanes ``tl`` (cell c = tl // R of the update's cells, ray
    j = tl % R) from the cells' representative points ``p`` (normals ``nrm``, keys ``keys``)."""
    c_of, j = tl // R, tl % R
    s2 = mixed_rng(dr.gather(mi.UInt32, keys, c_of) * R + j, mix)
    u = mi.Point2f(s2.next_float32(), s2.next_float32())
    sil = dr.zeros(mi.SurfaceInteraction3f)    # width 1: a literal of the inputs' width would be baked
    sil.p, sil.n = take3(p, c_of), take3(nrm, c_of)
    sil.sh_frame = mi.Frame3f(sil.n)
    d = sil.sh_frame.to_world(mi.warp.square_to_cosine_hemisphere(u))
    ray = sil.spawn_ray(d)
    dr.eval(ray)
    return ray


def glossy_kernel(sc, lights, pi, ray, gi, lane_key, mix):
    """At the hits ``gi`` of cache rays on non-diffuse surfaces (glossy, metal), the
    outgoing radiance towards the entry is view-dependent, which a cell's diffuse radiance cannot
    hold: one light sample with the hit's BSDF (next-event estimation: the light after one
    reflection) and one BSDF-sampled ray, whose hit cell's radiance (layer ``bounces`` - 1) the
    caller adds with the weight. Returns (NEE term, BSDF weight, BSDF ray, its mask)."""
    ctx = mi.BSDFContext()
    pw = dr.gather(type(pi), pi, gi)
    rw = dr.gather(mi.Ray3f, ray, gi)
    si = pw.compute_surface_interaction(rw, mi.RayFlags.All, True)
    bsdf = si.bsdf()
    rng = mixed_rng(dr.gather(mi.UInt32, lane_key, gi), mix)
    # ------------------ next-event estimation at the hit ------------------
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    ds, w, okd = sample_light(sc, si, u, si.is_valid())
    okd = visible(sc, si, ds, okd)
    f = mi.Color3f(bsdf.eval(ctx, si, si.to_local(ds.d), okd))
    Ld = dr.select(okd, f * w, 0.0)
    # ------------------ one BSDF-sampled bounce ------------------
    bs, bw = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                         si.is_valid())
    ok2 = si.is_valid() & (bs.pdf > 0.0) & (dr.max(mi.Color3f(bw)) > 0.0)
    ray2 = si.spawn_ray(si.to_world(bs.wo))
    bw = dr.select(ok2, mi.Color3f(bw), 0.0)
    dr.eval(Ld, bw, ray2, ok2)
    return Ld, bw, ray2, ok2
