"""The listed lights of VISIBILITY records at a point: their exact unoccluded terms
(:func:`light_at`, :func:`light_irradiance`), the shadow rays of the update's samples
(:func:`footprint_ray`) and the rays an entry traces (:func:`traced_rays`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.adaptive.visibility.record import EMPTY
from slc.scene.bsdf_table import facing

SMALL_SIN = 0.04            # sine of the angular radius of a region whose shadow edges are traced per pixel
FOOTPRINT = 2.0            # the shadow-tested footprint of an entry, in texels (an edge near it is caught too)
LISTED_SHARE = 0.95         # listed share of an entry's light above which it traces vis_rays of its rays


def has_delta(scene: mi.Scene) -> bool:
    """Whether the scene has a delta emitter (point, spot, directional)."""
    return any(bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) for e in scene.emitters())


def light_at(emitters_dr, si, idx, active, sph=None, env=None, delta=True, n=None, reach=False):
    """(direction, I/d^2 RGB) of emitter ``idx`` at ``si``: exact and
    unoccluded for a delta light; for a sphere light of ``sph`` the point-light
    term pi L r^2/d^2 towards its current centre; for a polygon light of ``sph`` its
    vector irradiance clipped to the hemisphere of ``n`` (default: the shading normal);
    for a region of the environment (``env``, index ``env.base + j``) its direction and
    irradiance per unit cosine Phi_j R_j (0 where inactive or the index is
    empty). ``delta``: the scene has delta emitters (else their
    ``sample_direction``, a virtual call, is not traced). With ``reach``, also the distance
    along the direction to a delta light or region (inf for one at infinity) and the mask of
    the lights whose shadow edges are hard: delta lights and regions of angular radius below
    :data:`SMALL_SIN` (the sun)."""
    active = mi.Bool(active) & (mi.UInt32(idx) != EMPTY)
    ii = dr.select(active, idx, 0)
    m_d = mi.Bool(active)
    N = dr.width(active)
    d = dr.zeros(mi.Vector3f, N)
    w = dr.zeros(mi.Color3f, N)
    dist, hard = dr.full(mi.Float, dr.inf, N), dr.zeros(mi.Bool, N)
    if env is not None:
        is_r, d_r, w_r, s_r = env.light(ii, active)
        m_d &= ~is_r
        d, w = dr.select(is_r, d_r, d), dr.select(is_r, w_r, w)
        hard |= is_r & (s_r < SMALL_SIN)
    if sph is not None:
        is_s, d_s, _, E_s = sph.light(si.p, dr.select(m_d, ii, 0), m_d, si.sh_frame.n if n is None else n)
        m_d &= ~is_s
        d, w = dr.select(is_s, d_s, d), dr.select(is_s, E_s, w)
    if delta:          # (else only spheres and regions can be listed: no emitter call traced)
        ptr = dr.gather(mi.EmitterPtr, emitters_dr, ii, m_d)
        ds, wd = ptr.sample_direction(si, mi.Point2f(0.5, 0.5), m_d)
        ok = m_d & (ds.pdf > 0.0)
        d = dr.select(m_d, ds.d, d)
        w = dr.select(m_d, dr.select(ok, mi.Color3f(wd), 0.0), w)
        dist = dr.select(m_d, ds.dist, dist)
        hard |= m_d
    return (d, w, dist, hard) if reach else (d, w)


def light_irradiance(emitters_dr, si, idx, active, sph, env, delta, nrm, two):
    r"""The unoccluded irradiance (RGB, cosine included) of emitter ``idx`` at the entries ``si``
    of normal ``nrm`` (:func:`light_at`); on the ``two`` lanes (two-sided BSDFs, None: none) a
    light counts from either hemisphere: :math:`|\cos\theta|`, and a polygon light's parts
    clipped to the hemisphere in front and behind are added."""
    d, w = light_at(emitters_dr, si, idx, active, sph, env, delta, n=nrm)
    E = w * dr.maximum(dr.dot(d, facing(nrm, d, two)), 0.0)
    if two is not None and sph is not None and sph.poly is not None:
        back = sph.polygon(dr.select(mi.Bool(active), idx, 0), mi.Bool(active) & two & (mi.UInt32(idx) != EMPTY))
        _, d_b, w_b = sph.poly.light(sph.table, si.p, -nrm, idx, back)
        E += dr.select(back, w_b * dr.maximum(-dr.dot(d_b, nrm), 0.0), 0.0)
    return E


def footprint_ray(si, ds, hard, texel, key, mix, k) -> mi.Ray3f:
    """The shadow ray of a light sample ``ds`` at the entries ``si``: from the entry's point,
    or for a light with hard shadow edges (``hard``; with the entries' footprints ``texel``,
    world-space texel edges) from a point of the entry's footprint in its tangent plane,
    placed by a hash of (key, mix, sample index ``k``)."""
    ray = si.spawn_ray_to(ds.p)
    if texel is None:
        return ray
    h0, h1 = mi.sample_tea_32(mi.UInt32(key), mi.UInt32(mix) + mi.UInt32(k) * 0x9E3779B9, 4)
    j = (mi.Point2f(mi.Float(h0 >> 8), mi.Float(h1 >> 8)) * (1.0 / 16777216.0) - 0.5) * (mi.Float(texel) * FOOTPRINT)
    o = ray.o + si.sh_frame.s * j.x + si.sh_frame.t * j.y
    v = ds.p - o
    dist = dr.norm(v)
    hard = mi.Bool(hard)
    return mi.Ray3f(dr.select(hard, o, ray.o), dr.select(hard, v / dr.select(dist > 0.0, dist, 1.0), ray.d),
                    dr.select(hard, dist * (1.0 - mi.math.ShadowEpsilon), ray.maxt), ray.time, ray.wavelengths)


def traced_rays(rays, s_delta, fresh, all_listable: bool, share: float) -> mi.UInt32:
    """The update rays of VISIBILITY entries given the ray policy's ``rays``: ``share`` of them
    (at least one) where the listed lights bring at least ``LISTED_SHARE`` of the entry's light
    (its statistics' ``s_delta``; a new entry, with no statistics yet, where every light of the
    scene can be listed): their unoccluded light is exact, only visible fractions are learnt."""
    listed = (mi.Float(s_delta) >= LISTED_SHARE) | (mi.Bool(fresh) & all_listable)
    return dr.select(listed, dr.maximum(mi.UInt32(mi.Float(rays) * share), 1), mi.UInt32(rays))
