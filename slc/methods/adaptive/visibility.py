r"""VISIBILITY representation: per-light visibility of the few delta lights
(point, spot, directional) that matter at an entry, plus a residual.

Record (``K + 2`` words, ``K = vis_lights``, default 12)::

    K x [ light index (16) | visibility v (unorm 8) | count (4) | spare (4) ]
    residual irradiance E_r (3 x 18-bit e6m12) | its count C_r (8)
    with environment regions: [ v_u (unorm 16) | its count n_u (8) | spare (8) ]

Shading at a pixel x (no rays): the lights' unoccluded contribution is
evaluated exactly at x (the emitter's own ``sample_direction``, which is
deterministic for a delta light), the visibility comes from the entry:

.. math:: L_o(x) = \sum_{i \le K} f_r(x, \omega_i, \omega_o) \frac{I_i(\omega_i)}{d_i^2}\, v_i
          \;+\; f_r(x, n, \omega_o)\, E_r ,

the residual (light of other emitters and of delta lights outside the list)
treated as arriving along the normal (exact for a Lambertian BSDF).

Update, per light sample of emitter j at the entry (visible V, cosine c):
a delta light in the list updates its visibility,
:math:`v_i \leftarrow v_i + (V - v_i)/\min(n_i + 1, 16)`; a delta light not in
the list replaces the list's least important light when its unoccluded
irradiance is larger (importance = luminance of
:math:`I_i/d_i^2 \cos\theta_i`, exact, recomputed every update); the
evicted light's estimate :math:`E_i v_i` moves into :math:`E_r` and the
newcomer's :math:`E_j V` out of it (energy kept). All other samples feed
the residual's running mean, :math:`E_r \leftarrow E_r + n(\hat E_r - E_r)/C_r` (:math:`C_r`
the sample count, at most 255, or 4 cycles while the entry is moving)
with :math:`\hat E_r = \frac1n\sum_k [k \text{ not in the list}]\, w_k V_k c_k`.

Small sphere lights (:mod:`slc.methods.adaptive.sphere_lights`, ``sph``) are listed
like delta lights where they are small at the entry (:math:`r/d` below
``sph.max_sin``): their :math:`v_i` is the running mean of shadow rays to
sampled points on the sphere and their unoccluded term is the closed form
:math:`\pi L r^2/d^2` towards the current centre.

Bright small regions of the environment map (:mod:`slc.methods.adaptive.env_lights`,
``env``) are listed like delta lights where wholly above the entry's horizon
(index ``env.base + j``, unoccluded term :math:`\Phi_j R_j` along
:math:`\mathbf d_j`); samples of regions above the horizon but not listed
update one shared visible fraction :math:`v_u` (running mean of their shadow
rays, window ``ENV_WINDOW``) instead of :math:`E_r`, and shading adds
:math:`v_u \sum_j f_r(x, \mathbf d_j, \omega_o)\,\Phi_j R_j` over those regions,
each at its own direction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.methods.cones.packing import WordReader, WordWriter, decode_radiance, encode_radiance
from slc.core.keys import keyed_rng, mixed_rng
from slc.methods.adaptive.sampling import LightStats, SampleStats, lum, sampler_of

EMPTY = 0xFFFF
STREAM_VIS = 0x3C6EF372
VIS_WINDOW = 16
ENV_WINDOW = 64             # samples in the running mean of the unlisted regions' visible fraction
RES_MAX_COUNT = 255                 # as the cones' C (8 bits)
MOVED_COUNT = 1             # visibility count of a listed light that moved (its next sample weighs 1/2)
LISTED_SHARE = 0.95         # listed share of an entry's light above which it traces vis_rays of its rays
UNSETTLED_COUNT = 4         # residual count cap of moving entries, in update cycles
RESIDUAL_ALPHA = math.radians(60.0)     # the residual as a lobe (conversion): a 60-degree cone about n


def words(K: int, env: bool = False) -> int:
    """Record words: K lights, the residual (2), and with environment regions
    the unlisted regions' visible fraction (1)."""
    return K + 2 + (1 if env else 0)


