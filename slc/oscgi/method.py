"""The registered ``osc-gi`` method: global illumination from primary radiance caches in the
on-surface cache and secondary radiance caches in a hashed world grid (``docs/osc-gi.md``)."""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi

from slc.core.backend import aligned
from slc.methods.cones.update import light_inputs
from slc.core.freeze import FrozenFunction
from slc.scene.gbuffer import layered, per_viewer, viewer_lanes
from slc.core.keys import INVALID, keyed_rng, mixed_rng, stream_key
from slc.scene.lights import SurfaceBSDF, diffuse_flags, direct_sample, sample_light, visible
from slc.methods import MethodError, Param, register
from slc.osc.cache import OnSurfaceCache
from slc.osc.payload import PayloadMethod, RayPolicy
from slc.methods.sh.shading import diffuse_only, shade_radiance
from slc.methods.oscgi.hemisphere import HemiGrid
from slc.methods.oscgi.laps import Laps
from slc.methods.oscgi.origins import backface_share, representative_points
from slc.methods.oscgi.secondary import SecondaryCache, _glossy_kernel
from slc.methods.oscgi.spatial import SpatialFilter

STREAM_PRIMARY = 0x05C61001
STREAM_PRIMARY_DIRECT = 0x05C61002
STREAM_SHADE = 0x05C61003
STREAM_GLOSSY = 0x05C61004
STREAM_PIXEL_DIRECT = 0x05C61005
STREAM_SHARP = 0x05C61006
DIRECT_METHODS = {"cones": "slc", "restir": "restir"}   # direct=... -> the registered method run beside
INITIAL_ENTRIES = 1 << 14     # the pool starts small and doubles on demand (entries are ~0.8 KB)


def _primary_ray_kernel(pts, keys, tl, mix, D: int, res: int):
    """The jittered cosine rays of the traced lanes ``tl`` (entry tl // D, texel tl % D) from the
    entries' own points ``pts`` = (position, geometric normal, shading normal); returns (rays, mask
    above the geometric surface). Only these three fields of the entries' interactions are inputs:
    passing the whole interaction made the frozen function record again when the sharing of its
    unused literal fields (``dn_du``, ``dn_dv``) with other fields changed between frames."""
    G = HemiGrid(res)
    et, kt = tl // D, tl % D
    si = dr.zeros(mi.SurfaceInteraction3f)   # only what spawn_ray needs; width 1 (a width would be baked)
    si.p = mi.Point3f(*[dr.gather(mi.Float, pts[0][c], et) for c in range(3)])
    si.n = mi.Vector3f(*[dr.gather(mi.Float, pts[1][c], et) for c in range(3)])
    n_sh = mi.Vector3f(*[dr.gather(mi.Float, pts[2][c], et) for c in range(3)])
    s = mixed_rng(dr.gather(mi.UInt32, keys, et) * D + kt, mix)
    d = mi.Frame3f(n_sh).to_world(G.direction(kt, mi.Point2f(s.next_float32(), s.next_float32())))
    ok = dr.dot(d, si.n) > 0.0                      # above the geometric surface
    ray = si.spawn_ray(d)
    dr.eval(ray, ok)
    return ray, ok


def _primary_direct_kernel(sc, lights, sie, keys, scratch, mix, nd, scale: float, res: int):
    """``nd`` (opaque) light samples per entry (the project's light sampling, shadow rays) binned
    into the texels of their directions, added to ``scratch`` (3 words per entry and texel;
    returned); ``lights`` declares the emitter table as an input."""
    G = HemiGrid(res)
    D = G.n
    frame_e = mi.Frame3f(sie.sh_frame.n)
    base = dr.arange(mi.UInt32, dr.width(keys)) * D
    sd = mixed_rng(keys, mix)

    def cond(i, sd):
        return i < nd

    def body(i, sd):
        u = mi.Point2f(sd.next_float32(), sd.next_float32())
        ds, w, okd = sample_light(sc, sie, u, mi.Bool(True))
        loc = frame_e.to_local(ds.d)
        okd &= (dr.dot(ds.d, sie.n) > 0.0) & (loc.z > 0.0) & dr.all(dr.isfinite(w))
        okd = visible(sc, sie, ds, okd)
        t = (base + G.texel(loc)) * 3
        for c in range(3):
            # Direct: the default (Expand) bakes the size of scratch into the kernel
            dr.scatter_add(scratch, w[c] * loc.z * scale, t + c, okd, mode=dr.ReduceMode.Direct)
        return i + 1, sd

    dr.while_loop(state=(mi.UInt32(0), sd), cond=cond, body=body, labels=("i", "sd"))
    dr.eval(scratch)
    return scratch


def _pixel_direct_kernel(sc, lights, table, si, active, idx, mix, n, lds):
    r"""RT-N direct light of the pixels ``si``: ``n`` (opaque) light samples with shadow rays,
    :math:`\frac1n\sum_j f\,L_e G V / p` (:func:`slc.scene.lights.direct_sample`); ``idx`` the pixels'
    stream keys (their width is the launch width), ``lights`` and ``table`` (the diffuse-BSDF table of
    :class:`slc.scene.lights.SurfaceBSDF`) declare what the kernel reads as inputs.

    ``lds`` (a Python bool, part of the recording's key): the n sample points of a pixel are the Hammersley set
    :math:`((j + \tfrac12)/n,\ \Phi_2(j))` shifted by one random offset r per pixel (Cranley-Patterson
    rotation, :math:`u_j = (h_j + r) \bmod 1`): each :math:`u_j` alone is uniform (unbiased), and
    together they cover the unit square (the light's area, and the emitter choice by
    :math:`u_x`) evenly; else n independent uniform points."""
    sampler = mixed_rng(idx, mix)
    ctx = mi.BSDFContext()
    bsdf = SurfaceBSDF(sc, si, active, ctx)
    inv_n = dr.rcp(mi.Float(dr.maximum(n, 1)))
    if lds:   # the pixel's offset, from its own stream (the independent samples keep theirs)
        rs = mixed_rng(idx, mix ^ STREAM_PIXEL_DIRECT)
        r = mi.Point2f(rs.next_float32(), rs.next_float32())

    def cond(i, L, sampler):
        return i < n

    def body(i, L, sampler):
        if lds:
            # ---- Hammersley point i, rotated by the pixel's offset (radical inverse: bit reversal) ----
            u = mi.Point2f(dr.fma(mi.Float(i), inv_n, 0.5 * inv_n), mi.Float(dr.brev(i)) * 2.3283064365386963e-10) + r
            u = dr.minimum(u - dr.floor(u), 0.99999994)
        else:
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        return i + 1, L + direct_sample(sc, si, bsdf, u, active, ctx), sampler

    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                labels=("i", "L", "sampler"))
    L = L * inv_n
    dr.eval(L)
    return L


