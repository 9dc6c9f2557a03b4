r"""The update cycle of VISIBILITY records (:mod:`slc.methods.adaptive.visibility`), in stages:

1. :func:`start`: the records unpacked (fresh ones empty);
2. :func:`listed_terms`: the listed lights' exact unoccluded irradiance at the entry, dropping
   the lights gone dark and restarting the visibility of lights that moved;
3. the sample loop: per sample, :func:`classify` (the sample's light, side, exact term,
   step) and :func:`take` (the list's visible fractions, a replacement, the residual's sums);
4. :func:`residual_mean`: the residual's running mean with the energy moved by replacements.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core.keys import mixed_rng, stream_key
from slc.methods.adaptive.sampling import LightStats, SampleStats, lum, sampler_of
from slc.methods.adaptive.visibility.lights import SMALL_SIN, footprint_ray, has_delta, light_irradiance
from slc.methods.adaptive.visibility.record import (EMPTY, ENV_WINDOW, MOVED_COUNT, RES_MAX_COUNT,
                                                    UNSETTLED_COUNT, VIS_COUNT_MAX, VIS_WINDOW, Record, empty,
                                                    listed, pack, slot, unpack, used_slots)
from slc.scene.bsdf_table import facing, two_sided

STREAM_VIS = 0x3C6EF372


@dataclass
class VisParams:
    """The fixed inputs of the update: ``K`` slots, the scene's ``sph`` (sphere and polygon lights,
    :class:`~slc.lib.lights.sphere_lights.SphereLights`) and ``env`` (the environment's bright
    regions, :class:`~slc.lib.lights.env_lights.EnvLights`), None where absent."""
    K: int
    sph: object = None
    env: object = None


@dataclass
class VisLanes:
    """The entries, one lane each: ``rec`` their records' words, ``si`` their surface points,
    ``key`` their keys, ``rays`` the rays each traces, ``moving`` the policy's motion state,
    ``fresh`` a new record, ``on`` the live lanes, ``texel`` their footprints (world-space
    texel edges; None: every sample from the entry's point)."""
    rec: list
    si: mi.SurfaceInteraction3f
    key: mi.UInt32
    rays: mi.UInt32
    moving: mi.Bool
    fresh: mi.Bool
    on: mi.Bool
    texel: mi.Float | None = None


class Site:
    """What every stage reads of the scene and the entries: the sampler, the emitters, the
    live lanes ``valid``, the entries' frame and normal, the two-sided lanes ``two`` (None:
    the scene has no two-sided BSDF) and the record's layout (``hx`` environment regions,
    ``back`` the residual behind the surface)."""

    def __init__(self, scene: mi.Scene, e: VisLanes, p: VisParams):
        self.scene, self.p = scene, p
        self.dl = has_delta(scene)
        self.poly = p.sph is not None and p.sph.poly is not None    # polygon lights listed: samples in solid angle
        self.samp = sampler_of(scene)
        self.em_dr = scene.emitters_dr()
        self.valid = mi.Bool(e.on) & e.si.is_valid()
        self.frame_l = e.si.sh_frame
        self.nrm = self.frame_l.n
        self.two = two_sided(scene, e.si.bsdf(), self.valid)       # entries on two-sided BSDFs
        self.back = self.two is not None
        self.hx = p.env is not None


@dataclass
class ListLoop:
    """The state of the update's sample loop (one lane per entry): ``k`` the samples
    drawn; per listed light (lists of K) its emitter ``idx``, visible fraction ``vis``,
    sample count ``cnt``, unoccluded irradiance ``wl`` and importance ``imp`` (its
    irradiance's luminance, -1 for an empty slot); ``S`` the cycle's sum of the other
    samples (the residual's estimate; ``Sb`` behind the surface), ``adj`` (``adjb``) the
    energy moved between the list and the residual by replacements, ``vu`` and ``nu`` the
    unlisted environment regions' visible fraction and sample count, ``vs`` and ``ns`` the
    sky's, ``stats`` the choice rule's sums (:class:`~slc.methods.adaptive.sampling.SampleStats`) and ``rng`` the random numbers."""
    k: mi.UInt32
    idx: list
    vis: list
    cnt: list
    wl: list
    imp: list
    S: mi.Color3f
    Sb: mi.Color3f
    adj: mi.Color3f
    adjb: mi.Color3f
    vu: mi.Float
    nu: mi.UInt32
    vs: mi.Float
    ns: mi.UInt32
    stats: SampleStats
    rng: mi.PCG32


@dataclass
class Sample:
    """One light sample of every entry, classified: ``ds``, ``w`` (radiance over density), ``ok``
    (a sample was drawn), ``em`` its light (a region's light index for a sample in a listed
    region), ``delta`` a listable light (delta, small sphere, polygon, region), ``region`` in a
    bright region of the environment, ``hard`` a light with hard shadow edges, ``cos`` the cosine
    on the sample's side, ``behind`` behind a two-sided entry, ``w1`` the light's exact unoccluded
    irradiance here, ``step`` the visible fraction's step weight (polygon lights' share of their
    exact term, else 1), ``sky`` the environment's outside its kept regions, ``sky_E`` the sky's
    exact unoccluded irradiance on the sample's side and ``sky_step`` the sample's step weight (its
    share of that), ``V`` visible."""
    ds: mi.DirectionSample3f
    w: mi.Color3f
    ok: mi.Bool
    em: mi.UInt32
    delta: mi.Bool
    region: mi.Bool
    hard: mi.Bool
    cos: mi.Float
    behind: mi.Bool
    w1: mi.Color3f
    step: mi.Float | None
    sky: mi.Bool
    sky_E: mi.Color3f | None
    sky_step: mi.Float | None
    V: mi.Bool | None = None


# ----------------------------------------------------------------------------- stages

def start(site: Site, e: VisLanes) -> Record:
    """The records unpacked; fresh records start empty."""
    K, N = site.p.K, dr.width(e.key)
    r0, e0 = unpack(e.rec, K, site.hx, site.back), empty(N, K)
    fresh = mi.Bool(e.fresh)
    sel = lambda a, b: dr.select(fresh, a, b)   # noqa: E731
    return Record([sel(e0.idx[i], r0.idx[i]) for i in range(K)], [sel(e0.vis[i], r0.vis[i]) for i in range(K)],
                  [sel(e0.cnt[i], r0.cnt[i]) for i in range(K)], sel(e0.E, r0.E), sel(e0.C, r0.C),
                  sel(e0.vu, r0.vu), sel(e0.nu, r0.nu), sel(e0.Eb, r0.Eb), sel(e0.vs, r0.vs), sel(e0.ns, r0.ns),
                  sel(e0.conv, r0.conv))


def listed_terms(site: Site, e: VisLanes, r: Record):
    """The listed lights' exact unoccluded irradiance ``wl`` at the entries and their importance
    ``imp`` (luminance, -1 for an empty slot); a light gone dark is dropped from ``r``, a light
    that moved restarts its count. Returns (wl, imp, gone: the entries that saw either)."""
    K, N, sph, env = site.p.K, dr.width(e.key), site.p.sph, site.p.env
    idx, vis, cnt = r.idx, r.vis, r.cnt
    n_used = used_slots(idx)

    # one emitter call site in a loop over the list: a call is traced once per emitter
    # instance, so K call sites would trace K times as much
    def lcond(i, wl):
        return i < n_used

    def lbody(i, wl):
        wc = light_irradiance(site.em_dr, e.si, slot(idx, i), site.valid, sph, env, site.dl, site.nrm, site.two)
        return i + 1, [dr.select(i == j, wc, wl[j]) for j in range(K)]

    _, wl = dr.while_loop(state=(mi.UInt32(0), [dr.zeros(mi.Color3f, N) for _ in range(K)]), cond=lcond, body=lbody)
    imp = []
    gone = mi.Bool(False)
    if sph is not None:
        # a listed light that moved: its visible fraction starts again from its next samples
        # (count MOVED_COUNT) and the entry reports motion (more rays for its next updates);
        # its unoccluded term follows the light at once
        for i in range(K):
            mv = sph.moved_at(dr.select(idx[i] != EMPTY, idx[i], 0), site.valid & (idx[i] != EMPTY))
            cnt[i] = dr.select(mv, dr.minimum(cnt[i], MOVED_COUNT), cnt[i])
            gone |= mv
    for i in range(K):
        dead = site.valid & (idx[i] != EMPTY) & ~(lum(wl[i]) > 0.0)
        gone |= dead & (vis[i] > 0.0)
        idx[i] = dr.select(dead, EMPTY, idx[i])
        imp.append(dr.select(idx[i] != EMPTY, lum(wl[i]), -1.0))
    return wl, imp, gone


def classify(site: Site, e: VisLanes, ls: ListLoop) -> Sample:
    """Draw one light sample per entry and classify it (:class:`Sample`, without ``V``)."""
    sph, env, nrm, two = site.p.sph, site.p.env, site.nrm, site.two
    u = mi.Point2f(ls.rng.next_float32(), ls.rng.next_float32())
    act = site.valid & (ls.k < e.rays)
    ds, w, ok, em = site.samp.sample(e.si, u, act, solid_angle=site.poly)
    ok &= dr.all(dr.isfinite(w))
    hard = ok & ds.delta            # a light whose shadow edges are hard (and a small region, below)
    n_s = facing(nrm, ds.d, two)    # the sample's side of a two-sided entry
    behind = (two & (dr.dot(ds.d, nrm) < 0.0)) if site.back else mi.Bool(False)
    cos = dr.maximum(dr.dot(ds.d, n_s), 0.0)
    delta = ok & ds.delta
    # the light's own unoccluded irradiance (w has the choice pmf ds.pdf in it)
    w1 = w * ds.pdf * cos
    if sph is not None:
        # a small sphere light is listed as a delta light, with its closed-form term; a
        # listed polygon light's term is the list's (the same formula at the same point)
        in_list, wl_em = listed(ls.idx, ls.wl, em)
        is_s, d_s, sin_a, E_s = sph.light(e.si.p, em, ok & ~ds.delta, n_s, poly_active=~in_list)
        on_p = sph.polygon(em, is_s)
        small = is_s & ((sin_a < sph.max_sin) | on_p)
        delta |= small
        w1 = dr.select(small, dr.select(on_p & in_list, wl_em, E_s * dr.maximum(dr.dot(d_s, n_s), 0.0)), w1)
    step = None
    if site.poly:
        # a polygon light's visible fraction is the ratio of its visible to its unoccluded
        # irradiance: the sample's step is weighted by its share r of the light's exact term
        # (E[r] = 1), so that v settles where E[r (V - v)] = 0, v = E[r V] / E[r]
        on_p = sph.polygon(em, ok & ~ds.delta)
        i_exact = lum(w1)
        r_k = lum(w * cos) * site.samp.choice_pmf(em, on_p) / dr.select(i_exact > 0.0, i_exact, 1.0)
        step = dr.select(on_p, dr.select(i_exact > 0.0, r_k, 0.0), 1.0)
    region, sky, sky_E, sky_step = mi.Bool(False), mi.Bool(False), None, None
    if env is not None and env.has_sky:
        # a sample of the environment outside its kept regions is the sky's: its step is its
        # share of the sky's exact unoccluded irradiance (E[r] = 1), as a polygon light's
        sky = env.sky_sample(ds.d, em, ok & ~ds.delta)
        sky_E = env.sky_irradiance(n_s, sky)
        E_s = lum(sky_E)
        r_s = lum(w * cos) * site.samp.choice_pmf(em, sky) / dr.select(E_s > 0.0, E_s, 1.0)
        sky_step = dr.select(E_s > 0.0, r_s, 0.0)
    if env is not None:
        # a sample inside a bright region of the environment (wholly above the horizon)
        # is that region's sample
        region, li, _, E_j = env.sample_listable(ds.d, em, n_s, ok & ~delta)
        delta |= region
        hard |= region & (env.light(li, region)[3] < SMALL_SIN)
        em = dr.select(region, li, em)
        w1 = dr.select(region, E_j, w1)
    return Sample(ds, w, ok, em, delta, region, hard, cos, behind, w1, step, sky, sky_E, sky_step)


def take(site: Site, ls: ListLoop, s: Sample, conv: mi.Bool, sky_cap: mi.Float) -> ListLoop:
    """One classified, shadow-tested sample into the loop's state: a listed light's visible
    fraction, the replacement of the least important listed light by a more important
    listable one (the energy moving between the list and the residual), the unlisted regions'
    visible fraction, the sky's visible fraction (its samples' weight sum capped at
    ``sky_cap``), the residual's sums. ``conv``: the entries whose record was converted
    from another representation and not updated since (its residual holds all of its light,
    regions and sky included)."""
    K, env = site.p.K, site.p.env
    idx, vis, cnt, wl, imp = ls.idx, ls.vis, ls.cnt, ls.wl, ls.imp
    Vf = dr.select(s.V, 1.0, 0.0)
    i1 = lum(s.w1)
    hit = mi.Bool(False)
    for i in range(K):
        h = s.delta & (idx[i] == s.em)
        hit |= h
        a = dr.rcp(mi.Float(dr.minimum(cnt[i] + 1, VIS_WINDOW)))
        if s.step is not None:
            a = dr.minimum(a * s.step, 1.0)
        vis[i] = dr.select(h, dr.fma(a, Vf - vis[i], vis[i]), vis[i])
        cnt[i] = dr.select(h, dr.minimum(cnt[i] + 1, VIS_COUNT_MAX), cnt[i])
    # least important listed light
    jmin, imin = mi.UInt32(0), mi.Float(imp[0])
    for i in range(1, K):
        b = imp[i] < imin
        imin = dr.select(b, imp[i], imin)
        jmin = dr.select(b, i, jmin)
    rep = s.delta & ~hit & (i1 > imin) & (s.cos > 0.0)
    for i in range(K):
        r = rep & (jmin == i)
        # energy moves between the list and E_r; a region's energy is never in E_r
        # (unlisted regions are the closed form times vu) but in a converted record's
        # (behind a two-sided entry: the residual of the newcomer's side)
        out_r = env.is_region(idx[i]) if env is not None else mi.Bool(False)
        moved = dr.select(r & (idx[i] != EMPTY) & ~out_r, wl[i] * vis[i], 0.0) \
            - dr.select(r & (~s.region | conv), s.w1 * Vf, 0.0)
        ls.adj += dr.select(s.behind, 0.0, moved)
        ls.adjb += dr.select(s.behind, moved, 0.0)
        idx[i] = dr.select(r, mi.UInt32(s.em), idx[i])
        vis[i] = dr.select(r, Vf, vis[i])
        cnt[i] = dr.select(r, 1, cnt[i])
        wl[i] = dr.select(r, s.w1, wl[i])
        imp[i] = dr.select(r, i1, imp[i])
    handled = hit | rep
    # an unlisted region's sample: the unlisted regions' visible fraction
    unl = s.region & ~handled
    au = dr.rcp(mi.Float(dr.minimum(ls.nu + 1, ENV_WINDOW)))
    ls.vu = dr.select(unl, dr.fma(au, Vf - ls.vu, ls.vu), ls.vu)
    ls.nu = dr.select(unl, dr.minimum(ls.nu + 1, 255), ls.nu)
    res = s.V & ~handled & ~unl
    if s.sky_step is not None:
        # a sample of the sky: the sky's visible fraction (a ratio estimator, as a polygon light's);
        # a converted record's first one takes the sky's estimate out of the residual, as a
        # listed light does
        first = s.sky & (ls.ns == 0) & conv
        took = dr.select(first, s.sky_E * Vf, 0.0)
        ls.adj -= dr.select(s.behind, 0.0, took)
        ls.adjb -= dr.select(s.behind, took, 0.0)
        # The visible fraction is the samples' weighted mean, v_s = sum r V / sum r, kept
        # incrementally with the weights' running sum W (``ns``, in 1/16, at most ``sky_cap``, as
        # the residual's count): v_s <- v_s + (r / W') (V - v_s), W' = min(W + r, cap).
        W = mi.Float(ls.ns) * (1.0 / 16.0)
        W1 = dr.minimum(W + s.sky_step, sky_cap)
        a_s = dr.select(W1 > 0.0, s.sky_step / dr.select(W1 > 0.0, W1, 1.0), 0.0)
        ls.vs = dr.select(s.sky, dr.fma(dr.minimum(a_s, 1.0), Vf - ls.vs, ls.vs), ls.vs)
        ls.ns = dr.select(s.sky, mi.UInt32(dr.minimum(dr.round(W1 * 16.0), 65535.0)), ls.ns)
        res &= ~s.sky
    ls.S += dr.select(res & ~s.behind, s.w * s.cos, 0.0)
    ls.Sb += dr.select(res & s.behind, s.w * s.cos, 0.0)
    ls.idx, ls.vis, ls.cnt, ls.wl, ls.imp = idx, vis, cnt, wl, imp
    return ls


def residual_mean(site: Site, e: VisLanes, r: Record, ls: ListLoop, gone: mi.Bool) -> Record:
    """The residual's running mean over the cycle's samples, with the energy moved by
    replacements; the count is in samples (as the cones' C): a cycle of n samples weighs
    n / C, capped at ``UNSETTLED_COUNT`` cycles for moving entries."""
    n = mi.Float(dr.maximum(mi.UInt32(e.rays), 1))
    cap = dr.select(mi.Bool(e.moving) | gone, float(UNSETTLED_COUNT) * n, float(RES_MAX_COUNT))
    C = dr.minimum(dr.minimum(r.C, cap - n) + n, cap)
    a = dr.minimum(n * dr.rcp(dr.maximum(C, 1.0)), 1.0)
    E = dr.maximum(r.E + ls.adj, 0.0)
    E = E + (ls.S / n - E) * a
    Eb = r.Eb
    if site.back:
        Eb = dr.maximum(Eb + ls.adjb, 0.0)
        Eb = Eb + (ls.Sb / n - Eb) * a
    return Record(ls.idx, ls.vis, ls.cnt, E, C, ls.vu, ls.nu, Eb, ls.vs, ls.ns, dr.zeros(mi.Bool, dr.width(C)))


# ----------------------------------------------------------------------------- the cycle

def update(scene: mi.Scene, e: VisLanes, p: VisParams, mix: mi.UInt32):
    """One update cycle of VISIBILITY records (the module's stages). A listed light whose
    unoccluded irradiance here is now 0 (switched off, turned or moved away) is dropped and
    reported as motion. Moving entries (the ray policy's state; new entries are not capped:
    their light did not move) cap the residual's count at ``UNSETTLED_COUNT`` cycles. ``mix``:
    the random streams' (seed, frame) mix (:func:`mix_of`). With the entries' footprints
    (``e.texel``), a sample of a light with hard shadow edges (a delta light; a region of the
    environment of angular radius below :data:`SMALL_SIN`, the sun) is shadow-tested from a
    point of the entry's footprint (:func:`~slc.methods.adaptive.visibility.lights.footprint_ray`),
    so that an entry that a shadow edge crosses keeps a visible fraction between 0 and 1 and its
    pixels trace that light's visibility (:mod:`slc.methods.adaptive.visibility.shading`).
    Returns (new words, motion, statistics)."""
    site = Site(scene, e, p)
    N = dr.width(e.key)
    r = start(site, e)
    # the sky's weight sum's cap: as the residual's count (about that many samples)
    n_s = mi.Float(dr.maximum(mi.UInt32(e.rays), 1))
    sky_cap = dr.select(mi.Bool(e.moving), float(UNSETTLED_COUNT) * n_s, float(RES_MAX_COUNT))
    wl, imp, gone = listed_terms(site, e, r)
    stats = LightStats(scene, e.si, p.sph, p.env, site.two)

    # ----------------------- light samples, one at a time per entry
    def cond(ls: ListLoop):
        return ls.k < e.rays

    def body(ls: ListLoop):
        s = classify(site, e, ls)
        s.V = s.ok & ~scene.ray_test(footprint_ray(e.si, s.ds, s.hard, e.texel, e.key, mix, ls.k), s.ok)
        # the choice rule's statistics
        ls.stats = stats.observe(ls.stats, s.ds, s.w, s.V, site.frame_l.to_local(s.ds.d))
        ls = take(site, ls, s, r.conv, sky_cap)
        ls.k = ls.k + 1
        return (ls,)

    S, Sb = dr.zeros(mi.Color3f, N), dr.zeros(mi.Color3f, N)
    adj, adjb = dr.zeros(mi.Color3f, N), dr.zeros(mi.Color3f, N)
    ls, = dr.while_loop(state=(ListLoop(mi.UInt32(0), r.idx, r.vis, r.cnt, wl, imp, S, Sb, adj, adjb, r.vu, r.nu,
                                        r.vs, r.ns, stats.init(N), mixed_rng(e.key, mix)),), cond=cond, body=body)
    out = pack(residual_mean(site, e, r, ls, gone), p.K, site.hx, site.back, dither=ls.rng.next_uint32())
    return out, gone, ls.stats


def mix_of(seed: int, frame: int) -> mi.UInt32:
    """The update's random streams' (seed, frame) mix (:func:`slc.core.keys.stream_key`)."""
    return stream_key(seed, frame, STREAM_VIS)