class Record:
    """An unpacked VISIBILITY record: the K listed lights (index, visible
    fraction, sample count), the residual irradiance ``E`` and its sample
    count ``C``, and the unlisted environment regions' visible fraction ``vu``
    and its sample count ``nu`` (0 without environment regions)."""

    def __init__(self, idx, vis, cnt, E, C, vu, nu):
        self.idx, self.vis, self.cnt, self.E, self.C, self.vu, self.nu = idx, vis, cnt, E, C, vu, nu


@dataclass
class ListLoop:
    """The state of the update's sample loop (one lane per entry): ``k`` the samples
    drawn; per listed light (lists of K) its emitter ``idx``, visible fraction ``vis``,
    sample count ``cnt``, unoccluded irradiance ``wl`` and importance ``imp`` (its
    irradiance's luminance, -1 for an empty slot); ``S`` the cycle's sum of the other
    samples (the residual's estimate), ``adj`` the energy moved between the list and
    the residual by replacements, ``vu`` and ``nu`` the unlisted environment regions'
    visible fraction and sample count, ``stats`` the choice rule's sums
    (:class:`~slc.methods.adaptive.sampling.SampleStats`) and ``rng`` the random numbers."""
    k: mi.UInt32
    idx: list
    vis: list
    cnt: list
    wl: list
    imp: list
    S: mi.Color3f
    adj: mi.Color3f
    vu: mi.Float
    nu: mi.UInt32
    stats: SampleStats
    rng: mi.PCG32


def unpack(w, K: int, env: bool = False) -> Record:
    idx = [w[i] & 0xFFFF for i in range(K)]
    vis = [mi.Float((w[i] >> 16) & 0xFF) * (1.0 / 255.0) for i in range(K)]
    cnt = [(w[i] >> 24) & 0xF for i in range(K)]
    rd = WordReader([w[K], w[K + 1]])
    E = mi.Color3f(*[decode_radiance(rd.get(18)) for _ in range(3)])
    C = mi.Float(rd.get(8))
    if env:
        x = mi.UInt32(w[K + 2])
        vu, nu = mi.Float(x & 0xFFFF) * (1.0 / 65535.0), mi.UInt32((x >> 16) & 0xFF)
    else:
        vu, nu = dr.zeros(mi.Float, dr.width(C)), dr.zeros(mi.UInt32, dr.width(C))
    return Record(idx, vis, cnt, E, C, vu, nu)


def pack(r: Record, K: int, env: bool = False):
    out = []
    for i in range(K):
        v = mi.UInt32(dr.clip(dr.round(r.vis[i] * 255.0), 0.0, 255.0))
        out.append((mi.UInt32(r.idx[i]) & 0xFFFF) | (v << 16) | (dr.minimum(mi.UInt32(r.cnt[i]), 15) << 24))
    wr = WordWriter(2)
    for ch in range(3):
        wr.put(encode_radiance(r.E[ch]), 18)
    wr.put(mi.UInt32(dr.clip(dr.round(r.C), 0.0, 255.0)), 8)
    out += wr.words
    if env:
        out.append(mi.UInt32(dr.clip(dr.round(r.vu * 65535.0), 0.0, 65535.0))
                   | (dr.minimum(mi.UInt32(r.nu), 255) << 16))
    return out


def empty(n: int, K: int) -> Record:
    return Record([dr.full(mi.UInt32, EMPTY, n) for _ in range(K)], [dr.zeros(mi.Float, n) for _ in range(K)],
                  [dr.zeros(mi.UInt32, n) for _ in range(K)], dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n),
                  dr.zeros(mi.Float, n), dr.zeros(mi.UInt32, n))


def slot(lst, i):
    """Element ``i`` (a per-lane index) of a per-slot list."""
    r = lst[0]
    for j in range(1, len(lst)):
        r = dr.select(i == j, lst[j], r)
    return r