def _sharp_mask(si, bsdf, g, alpha: float):
    """Pixels (of ``g``, the non-diffuse ones) whose reflection is sharper than the hemisphere
    texels: a delta lobe, or a GGX roughness below ``alpha`` (roughconductor / roughplastic:
    the attribute ``alpha``; principled: ``roughness``^2, Disney's mapping; a BSDF with
    neither attribute reads 0 and counts as sharp only through its flags)."""
    flags = bsdf.flags()
    a_ggx = bsdf.eval_attribute_1("alpha", si, g)
    rough = bsdf.eval_attribute_1("roughness", si, g)
    a = dr.maximum(a_ggx, dr.square(rough))
    return g & (mi.has_flag(flags, mi.BSDFFlags.Delta) | ((a_ggx > 0.0) | (rough > 0.0)) & (a < alpha))


def _sharp_shade(sc, sec, si, bsdf, sharp, frame_e, texel_at, sampler, n: int, n_texel: int, emitters: bool):
    r"""Sharp reflections of the pixels ``sharp`` (session gi10). The BSDF's samples are split by
    the lobe they come from (:math:`\mathbb 1_g`: a glossy or delta lobe, ``bs.sampled_type``),
    two estimators of the two parts of the same integral, so their sum is that of one estimator:

    .. math:: L_o \approx \frac1n\sum_{j\le n} \mathbb 1_g\, w_j\, L_c(\omega_j)
              + \frac1m\sum_{j\le m} (1 - \mathbb 1_g)\, w_j\, L_k(\omega_j),
              \qquad w_j = f\cos/p,

    the first by ``n`` BSDF-sampled rays, :math:`L_c` the outgoing radiance (layer ``bounces``)
    of the secondary cell at the ray's hit (what a primary cache ray reads there; a miss gives 0),
    the second (the diffuse lobe of a principled BSDF, 0 for a conductor) from the entry's texels
    as before, ``m`` = ``n_texel`` samples, no rays. Where a ray's hit has no cell holding a value
    (never touched by a cache ray, or not updated yet) or has a glossy / delta BSDF (a cell holds
    diffuse light only) the entry's texel towards :math:`\omega_j` is read instead
    (``texel_at(d, m)``). ``emitters``: the emission at the hit is added (only when the entries
    hold direct light too, ``direct=cache``; else the pixel's direct light comes from elsewhere).
    The cell is looked up without insertion (:meth:`SecondaryCache.find`)."""
    ctx = mi.BSDFContext()

    def lobe(t):
        return mi.has_flag(t, mi.BSDFFlags.Glossy) | mi.has_flag(t, mi.BSDFFlags.Delta)

    L = mi.Color3f(0.0)
    # ------------------ glossy / delta lobes: BSDF rays into the secondary cells ------------------
    for _ in range(n):
        bs, bw = bsdf.sample(ctx, si, sampler.next_float32(), mi.Point2f(sampler.next_float32(),
                                                                         sampler.next_float32()), sharp)
        ok = sharp & (bs.pdf > 0.0) & lobe(bs.sampled_type)
        d = si.to_world(bs.wo)
        ray = si.spawn_ray(d)
        pi = sc.ray_intersect_preliminary(ray, coherent=False, active=ok)
        sh = pi.compute_surface_interaction(ray, mi.RayFlags.All, ok)
        hit = ok & sh.is_valid()
        hflags = sh.bsdf().flags()
        diff = hit & ~mi.has_flag(hflags, mi.BSDFFlags.Glossy) & ~mi.has_flag(hflags, mi.BSDFFlags.Delta)
        # ---------------- the hit's cell (looked up, not inserted), if it holds a value ----------------
        key, home, _ = sec.key_of(sh, ray.d, mi.UInt32(pi.shape_index))
        slot_c, found = sec.find(key, home, diff)
        found = sec.updated_once(slot_c, found)
        Lc = sec.radiance(slot_c, found)
        # ---------------- else the entry's texel (the cached estimate) ----------------
        Lt, okt = texel_at(d, hit & ~found)
        Li = dr.select(found, Lc, dr.select(okt, Lt, 0.0))
        if emitters:
            Li += dr.select(hit, sh.emitter(sc).eval(sh, hit), 0.0)
        L += dr.select(ok, mi.Color3f(bw) * Li, 0.0) * (1.0 / float(n))

    # ------------------ the other lobes (diffuse): the entry's texels, no rays ------------------
    m_t = dr.opaque(mi.UInt32, n_texel)

    def cond_t(i, Lt, sampler):
        return (i < m_t) & sharp

    def body_t(i, Lt, sampler):
        bs, bw = bsdf.sample(ctx, si, sampler.next_float32(), mi.Point2f(sampler.next_float32(),
                                                                         sampler.next_float32()), sharp)
        okj = sharp & (bs.pdf > 0.0) & ~lobe(bs.sampled_type)
        Li, okj = texel_at(si.to_world(bs.wo), okj)
        return i + 1, Lt + dr.select(okj, mi.Color3f(bw) * mi.Color3f(Li), 0.0), sampler

    _, Ld, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond_t, body=body_t,
                             labels=("i", "Lt", "sampler"))
    return L + Ld * (1.0 / float(n_texel))


def _cache_params():
    """The on-surface cache's settings: mip bias 2 as in the slides (one entry per about 2x2
    pixels) and 4x4 blocks (the slides: 2x2; the cache's per-frame request flag spans every
    virtual block, 4x more of them at 2x2: see docs/osc-gi.md)."""
    out = []
    for p in PayloadMethod.cache_params:
        if p.name == "block":
            p = Param("block", 4, p.help, choices=p.choices)
        elif p.name == "bias":
            p = Param("bias", 2.0, p.help, lo=p.lo, hi=p.hi)
        out.append(p)
    return tuple(out)