def used_slots(idx: list) -> mi.UInt32:
    """One past the last listed slot of each lane (0 for an empty list): the slots' loops stop
    there (an entry often lists fewer lights than its record has slots)."""
    n = dr.zeros(mi.UInt32, dr.width(idx[0]))
    for i, j in enumerate(idx):
        n = dr.select(j != EMPTY, i + 1, n)
    return n


def _listed(idx: list, wl: list, em: mi.UInt32):
    """(whether emitter ``em`` is in the list ``idx``, its listed unoccluded irradiance ``wl``)."""
    listed, w = mi.Bool(False), dr.zeros(mi.Color3f, dr.width(em))
    for i, j in enumerate(idx):
        h = j == em
        listed |= h
        w = dr.select(h, wl[i], w)
    return listed, w


def light_at(emitters_dr, si, idx, active, sph=None, env=None, delta=True):
    """(direction, I/d^2 RGB) of emitter ``idx`` at ``si``: exact and
    unoccluded for a delta light; for a sphere light of ``sph`` the point-light
    term pi L r^2/d^2 towards its current centre; for a region of the
    environment (``env``, index ``env.base + j``) its direction and
    irradiance per unit cosine Phi_j R_j (0 where inactive or the index is
    empty). ``delta``: the scene has delta emitters (else their
    ``sample_direction``, a virtual call, is not traced)."""
    active = mi.Bool(active) & (mi.UInt32(idx) != EMPTY)
    ii = dr.select(active, idx, 0)
    m_d = mi.Bool(active)
    d = dr.zeros(mi.Vector3f, dr.width(active))
    w = dr.zeros(mi.Color3f, dr.width(active))
    if env is not None:
        is_r, d_r, w_r, _ = env.light(ii, active)
        m_d &= ~is_r
        d, w = dr.select(is_r, d_r, d), dr.select(is_r, w_r, w)
    if sph is not None:
        is_s, d_s, _, E_s = sph.light(si.p, dr.select(m_d, ii, 0), m_d, si.sh_frame.n)
        m_d &= ~is_s
        d, w = dr.select(is_s, d_s, d), dr.select(is_s, E_s, w)
    if not delta:      # only spheres and regions can be listed: no emitter call traced
        return d, w
    ptr = dr.gather(mi.EmitterPtr, emitters_dr, ii, m_d)
    ds, wd = ptr.sample_direction(si, mi.Point2f(0.5, 0.5), m_d)
    ok = m_d & (ds.pdf > 0.0)
    d = dr.select(m_d, ds.d, d)
    w = dr.select(m_d, dr.select(ok, mi.Color3f(wd), 0.0), w)
    return d, w


def traced_rays(rays, s_delta, fresh, all_listable: bool, share: float) -> mi.UInt32:
    """The update rays of VISIBILITY entries given the ray policy's ``rays``: ``share`` of them
    (at least one) where the listed lights bring at least ``LISTED_SHARE`` of the entry's light
    (its statistics' ``s_delta``; a new entry, with no statistics yet, where every light of the
    scene can be listed): their unoccluded light is exact, only visible fractions are learnt."""
    listed = (mi.Float(s_delta) >= LISTED_SHARE) | (mi.Bool(fresh) & all_listable)
    return dr.select(listed, dr.maximum(mi.UInt32(mi.Float(rays) * share), 1), mi.UInt32(rays))


def has_delta(scene: mi.Scene) -> bool:
    """Whether the scene has a delta emitter (point, spot, directional)."""
    return any(bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) for e in scene.emitters())


# ----------------------------------------------------------------------------- update

def update(scene: mi.Scene, rec, si, key, rays, moving, fresh, on, frame: int, seed: int, K: int, sph=None,
           env=None, mix=None):
    """One function because it is one traced update whose stages (unpack, the listed lights'
    irradiance, the sample loop, the residual) share the light list's state; its stages are
    marked by banner comments.

    One update cycle of VISIBILITY records ``rec`` (lists of words, one lane
    per entry) at the entries' points ``si`` (``sph``: the scene's
    :class:`~slc.methods.adaptive.sphere_lights.SphereLights`, or None). A listed light whose unoccluded
    irradiance here is now 0 (switched off, turned or moved away) is dropped
    and reported as motion. Moving entries (the ray policy's state; new
    entries are not capped: their light did not move) cap the residual's
    count at ``UNSETTLED_COUNT`` cycles. Returns (new words, motion,
    stats values). ``env``: the environment's bright regions
    (:class:`~slc.methods.adaptive.env_lights.EnvLights`), listed where wholly above
    the entry's horizon. ``mix``: the random streams' (seed, frame) mix as an
    opaque array (:func:`slc.core.keys.stream_key`; the frozen update's input),
    else computed from ``seed`` and ``frame``."""
    sc = scene
    dl = has_delta(sc)
    poly = sph is not None and sph.poly is not None     # polygon lights listed: samples in solid angle
    N = dr.width(key)
    samp = sampler_of(sc)
    em_dr = sc.emitters_dr()
    valid = mi.Bool(on) & si.is_valid()
    frame_l = si.sh_frame
    nrm = frame_l.n

    # ----------------------- unpack (fresh records start empty)
    hx = env is not None
    r0, e0 = unpack(rec, K, hx), empty(N, K)
    fresh = mi.Bool(fresh)
    idx = [dr.select(fresh, e0.idx[i], r0.idx[i]) for i in range(K)]
    vis = [dr.select(fresh, e0.vis[i], r0.vis[i]) for i in range(K)]
    cnt = [dr.select(fresh, e0.cnt[i], r0.cnt[i]) for i in range(K)]
    E, C = dr.select(fresh, e0.E, r0.E), dr.select(fresh, e0.C, r0.C)
    vu, nu = dr.select(fresh, e0.vu, r0.vu), dr.select(fresh, e0.nu, r0.nu)

    # ----------------------- the listed lights' exact unoccluded irradiance here
    # one emitter call site in a loop over the list: a call is traced once per emitter
    # instance, so K call sites would trace K times as much
    n_used = used_slots(idx)

    def lcond(i, wl):
        return i < n_used

    def lbody(i, wl):
        d, w = light_at(em_dr, si, slot(idx, i), valid, sph, env, dl)
        wc = w * dr.maximum(dr.dot(d, nrm), 0.0)
        return i + 1, [dr.select(i == j, wc, wl[j]) for j in range(K)]

    _, wl = dr.while_loop(state=(mi.UInt32(0), [dr.zeros(mi.Color3f, N) for _ in range(K)]), cond=lcond, body=lbody)
    imp = []
    gone = mi.Bool(False)
    if sph is not None:
        # a listed light that moved: its visible fraction starts again from its next samples
        # (count MOVED_COUNT) and the entry reports motion (more rays for its next updates);
        # its unoccluded term follows the light at once
        for i in range(K):
            mv = sph.moved_at(dr.select(idx[i] != EMPTY, idx[i], 0), valid & (idx[i] != EMPTY))
            cnt[i] = dr.select(mv, dr.minimum(cnt[i], MOVED_COUNT), cnt[i])
            gone |= mv
    for i in range(K):
        dead = valid & (idx[i] != EMPTY) & ~(lum(wl[i]) > 0.0)
        gone |= dead & (vis[i] > 0.0)
        idx[i] = dr.select(dead, EMPTY, idx[i])
        imp.append(dr.select(idx[i] != EMPTY, lum(wl[i]), -1.0))

    if mix is None:
        rng = keyed_rng(key, seed, frame, STREAM_VIS)
    else:                              # keyed_rng with the mix given
        rng = mixed_rng(key, mix)
    stats = LightStats(sc, si, sph, env)
    S = dr.zeros(mi.Color3f, N)
    adj = dr.zeros(mi.Color3f, N)

    # ----------------------- light samples, one at a time per entry
    def cond(ls: ListLoop):
        return ls.k < rays

    def body(ls: ListLoop):
        k, idx, vis, cnt, wl, imp, S, adj, vu, nu, rng = (ls.k, ls.idx, ls.vis, ls.cnt, ls.wl, ls.imp, ls.S, ls.adj,
                                                          ls.vu, ls.nu, ls.rng)
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        act = valid & (k < rays)
        ds, w, ok, em = samp.sample(si, u, act, solid_angle=poly)
        ok &= dr.all(dr.isfinite(w))
        V = ok & ~sc.ray_test(si.spawn_ray_to(ds.p), ok)
        cos = dr.maximum(dr.dot(ds.d, nrm), 0.0)
        Vf = dr.select(V, 1.0, 0.0)
        delta = ok & ds.delta
        # the light's own unoccluded irradiance (w has the choice pmf ds.pdf in it)
        w1 = w * ds.pdf * cos
        if sph is not None:
            # a small sphere light is listed as a delta light, with its closed-form term; a
            # listed polygon light's term is the list's (the same formula at the same point)
            listed, wl_em = _listed(idx, wl, em)
            is_s, d_s, sin_a, E_s = sph.light(si.p, em, ok & ~ds.delta, nrm, poly_active=~listed)
            on_p = sph.polygon(em, is_s)
            small = is_s & ((sin_a < sph.max_sin) | on_p)
            delta |= small
            w1 = dr.select(small, dr.select(on_p & listed, wl_em, E_s * dr.maximum(dr.dot(d_s, nrm), 0.0)), w1)
        if poly:
            # a polygon light's visible fraction is the ratio of its visible to its unoccluded
            # irradiance: the sample's step is weighted by its share r of the light's exact term
            # (E[r] = 1), so that v settles where E[r (V - v)] = 0, v = E[r V] / E[r]
            on_p = sph.polygon(em, ok & ~ds.delta)
            i_exact = lum(w1)
            r_k = lum(w * cos) * samp.choice_pmf(em, on_p) / dr.select(i_exact > 0.0, i_exact, 1.0)
            step = dr.select(on_p, dr.select(i_exact > 0.0, r_k, 0.0), 1.0)
        region = mi.Bool(False)
        if env is not None:
            # a sample inside a bright region of the environment (wholly above the horizon)
            # is that region's sample
            region, li, _, E_j = env.sample_listable(ds.d, em, nrm, ok & ~delta)
            delta |= region
            em = dr.select(region, li, em)
            w1 = dr.select(region, E_j, w1)
        # the choice rule's statistics
        ls.stats = stats.observe(ls.stats, ds, w, V, frame_l.to_local(ds.d))
        i1 = lum(w1)
        hit = mi.Bool(False)
        for i in range(K):
            h = delta & (idx[i] == em)
            hit |= h
            a = dr.rcp(mi.Float(dr.minimum(cnt[i] + 1, VIS_WINDOW)))
            if poly:
                a = dr.minimum(a * step, 1.0)
            vis[i] = dr.select(h, dr.fma(a, Vf - vis[i], vis[i]), vis[i])
            cnt[i] = dr.select(h, dr.minimum(cnt[i] + 1, 15), cnt[i])
        # least important listed light
        jmin, imin = mi.UInt32(0), mi.Float(imp[0])
        for i in range(1, K):
            b = imp[i] < imin
            imin = dr.select(b, imp[i], imin)
            jmin = dr.select(b, i, jmin)
        rep = delta & ~hit & (i1 > imin) & (cos > 0.0)
        for i in range(K):
            r = rep & (jmin == i)
            # energy moves between the list and E_r; a region's energy is never in E_r
            # (unlisted regions are the closed form times vu)
            out_r = env.is_region(idx[i]) if env is not None else mi.Bool(False)
            adj += dr.select(r & (idx[i] != EMPTY) & ~out_r, wl[i] * vis[i], 0.0) \
                - dr.select(r & ~region, w1 * Vf, 0.0)
            idx[i] = dr.select(r, mi.UInt32(em), idx[i])
            vis[i] = dr.select(r, Vf, vis[i])
            cnt[i] = dr.select(r, 1, cnt[i])
            wl[i] = dr.select(r, w1, wl[i])
            imp[i] = dr.select(r, i1, imp[i])
        handled = hit | rep
        # an unlisted region's sample: the unlisted regions' visible fraction
        unl = region & ~handled
        au = dr.rcp(mi.Float(dr.minimum(nu + 1, ENV_WINDOW)))
        vu = dr.select(unl, dr.fma(au, Vf - vu, vu), vu)
        nu = dr.select(unl, dr.minimum(nu + 1, 255), nu)
        S += dr.select(V & ~handled & ~unl, w * cos, 0.0)
        ls.k, ls.idx, ls.vis, ls.cnt, ls.wl, ls.imp, ls.S, ls.adj, ls.vu, ls.nu, ls.rng = \
            k + 1, idx, vis, cnt, wl, imp, S, adj, vu, nu, rng
        return (ls,)

    ls, = dr.while_loop(state=(ListLoop(mi.UInt32(0), idx, vis, cnt, wl, imp, S, adj, vu, nu, stats.init(N), rng),),
                        cond=cond, body=body)
    idx, vis, cnt, S, adj, vu, nu = ls.idx, ls.vis, ls.cnt, ls.S, ls.adj, ls.vu, ls.nu

    # ----------------------- the residual's running mean (with the energy moved by swaps)
    # the count is in samples (as the cones' C): a cycle of n samples weighs n / C
    n = mi.Float(dr.maximum(mi.UInt32(rays), 1))
    cap = dr.select(mi.Bool(moving) | gone, float(UNSETTLED_COUNT) * n, float(RES_MAX_COUNT))
    C = dr.minimum(dr.minimum(C, cap - n) + n, cap)
    E = dr.maximum(E + adj, 0.0)
    E = E + (S / n - E) * dr.minimum(n * dr.rcp(dr.maximum(C, 1.0)), 1.0)
    out = pack(Record(idx, vis, cnt, E, C, vu, nu), K, hx)
    return out, gone, ls.stats.values()