class OSCGI(PayloadMethod):
    r"""Radiance caching with on-surface caches (``osc-gi``, Tatzgern et al. 2024).

    *Primary caches*: every requested on-surface cache entry x (its own surface point, rays offset
    along its normal) keeps the incoming radiance over its hemisphere in ``hemi`` x ``hemi`` texels
    of the cosine-weighted concentric map (:class:`~slc.methods.oscgi.hemisphere.HemiGrid`, frame of the
    entry's shading normal). Each update traces one jittered cosine ray per texel; a ray's hit y
    falls in a secondary cell whose outgoing radiance :math:`L_o(y)` (layer ``bounces``) is the
    texel's new sample; with ``output=full``, ``direct_rays`` light samples (next-event
    estimation, :func:`slc.scene.lights.sample_light` + shadow ray) are binned into the texels of their
    directions, :math:`\hat L_k \mathrel{+}= \frac{L_e\cos\theta}{n\,p\,\pi/R^2}[\omega\in k]`.
    Temporal filter: :math:`L_k \leftarrow L_k + (\hat L_k - L_k)/\min(c, N_{max})`, c the
    entry's update count (an EMA over ``n_max`` samples once settled); a new entry starts from
    its LOD seed (a coarser entry) when the cache gives one.

    *Secondary caches*: :class:`~slc.methods.oscgi.secondary.SecondaryCache`, cells of
    ``secondary_cm`` cm keyed by position, normal bin and shape, storing outgoing diffuse radiance
    in ``bounces`` layers (direct light by ``light_samples`` light samples, indirect by
    ``secondary_rays`` cosine rays into other cells; EMA capped at ``secondary_n_max``), so the primary point receives light after
    1..``bounces`` reflections, the paths of the indirect reference. At most ``secondary_budget``
    cells are updated per frame (ring 1 first, then least-sampled, then oldest; the others keep
    their value, and a texel does not blend a sample from a cell never updated unless it has no
    value either); cells unused for ``secondary_evict`` frames are freed.

    *Glossy hits* (``glossy_hits``): a primary ray whose hit has a glossy or delta BSDF takes its
    sample at the hit, since a cell's diffuse radiance cannot hold view-dependent light (and is 0
    for a metal): one light sample with the hit's BSDF plus one BSDF-sampled ray whose hit cell's
    layer ``bounces`` - 1 is weighted by :math:`f\cos/p` (that cell requested as ring 2); a
    secondary ray hitting such a surface takes the light sample's term alone (layer 1 exactly).

    ``freeze`` (on): the kernels with shape, BSDF or emitter calls (cache rays and cell keys,
    representative albedo, direct light of cells and entries, secondary rays, glossy hits) are
    traced once and replayed (:class:`slc.core.freeze.FrozenFunction`); the same images as traced.

    *Shading* (no rays): diffuse-only BSDFs exactly from the texels,
    :math:`L_o = \frac{\rho}{\pi} E,\ E = \frac{\pi}{R^2}\sum_k L_k`; other BSDFs by
    ``glossy_samples`` BSDF samples of the hemisphere, :math:`\frac{1}{n}\sum_j w_j L_{k(\omega_j)}`.
    ``output``: ``indirect`` (light after at least one reflection) or ``full`` (direct + indirect;
    the emission seen directly is added by the pipeline).

    *Sharp reflections and interpolation* (session gi10, both off): ``sharp`` > 0: pixels with a
    delta lobe or a GGX alpha below ``sharp`` trace ``sharp_rays`` BSDF rays for their glossy /
    delta lobes and read the secondary cell at each hit (:func:`_sharp_shade`; the diffuse lobe
    from the texels as above); ``trilinear``: each BSDF sample reads one texel of its bilinear
    footprint chosen with probability = its bilinear weight (unbiased for the bilinear blend;
    :meth:`~slc.methods.oscgi.hemisphere.HemiGrid.texel_stochastic`), not the nearest texel.

    *Direct light* (``output=full``), ``direct``: ``rt`` (default) ``direct_n`` (16) light samples
    per pixel with shadow rays, :math:`\frac1n\sum_j f L_e G V/p` (RT-N, frozen; with ``direct_lds``,
    on, the n points a Hammersley set shifted by a random offset per pixel), added to the
    cached indirect light; ``cones`` / ``restir``: the registered ``slc`` / ``restir`` method run
    beside on the same G-buffers; ``cache``: light samples binned into the entries' texels (above;
    the default before session gi6). Except for ``cache`` the entries hold indirect light only,
    exactly as with ``output=indirect``.

    *Secondary cell edge*: max(``secondary_cm``, ``secondary_scene`` x the scene diagonal d), or
    with ``secondary_px`` > 0 also at least min(``secondary_px`` x the first frame's median pixel
    footprint, ``secondary_max`` x d); ``secondary_lod`` > 0 adds levels growing with the hit
    distance (off).

    *Many viewers* (session gi9): ``update_budget`` (2) caps the entries updated per frame at
    ``update_budget`` x (pixels of the largest viewer) / bias^2, about twice one viewer's entries
    (never reached by one viewer): every new entry, then the most due (fewest samples, oldest
    update); the others keep their value (:meth:`_budgeted`). ``front_only`` (on): only pixels
    facing the viewer request entries (back faces are shaded black). Several viewers are shaded
    in one launch (:meth:`shade_all`).

    Storage per entry: 3 R^2 radiance words, the irradiance (3 words) and the update count.
    Ray budget (the ray policy): an entry's first update traces all R^2 texels, later updates
    ``texel_rays`` of them in rotation (texel k when k = c mod R^2/``texel_rays``, c the update
    number), each traced texel blended with 1/min(its own sample count, ``n_max``); light samples
    (``output=full``) only feed the traced texels.
    """

    name = "osc-gi"
    output = "full"
    params = (
        Param("output", "full", "what is returned: direct + indirect, or indirect light only",
              choices=("full", "indirect")),
        Param("bounces", 2, "indirect bounces (layers of the secondary caches)", lo=1, hi=8),
        Param("hemi", 8, "hemisphere texels per side of a primary cache entry", lo=2, hi=16),
        Param("texel_rays", 64, "texels traced per settled entry and update (new entries: all; divides hemi^2)",
              lo=1, hi=256),
        Param("n_max", 4, "EMA cap: blend factor 1/min(n, n_max)", lo=1, hi=256),
        Param("secondary_n_max", 2, "EMA cap of the secondary cells (0: n_max, as before session gi8)", lo=0, hi=256),
        Param("secondary_cm", 15.0, "secondary cell edge [cm] (30 before session gi8)", lo=1.0, hi=1000.0),
        Param("secondary_scene", 0.04, "secondary cell edge at least this fraction of the scene's bounding-box "
              "diagonal (0: off)", lo=0.0, hi=1.0),
        Param("secondary_px", 0.0, "secondary cell edge at least this many pixel footprints (median over the first "
              "frame's pixels; 0: off), at most secondary_max of the scene's diagonal", lo=0.0, hi=1e4),
        Param("secondary_max", 0.05, "secondary_px: largest footprint-based cell edge, fraction of the scene's "
              "bounding-box diagonal", lo=0.0, hi=1.0),
        Param("secondary_lod", 0.0, "secondary cells grow with the hit distance t: edge about "
              "max(secondary_cm, secondary_lod t), in powers of 2 (0: fixed cells)", lo=0.0, hi=4.0),
        Param("secondary_rays", 16, "cosine rays per secondary cell update (32 before session gi8)", lo=1, hi=1024),
        Param("light_samples", 4, "light samples per secondary cell update", lo=1, hi=1024),
        Param("secondary_direct", "plain", "secondary cells' direct light: plain light samples, or each chosen by "
              "resampled importance sampling among secondary_ris_m candidates (ris, one shadow ray)",
              choices=("plain", "ris")),
        Param("secondary_ris_m", 8, "secondary_direct=ris: candidates per light sample", lo=1, hi=256),
        Param("direct_rays", 8, "light samples per primary entry update (output=full)", lo=1, hi=1024),
        Param("glossy_samples", 16, "BSDF samples of the hemisphere per glossy pixel (8 before session gi8)", lo=1, hi=1024),
        Param("secondary_slots", 17, "log2 of the secondary hash-table size", lo=8, hi=24),
        Param("secondary_budget", 8192, "secondary cell updates per frame, least-sampled first (0: all)",
              lo=0, hi=1 << 24),
        Param("secondary_evict", 4, "free secondary cells unused for this many frames (0: never)", lo=0, hi=1 << 16),
        Param("shape_key", True, "secondary cells keyed by shape too (no sharing across shapes)"),
        Param("seed_finer", True, "new entries without a coarser seed start from their finer level's entries"),
        Param("filter_radius", 0, "spatial filter radius in texels inside islands (0: off; the slides: 3)",
              lo=0, hi=8),
        Param("filter_angle", 25.0, "spatial filter: largest normal difference and parallax turn [deg]",
              lo=0.0, hi=90.0),
        Param("parallax", True, "spatial filter: parallax-corrected directions"),
        Param("glossy_hits", True, "primary rays hitting glossy/metal surfaces: NEE + one BSDF ray into a cell "
              "(else the cell's diffuse radiance: 0 for a metal)"),
        Param("freeze", True, "kernels with shape/BSDF/emitter calls traced once and replayed (dr.freeze)"),
        Param("direct", "rt", "direct light of output=full: cached in the entries (cache), or per pixel by "
              "direct_n light samples (rt), the cones (slc) or ReSTIR run beside (cones, restir)",
              choices=("cache", "rt", "cones", "restir")),
        Param("direct_n", 16, "light samples per pixel with direct=rt", lo=1, hi=1024),
        Param("direct_lds", True, "direct=rt: a pixel's light samples are a randomly shifted Hammersley set "
              "(stratified over the light; else independent)"),
        Param("update_budget", 2.0, "primary entries updated per frame at most, in units of one viewer's share: "
              "update_budget x (pixels of the largest viewer) / bias^2; new entries always, then the most due "
              "(fewest samples, oldest update); 0: every requested entry", lo=0.0, hi=1e6),
        Param("origin", "texel", "where an entry's rays start: its own surface point (texel), or its point projected "
              "onto the plane of its island's first triangle (representative: the slides' naive triangle ids, "
              "for measuring the artefact)", choices=("texel", "representative")),
        Param("front_only", True, "only pixels facing the viewer request entries (back faces are shaded black)"),
        Param("sharp", 0.0, "sharp reflections (session gi10): pixels with a delta lobe or a GGX alpha below this "
              "trace sharp_rays BSDF rays and read the secondary cell at the hit instead of the entry's texels "
              "(0: off)", lo=0.0, hi=1.0),
        Param("sharp_rays", 2, "sharp: BSDF-sampled rays per sharp pixel", lo=1, hi=64),
        Param("trilinear", False, "glossy shading reads one texel of the direction's bilinear footprint, chosen "
              "with probability = its bilinear weight (stochastic interpolation; else the nearest texel)"),
    ) + _cache_params()
    storage_type = mi.Float
    probe_origins = False          # count the cache rays hitting a back face (origin_probe: back, valid)
    origin_probe = (0, 0)

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.grid = HemiGrid(self.hemi)
        self.words = 3 * self.grid.n + 5           # radiance per texel, irradiance, count, mean 1/t
        self.filter = SpatialFilter(self.filter_radius, self.filter_angle, self.parallax)
        self.label = None if self.output == "full" else "osc-gi:output=indirect"
        # traced once and replayed (FrozenFunction): a new width of the inputs needs no recording
        self._k_ray = FrozenFunction(_primary_ray_kernel, bool(self.freeze), max_recordings=6)
        self._k_direct = FrozenFunction(_primary_direct_kernel, bool(self.freeze), max_recordings=6)
        self._k_glossy = FrozenFunction(_glossy_kernel, bool(self.freeze), max_recordings=6)
        self._k_pixel = FrozenFunction(_pixel_direct_kernel, bool(self.freeze), max_recordings=6)
        # direct light in the entries only with output=full, direct=cache; else per pixel (render)
        self._cache_direct = self.output == "full" and self.direct == "cache"
        self._sub = None
        if self.output == "full" and self.direct in DIRECT_METHODS:
            from slc import methods
            self._sub = methods.create(DIRECT_METHODS[self.direct], scene, seed=self.seed)

    def validate(self):
        if self.output not in ("full", "indirect"):
            raise MethodError(f"{self.name}: output must be full or indirect")
        if self.direct not in ("cache", "rt") + tuple(DIRECT_METHODS):
            raise MethodError(f"{self.name}: direct must be cache, rt, cones or restir")
        D = self.hemi * self.hemi
        if self.texel_rays > D or D % self.texel_rays:
            raise MethodError(f"{self.name}: texel_rays must divide hemi^2 = {D} (got {self.texel_rays})")

    def ray_policy(self) -> RayPolicy:
        """All texels for an entry's first update, ``texel_rays`` afterwards (texels in rotation)."""
        D = self.hemi * self.hemi
        return RayPolicy(new=D, new_updates=1, settled=self.texel_rays, moving=D, motion_updates=1)

    def reset(self):
        super().reset()
        self.secondary = None
        # sub-stage clock of update (off unless an experiment sets _profile: no host syncs)
        self.laps = Laps(getattr(self, "_profile", False), getattr(self, "_profile_skip", 0))
        self.memory_log = []          # per frame: (primary bytes, secondary bytes in use)
        self._upd_frame = None        # per slot: frame of the entry's last update (update_budget)
        self.entries_updated = 0      # entries the last update took
        if getattr(self, "_sub", None) is not None:
            self._sub.reset()

    def _cell_edge(self, gbuffers) -> float:
        """The secondary cells' edge (scene units): max(``secondary_cm``, ``secondary_scene`` x the
        scene's bounding-box diagonal d, and with ``secondary_px`` > 0 min(``secondary_px`` x the
        median pixel footprint of the first frame's viewers, ``secondary_max`` x d)); fixed from
        then on (a new edge would change every cell's key)."""
        import numpy as np
        unit = float(getattr(self.scene, "unit", 1.0) or 1.0)
        bb = self.scene.mi_scene.bbox()
        diag = float(np.linalg.norm(np.array(bb.max) - np.array(bb.min)))
        diag = diag if np.isfinite(diag) else 0.0
        h = max(self.secondary_cm / 100.0 * unit, self.secondary_scene * diag)
        if self.secondary_px > 0.0 and gbuffers:
            fp = np.concatenate([np.asarray(gb.footprint)[np.asarray(gb.valid, dtype=bool)] for gb in gbuffers])
            fp = fp[np.isfinite(fp) & (fp > 0.0)]
            if fp.size:
                h = max(h, min(float(self.secondary_px * np.median(fp)), self.secondary_max * diag))
        return h

    def _make_cache(self):
        cache = self._cache_arg
        if cache is None:
            cache = OnSurfaceCache(self.scene, block_size=self.block, bias=self.bias, evict_after=self.evict_after,
                                   max_blocks=max(1, INITIAL_ENTRIES // (self.block * self.block)),
                                   front_only=bool(self.front_only))
        self.cache = cache
        self.secondary = SecondaryCache(self.scene.mi_scene, self._cell_edge(getattr(self, "_gbuffers", None)), self.bounces,
                                        self.secondary_n_max or self.n_max, self.secondary_rays, self.light_samples,
                                        1 << self.secondary_slots, shape_key=self.shape_key, seed=self.seed,
                                        budget=self.secondary_budget, evict_after=self.secondary_evict,
                                        freeze=bool(self.freeze), glossy_hits=bool(self.glossy_hits),
                                        lod=self.secondary_lod, direct=self.secondary_direct,
                                        ris_m=self.secondary_ris_m)
        self.secondary.laps = self.laps

    # ----------------------------------------------------------------- update
    def update(self, ctx, fr, rays, unsettled):
        n_requested = fr.n_active
        # ------- the per-frame budget (update_budget): which requested entries are updated -------
        fr, rays, unsettled = self._budgeted(ctx, fr, rays, unsettled)
        sc, G, W, sec = self.scene.mi_scene, self.grid, self.words, self.secondary
        D, N = G.n, fr.n_active
        laps = self.laps
        laps.start()
        # in a frame without new entries the cache's seed slots are a literal (all INVALID), which
        # would give the kernels reading them another IR (built in a timed frame): an array in memory
        dr.make_opaque(fr.seed_slot)

        # ------- primary rays: one jittered cosine ray per texel of this update's share -------
        # texel k of an entry is traced in its first update and, afterwards, in update c when
        # k = c (mod S), S = hemi^2 / texel_rays: every texel once per S updates
        lane = dr.arange(mi.UInt32, N * D)
        e, k = lane // D, lane % D
        S = D // self.texel_rays
        is_new = dr.gather(mi.Bool, fr.is_new, e)
        seed_slot = dr.gather(mi.UInt32, fr.seed_slot, e)
        seeded = is_new & (seed_slot != INVALID)
        slot = dr.gather(mi.UInt32, fr.active, e)
        # ------- new entries without a coarser seed: the mean of their finer entries, if any -------
        kids = self._finer_seeds(fr)
        # per entry (N lanes), then spread to the entry's texels
        n_kids_e = sum(dr.select(kd != INVALID, 1.0, 0.0) for kd in kids)
        fine_e = fr.is_new & (fr.seed_slot == INVALID) & (n_kids_e > 0.0)
        self._finer_seeded = fine_e                                     # per entry (tests)
        n_kids = dr.gather(mi.Float, n_kids_e, e) if kids else 0.0
        fine = dr.gather(mi.Bool, fine_e, e)
        fine_old = []
        for ch in range(3):
            acc = mi.Float(0.0)
            for kd in kids:
                ks = dr.gather(mi.UInt32, kd, e)
                acc += dr.gather(mi.Float, self.storage, ks * W + k * 3 + ch, fine & (ks != INVALID))
            fine_old.append(acc * dr.rcp(dr.maximum(n_kids, 1.0)))
        # fine_old is read (masked) in the EMA's kernel below: not evaluated here over every texel
        dr.eval(fine_e)
        laps.lap("primary_seeds")
        acc = None                    # an unevaluated reader of the storage (see the scatters below)
        c_old = dr.select(is_new, dr.select(seeded | fine, 1.0, 0.0),
                          dr.gather(mi.Float, self.storage, slot * W + 3 * D + 3))
        c = mi.UInt32(c_old) + 1                                     # this update's number
        full = dr.gather(mi.UInt32, rays, e) >= D
        traced = full | ((k % S) == (c % S))
        dr.eval(traced, c_old)
        # ---- only this update's texels from here on (a compact lane list tl into the N x D lanes) ----
        tl = dr.compress(traced)
        et, kt = tl // D, tl % D
        ray_k = self._k_ray if dr.width(tl) > 1 else _primary_ray_kernel
        o = fr.si.p if self.origin == "texel" else representative_points(self.cache, fr.active, fr.si.p)
        ray, ok = ray_k((o, fr.si.n, fr.si.sh_frame.n), fr.keys, tl,
                        stream_key(self.seed, ctx.frame, STREAM_PRIMARY), D, self.hemi)
        laps.lap("primary_raygen", ray, ok)
        hits = sec.trace(ray, ok)   # (p, n, t, shape index, preliminary intersection, valid, key, home, front n)
        laps.lap("primary_rays", *hits)
        if self.probe_origins:                      # (measurements, tests: back-face hits of the cache rays)
            b, v = backface_share(hits[1], ray.d, hits[5])
            self.origin_probe = (self.origin_probe[0] + b, self.origin_probe[1] + v)

        # ------------- secondary caches: cells of the hits, requests, update (all shared) -------------
        req = sec.begin_frame(ctx.frame)              # eviction first: slots move in a rebuild
        laps.lap("secondary_evict", req)
        slots, hok = sec.touch(hits, ray, ok)
        sec.request(req, slots, hok, 1)
        sec.record_reuse(slots, hok)
        # ----- non-diffuse hits (glossy_hits): NEE + one BSDF ray into a cell (ring 2) per lane -----
        gl = None
        if self.glossy_hits:
            gi = dr.compress(hits[9])
            if dr.width(gi) > 0:
                lane_key = dr.gather(mi.UInt32, fr.keys, et) * D + kt
                gk = self._k_glossy if dr.width(gi) > 1 else _glossy_kernel
                Ld, bw, ray2, ok2 = gk(sc, light_inputs(sc), hits[4], ray, gi, lane_key,
                                       stream_key(self.seed, ctx.frame, STREAM_GLOSSY))
                s2, h2ok = None, mi.Bool(False)
                if self.bounces > 1:
                    hits2 = sec.trace(ray2, ok2)
                    s2, h2ok = sec.touch(hits2, ray2, ok2)
                    h2ok &= dr.dot(hits2[1], ray2.d) != 0.0
                    sec.request(req, s2, h2ok, 2)
                gl = (gi, Ld, bw, s2, h2ok)
        laps.lap("secondary_lookup", slots, hok, req)
        sec.update(ctx.frame, req)
        laps.lap("secondary_update")
        Lc = sec.radiance(slots, hok)                  # outgoing radiance of the hit's cell
        # a hit cell never updated yet (over the budget) holds no value: the texel is not blended
        # (it keeps its value) rather than pulled towards 0, unless it has no value yet either
        em = hok & ~sec.updated_once(slots, hok)
        if gl is not None:
            gi, Ld, bw, s2, h2ok = gl
            Lg = Ld
            if s2 is not None:
                Lg = Lg + bw * sec.radiance(s2, h2ok, layer=self.bounces - 1)
            Lc = [mi.Float(Lc[ch]) for ch in range(3)]
            for ch in range(3):
                dr.scatter(Lc[ch], Lg[ch], gi)
            dr.scatter(em, h2ok & ~sec.updated_once(s2, h2ok) if s2 is not None else mi.Bool(False), gi)
        # mean inverse hit distance of the entry's rays this update (a miss: 0), for the filter
        t_hit = hits[2]
        it_hit = dr.select(t_hit != dr.inf, dr.rcp(dr.maximum(t_hit, 1e-6)), 0.0)
        if dr.width(tl) == N * D:
            # every texel traced (texel_rays = hemi^2, the default, or all entries updated in full):
            # tl is the identity, the per-lane values are used as they are (no scatters)
            sample = [mi.Float(Lc[ch]) for ch in range(3)]
            empty = mi.Bool(em)
            inv_t, n_t = dr.select(ok, it_hit, 0.0), dr.select(ok, 1.0, 0.0)
        else:
            sample = [dr.zeros(mi.Float, N * D) for _ in range(3)]
            empty = dr.zeros(mi.Bool, N * D)
            for ch in range(3):
                dr.scatter(sample[ch], Lc[ch], tl)
            dr.scatter(empty, em, tl)
            inv_t, n_t = dr.zeros(mi.Float, N * D), dr.zeros(mi.Float, N * D)
            dr.scatter(inv_t, it_hit, tl, ok)
            dr.scatter(n_t, 1.0, tl, ok)
        dr.eval(*sample, empty, inv_t, n_t)
        laps.lap("primary_samples")

        # ----------------- direct light (output=full): light samples binned into texels -----------------
        if self._cache_direct:
            scratch = dr.zeros(mi.Float, N * D * 3)
            direct_k = self._k_direct if N > 1 else _primary_direct_kernel
            scratch = direct_k(sc, light_inputs(sc), fr.si, fr.keys, scratch,
                               stream_key(self.seed, ctx.frame, STREAM_PRIMARY_DIRECT),
                               dr.opaque(mi.UInt32, self.direct_rays), 1.0 / (self.direct_rays * G.texel_weight),
                               self.hemi)
            sample = [sample[c] + dr.gather(mi.Float, scratch, lane * 3 + c) for c in range(3)]
            laps.lap("primary_direct")

        # ------------ temporal EMA per traced texel; new entries start from their seed ------------
        # a texel's own sample count: c for full updates, about 1 + ceil((c - 1) / S) in rotation
        src = dr.select(seeded, seed_slot, slot)
        keep = ~is_new | seeded
        cnt = c_old + 1.0
        c_k = dr.select(full, cnt, 1.0 + mi.Float((c - 1 + S - 1) // S))
        a = dr.select(traced & ~(empty & (c_k > 1.0)), dr.rcp(dr.minimum(c_k, float(self.n_max))), 0.0)
        new = []
        for ch in range(3):
            old = dr.select(fine, fine_old[ch], dr.gather(mi.Float, self.storage, src * W + k * 3 + ch, keep))
            new.append(dr.fma(a, dr.select(traced, sample[ch], old) - old, old))
        E = [dr.block_sum(x, D) * G.texel_weight for x in new]      # per entry: (pi/R^2) sum_k L_k
        # the mean inverse hit distance, EMA over updates (the seed's value for a seeded entry)
        n_e, s_e = dr.block_sum(n_t, D), dr.block_sum(inv_t, D)
        c_e = dr.gather(mi.Float, c_old, dr.arange(mi.UInt32, N) * D) + 1.0
        src_e = dr.select(dr.gather(mi.Bool, seeded, dr.arange(mi.UInt32, N) * D), fr.seed_slot, fr.active)
        keep_e = ~fr.is_new | (fr.seed_slot != INVALID)
        d_old = dr.gather(mi.Float, self.storage, src_e * W + 3 * D + 4, keep_e)
        a_e = dr.select(n_e > 0.0, dr.select(keep_e, dr.rcp(dr.minimum(c_e, float(self.n_max))), 1.0), 0.0)
        d_new = dr.fma(a_e, s_e * dr.rcp(dr.maximum(n_e, 1.0)) - d_old, d_old)
        dr.eval(*new, *E, cnt, d_new)
        laps.lap("primary_blend")
        # no live reader of the storage (unevaluated gathers) may survive the scatters below: Dr.Jit
        # would copy the whole storage (12.9 MB at 16k entries) before writing into it
        del old, d_old, fine_old
        for ch in range(3):
            dr.scatter(self.storage, new[ch], slot * W + k * 3 + ch)
            dr.scatter(self.storage, E[ch], fr.active * W + 3 * D + ch)
        dr.scatter(self.storage, cnt, slot * W + 3 * D + 3, k == 0)
        dr.scatter(self.storage, d_new, fr.active * W + 3 * D + 4)
        laps.lap("primary_ema", self.storage)
        return dr.zeros(mi.Bool, n_requested)

    def update_limit(self, fr) -> int:
        """The most entries one frame's update may take (``update_budget`` x the largest
        viewer's pixels / bias^2; 0 when off): about ``update_budget`` times the entries one
        viewer requests (one entry per bias x bias pixels at the footprint's level)."""
        if self.update_budget <= 0.0 or not fr.pixel_slot:
            return 0
        px = max(dr.width(ps) for ps in fr.pixel_slot)
        return max(1, int(math.ceil(self.update_budget * px / max(float(self.bias), 1e-3) ** 2)))

    def _budgeted(self, ctx, fr, rays, unsettled):
        """(fr, rays, unsettled) of the entries this frame's update takes. Under the limit
        (:meth:`update_limit`; always for one viewer at the default) every requested entry.
        Over it, the slides' fixed per-frame budget: every new entry (it has no value yet), then
        the settled ones most due, due = frame of the last update + min(updates, ``n_max``)
        (fewest samples first, then oldest; ties by slot), up to the limit. An entry not taken
        keeps its value (it holds one: every entry is updated in its first frame); once every
        entry has ``n_max`` updates the order is a round robin, so each of N entries is updated
        at least once every ceil(N / limit) frames while no new ones arrive (tested). The last
        update's frame per slot is kept beside the storage (``_upd_frame``). With several
        viewers the update always reads the entries through the selection (all of them when
        under the limit), so that its kernels are the same whether or not the budget bites in
        a frame (a first frame under the limit after the warm-up would build kernels); one viewer
        under the limit reads the cache's arrays as before (the same kernels and images)."""
        import numpy as np
        N, B = fr.n_active, self.update_limit(fr)
        cap = dr.width(self.storage) // self.words
        if B > 0 and (self._upd_frame is None or dr.width(self._upd_frame) < cap):
            grown = dr.zeros(mi.UInt32, cap)
            if self._upd_frame is not None:
                dr.scatter(grown, self._upd_frame, dr.arange(mi.UInt32, dr.width(self._upd_frame)))
            self._upd_frame = grown
        self.entries_updated = N
        if B <= 0:
            return fr, rays, unsettled
        now = dr.opaque(mi.UInt32, ctx.frame)
        if N <= B and len(fr.pixel_slot) < 2:
            dr.scatter(self._upd_frame, now, fr.active)
            dr.eval(self._upd_frame)
            return fr, rays, unsettled
        take = N
        if N > B:
            D, W = self.grid.n, self.words
            slot = np.array(fr.active, dtype=np.int64)
            cnt = np.array(dr.gather(mi.Float, self.storage, fr.active * W + 3 * D + 3))
            last = np.array(dr.gather(mi.UInt32, self._upd_frame, fr.active), dtype=np.int64)
            due = last + np.minimum(cnt, float(self.n_max)).astype(np.int64)
            due[np.array(fr.is_new, dtype=bool)] = -1                  # new entries: always
            order = np.lexsort((slot, due))
            take = min(max(B, int(np.count_nonzero(due < 0))), N)
        # an aligned copy: a numpy buffer at an unaligned address is another kernel (slc.core.backend.aligned)
        sel = (mi.UInt32(aligned(np.sort(order[:take]), np.uint32)) if take < N
               else dr.arange(mi.UInt32, N))
        sub = dataclasses.replace(fr, active=dr.gather(mi.UInt32, fr.active, sel),
                                  si=dr.gather(mi.SurfaceInteraction3f, fr.si, sel),
                                  is_new=dr.gather(mi.Bool, fr.is_new, sel),
                                  seed_slot=dr.gather(mi.UInt32, fr.seed_slot, sel),
                                  keys=dr.gather(mi.UInt32, fr.keys, sel))
        rays, unsettled = dr.gather(mi.UInt32, rays, sel), dr.gather(mi.Bool, unsettled, sel)
        # arrays in memory: a gather from a literal (the cache's is_new / seed_slot in a frame without
        # new entries) stays a literal, and the update's kernels would get another IR (a kernel build)
        dr.make_opaque(sub.active, sub.si, sub.is_new, sub.seed_slot, sub.keys, rays, unsettled)
        dr.scatter(self._upd_frame, now, sub.active)
        dr.eval(self._upd_frame)      # now: a pending scatter would fuse into whichever kernel comes next
        self.entries_updated = take
        return sub, rays, unsettled

    def _finer_seeds(self, fr) -> list:
        """Per active entry, the slots of the 4 entries of the next finer level covering it
        (INVALID where absent, not mapped, new this frame, never updated, or where the entry is
        not new, has a coarser seed or is at level 0): the slides seed new entries from the
        adjacent levels, coarser and finer; the on-surface cache gives the coarser one."""
        N, W, D = fr.n_active, self.words, self.grid.n
        L, pool = getattr(self.cache, "layout", None), getattr(self.cache, "pool", None)
        if not self.seed_finer or L is None or pool is None:
            return []
        new_now = dr.zeros(mi.Bool, dr.width(self.storage) // W)     # entries new this frame
        dr.scatter(new_now, True, fr.active, fr.is_new)
        isl, lvl, tx, ty = pool.entry_texels(fr.active)
        need = fr.is_new & (fr.seed_slot == INVALID) & (lvl > 0)
        key = isl * L.levels + dr.maximum(lvl, 1) - 1
        wl, hl = L.key_extent(key, need)
        kids = []
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            cx, cy = tx * 2 + dx, ty * 2 + dy
            m = need & (mi.Int32(cx) < wl) & (mi.Int32(cy) < hl)
            sl = pool.slot(L.vblock(key, cx, cy, m), L.within(cx, cy), m)
            m &= sl != INVALID
            m &= ~dr.gather(mi.Bool, new_now, sl, m)
            m &= dr.gather(mi.Float, self.storage, sl * W + 3 * D + 3, m) > 0.0
            kids.append(dr.select(m, sl, INVALID))
        dr.eval(*kids)
        return kids

    # ------------------------------------------------------------------ shade
    def shade_all(self, ctx, fr, gbuffers):
        """Every viewer's pixels. Several viewers are shaded in one launch over the frame's
        layered G-buffer (:func:`slc.scene.gbuffer.layered`; the cache's slots laid out the same way,
        ``fr.layer_slot`` / ``fr.layer_index``), then split per viewer: each pixel keeps the
        random-number key it has per viewer (its index within its own viewer), so the images are
        those of :meth:`shade` bit for bit, and the shading (BSDF calls) is traced in Python once
        a frame instead of once per viewer (session gi9: 16 viewers at 32x18 spent 17 of 31 ms a
        frame tracing 16 shading kernels, 0.2 ms of it executing them). With the spatial filter
        on (``filter_radius`` > 0), from a filtered copy of the active entries
        (:class:`~slc.methods.oscgi.spatial.SpatialFilter`, timed with the display), the temporal state
        left unfiltered."""
        raw = self.storage
        if self.filter.r > 0:
            self.storage = self.filter.apply(self.cache, raw, fr, self.grid, self.words)
        try:
            if len(gbuffers) < 2 or fr.layer_slot is None or fr.layer_index is None:
                return [self.shade(ctx, fr, v, gb) for v, gb in enumerate(gbuffers)]
            lay = layered(gbuffers)
            L = self._shade_pixels(ctx, fr, lay.si, lay.valid, mi.UInt32(fr.layer_slot),
                                   mi.UInt32(fr.layer_index), lay.pixel)
            return per_viewer(L, lay.sizes, lay.offsets)
        finally:
            self.storage = raw

    def shade(self, ctx, fr, v, gb):
        """One viewer's pixels (see :meth:`_shade_pixels`)."""
        if len(fr.pixel_slot) > 1 and fr.layer_slot is not None:
            # several viewers: the viewer's part of the layered values, gathered here rather than
            # through the cache's per-viewer views, whose unevaluated gathers (made in another
            # order) gave the fused shading kernel of all viewers another IR in some frames (a kernel
            # built in a timed frame of the 16-viewer row)
            at = viewer_lanes(gb.size, sum(dr.width(fr.pixel_slot[u]) for u in range(v)))
            slot = dr.gather(mi.UInt32, fr.layer_slot, at)
            idx = dr.gather(mi.UInt32, fr.layer_index, at)
        else:
            slot, idx = mi.UInt32(fr.pixel_slot[v]), mi.UInt32(fr.pixel_index[v])
        return self._shade_pixels(ctx, fr, gb.si, mi.Bool(gb.valid), slot, idx, dr.arange(mi.UInt32, gb.size))

    def _shade_pixels(self, ctx, fr, si, valid, slot, idx, pid):
        """Pixels ``si`` (G-buffer mask ``valid``) from their entries (``slot`` into the storage,
        ``idx`` into ``fr.si``); ``pid`` each pixel's index within its own viewer (the key of
        its random numbers). Diffuse BSDFs from the irradiance words, others by BSDF samples of
        the hemisphere texels (:func:`slc.methods.sh.shading.shade_radiance`)."""
        G, W, D = self.grid, self.words, self.grid.n
        ok = valid & (slot != INVALID) & (si.wi.z > 0.0)
        bsdf = si.bsdf()
        d_only = diffuse_only(bsdf)
        g = ok & ~d_only
        n_e = mi.Vector3f(*[dr.gather(mi.Float, fr.si.sh_frame.n[c], idx, g) for c in range(3)])
        frame_e = mi.Frame3f(n_e)

        def irradiance():
            # diffuse: E from the entry's irradiance words
            return mi.Color3f(*[dr.gather(mi.Float, self.storage, slot * W + 3 * D + c, ok & d_only)
                                for c in range(3)])

        def radiance(d, m, u=None):
            # glossy: the entry's hemisphere texel towards d (BSDF importance sampling); with
            # trilinear one texel of the bilinear footprint, chosen by its weight (u)
            loc = frame_e.to_local(d)
            m = m & (loc.z > 0.0)
            t = slot * W + (G.texel(loc) if u is None else G.texel_stochastic(loc, u)) * 3
            return mi.Color3f(*[dr.gather(mi.Float, self.storage, t + c, m) for c in range(3)]), m

        sampler = keyed_rng(pid, self.seed, ctx.frame, STREAM_SHADE)
        if self.sharp <= 0.0:
            return shade_radiance(si, bsdf, ok, irradiance, radiance, sampler, self.glossy_samples,
                                  jitter=bool(self.trilinear))
        # ------- sharp reflections: BSDF rays to the secondary cells (the others as above) -------
        sharp = _sharp_mask(si, bsdf, g, float(self.sharp))
        L = shade_radiance(si, bsdf, ok & ~sharp, irradiance, radiance, sampler, self.glossy_samples,
                           jitter=bool(self.trilinear))
        s2 = keyed_rng(pid, self.seed, ctx.frame, STREAM_SHARP)
        Ls = _sharp_shade(self.scene.mi_scene, self.secondary, si, bsdf, sharp, frame_e, radiance, s2,
                          int(self.sharp_rays), int(self.glossy_samples), bool(self._cache_direct))
        return dr.select(sharp, Ls, L)

    # ------------------------------------------------------------------ frame
    def render(self, ctx, gbuffers, timer):
        self._gbuffers = gbuffers            # for the cell edge of secondary_px (read when the cache is made)
        out = super().render(ctx, gbuffers, timer)
        self._gbuffers = None
        # ------- direct light per pixel (output=full, direct != cache): added to the cached indirect -------
        if self.output == "full" and self.direct == "rt":
            with timer.stage("direct") as st:
                sc = self.scene.mi_scene
                mix = stream_key(self.seed, ctx.frame, STREAM_PIXEL_DIRECT)
                n = dr.opaque(mi.UInt32, self.direct_n)
                # every viewer's pixels in one launch (the frame's layers); streams keyed by the pixel
                # index within its viewer (identical viewers: identical images)
                lay = layered(gbuffers)
                idx = lay.pixel if lay.pixel is not None else dr.arange(mi.UInt32, lay.size)
                k = self._k_pixel if lay.size > 1 else _pixel_direct_kernel
                L = k(sc, light_inputs(sc), diffuse_flags(sc), lay.si, mi.Bool(lay.valid), idx, mix, n,
                      bool(self.direct_lds))
                if len(gbuffers) == 1:
                    out[0] = out[0] + L
                else:
                    out = [o + Lv for o, Lv in zip(out, per_viewer(L, lay.sizes, lay.offsets))]
                st.outputs(*out)
        elif self._sub is not None:
            sub = self._sub.render(ctx, gbuffers, timer)
            out = [a + b for a, b in zip(out, sub)]
        if self.cache is not None:
            self._cells = self.secondary.used_cells()
            self.memory_log.append((int(self.cache.memory_bytes())
                                    + int(self.cache.entries_allocated()) * self.payload_bytes(),
                                    self._cells * 4 * self.secondary.words_per_slot()))
        return out

    # ------------------------------------------------------------------ reports
    def memory_bytes(self) -> int:
        """Primary caches (the on-surface cache and its payloads) + the secondary hash table."""
        return (super().memory_bytes() + (self.secondary.memory_bytes() if self.secondary is not None else 0)
                + (self._sub.memory_bytes() if self._sub is not None else 0))

    def stats(self) -> dict:
        out = super().stats()
        if self.secondary is not None:
            sec = self.secondary
            r = sec.reuse
            out.update({"secondary_cells": float(getattr(self, "_cells", 0)), "secondary_updated": float(sec.updated),
                        "entries_updated": float(self.entries_updated),
                        "secondary_overflow": float(sec.overflow), "secondary_requested": float(sec.requested),
                        "secondary_evicted": float(sec.evicted), "secondary_cell_m": float(sec.h),
                        "secondary_reuse_mean": float(dr.mean(mi.Float(r))[0]) if dr.width(r) else 0.0})
            if self.memory_log:
                out["primary_mb"] = self.memory_log[-1][0] / 2 ** 20
                out["secondary_mb"] = self.memory_log[-1][1] / 2 ** 20
        return out


register("osc-gi", OSCGI, help="GI from primary (on-surface, hemisphere) and secondary (world-grid) radiance caches")