# ----------------------------------------------------------------------------- shading

def residual(rec: Record, nrm, env, active) -> mi.Color3f:
    """The record's irradiance not from listed lights at normal ``nrm``: the
    residual E_r plus the unlisted environment regions' closed form times
    their visible fraction."""
    E = mi.Color3f(rec.E)
    if env is not None:
        E += env.unlisted_irradiance(nrm, rec.idx, active) * rec.vu
    return E


# ----------------------------------------------------------------------------- conversion

def lobes(scene: mi.Scene, rec, si, active, K: int, sph=None, env=None):
    """The record as lobes (local direction, half-angle, integrated radiance RGB,
    mask): one Dirac lobe per listed light (I/d^2 v at the entry) and the
    residual (with the unlisted regions) as a 60-degree cone about the normal
    (its irradiance / mean cosine)."""
    em_dr, dl = scene.emitters_dr(), has_delta(scene)
    r = unpack(rec, K, env is not None)
    out = []
    for i in range(K):
        m = mi.Bool(active) & (r.idx[i] != EMPTY)
        d, w = light_at(em_dr, si, r.idx[i], m, sph, env, dl)
        out.append((si.sh_frame.to_local(d), mi.Float(0.0), w * r.vis[i], m & (dr.max(w * r.vis[i]) > 0.0)))
    mean_cos = 0.5 * (1.0 + math.cos(RESIDUAL_ALPHA))
    E = residual(r, si.sh_frame.n, env, active)
    out.append((mi.Vector3f(0.0, 0.0, 1.0), mi.Float(RESIDUAL_ALPHA), E * (1.0 / mean_cos),
                mi.Bool(active) & (dr.max(E) > 0.0)))
    return out


def from_irradiance(E, n: int, K: int, env: bool = False):
    """A record with no listed light and residual ``E`` (the energy of another
    representation at the normal); the lights come in with the next samples
    (the unlisted regions' visible fraction starts with no sample)."""
    r = empty(n, K)
    r.E, r.C = mi.Color3f(E), dr.full(mi.Float, 4.0, n)
    return pack(r, K, env)
