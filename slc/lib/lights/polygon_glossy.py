r"""Glossy shading of polygon lights without shadow rays (docs/adaptive.md, "Polygon lights").

A VISIBILITY record lists a polygon light with its visible fraction :math:`v`; a Lambertian
pixel gets the light's exact irradiance :math:`E` (:mod:`slc.lib.lights.polygon_lights`),
other BSDFs see the light as a point along its vector irradiance :math:`\mathbf d`. That is
wrong for a lobe that is narrow against the light: at a pixel :math:`y` whose BSDF's peak density
(at the mirror direction) times the light's solid angle :math:`\Omega` exceeds ``tau``, the
record's term is :math:`v\, \hat I`, an estimate of the unshadowed integral

.. math:: I(y) = \int_{\Omega_L} f(y, \omega_o, \omega)\, \cos\theta\, L\, d\omega
          = c\, E + \int_{\Omega_L} (f - c \cos\theta)\, L\, d\omega,

with the diffuse reflectance as a control variate, :math:`c = \rho_d/\pi` for a BSDF with a
diffuse lobe (0 otherwise; exact for any :math:`c`: its integral is :math:`c E`), and the second
integral by multiple importance sampling of ``S`` pairs of samples and no ray: one direction
uniform in the light's solid angle (a triangle chosen in proportion to the solid angle it
subtends, then :func:`slc.scene.spherical.sample_triangle`; by area where that triangle is too
small or too wide for the map), one from the BSDF, kept where it meets a front face of the light
(intersected with its triangles, at most 16), each weighted by the balance heuristic,

.. math:: \frac1S \sum_s \frac{g(\omega_l) L}{p_l(\omega_l) + p_f(\omega_l)}
                 + \frac{g(\omega_b) L\, [\omega_b \text{ hits}]}{p_l(\omega_b) + p_f(\omega_b)},
          \qquad g = f - c\cos\theta,

with :math:`f` the BSDF value with its cosine (Mitsuba's ``eval``), :math:`p_l` the light
density (:math:`1/\Omega` where the triangle is sampled in solid angle, the area density
:math:`d^2/(A\cos)` times the triangle's choice probability elsewhere) and :math:`p_f` the
BSDF's. The pairs are a (0, 2)-sequence per strategy, scrambled per pixel (the triangle chosen
with the light sample's first coordinate, reused within it). A sharp lobe is found by its BSDF
sample, a wide one by its light sample. The record's visible fraction is the light's, weighted
by the cosine: it is exact for a glossy lobe only where it is 0 or 1 (the light wholly hidden or
visible from the entry); where it is partial the samples are shadowed by a ray each
(``shadow``) and multiply nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from slc.core.structs import drjit_struct
from slc.scene.emitter_table import RECT, ROW, ROW_E0, ROW_E1, ROW_L, ROW_P0
from slc.scene.spherical import OMEGA_MAX, OMEGA_MIN, sample_triangle, solid_angle

GLOSSY = int(mi.BSDFFlags.GlossyReflection) | int(mi.BSDFFlags.GlossyTransmission)
DIFFUSE = int(mi.BSDFFlags.DiffuseReflection) | int(mi.BSDFFlags.DiffuseTransmission)
VIS_WHOLE = 0.999  # a visible fraction above this: the light wholly visible from the entry (no shadow ray)
PEAK_TAU = 0.1     # a lobe is sampled where its peak density (1/sr) times the light's solid angle exceeds this


def has_glossy(scene: mi.Scene) -> bool:
    """Whether any shape of the scene has a BSDF with a glossy lobe."""
    return any(s.bsdf() is not None and (int(s.bsdf().flags()) & GLOSSY) for s in scene.shapes())


@dataclass
class Tri:
    """A triangle ``(p0, p0 + e0, p0 + e1)`` of a light, its radiance, whether it faces the
    shading point and the solid angle it subtends there (0 where it does not face it)."""
    p0: mi.Point3f
    e0: mi.Vector3f
    e1: mi.Vector3f
    L: mi.Color3f
    front: mi.Bool
    omega: mi.Float


def _tri(table, x: mi.Point3f, off: mi.UInt32, rect: mi.Bool, t: mi.UInt32, m: mi.Bool) -> Tri:
    """Triangle ``t`` of the light whose rows start at ``off``: a mesh's row ``t``; a
    rectangle's two halves ``(p0, e0, e0 + e1)`` and ``(p0, e0 + e1, e1)`` (row 0)."""
    r = dr.select(rect, off, off + t)

    def get(c):
        return dr.gather(mi.Float, table._rows, r * ROW + c, m)
    p0 = mi.Point3f(get(ROW_P0), get(ROW_P0 + 1), get(ROW_P0 + 2))
    e0 = mi.Vector3f(get(ROW_E0), get(ROW_E0 + 1), get(ROW_E0 + 2))
    e1 = mi.Vector3f(get(ROW_E1), get(ROW_E1 + 1), get(ROW_E1 + 2))
    L = mi.Color3f(get(ROW_L), get(ROW_L + 1), get(ROW_L + 2))
    half = rect & ((t & 1) == 1)
    a = mi.Vector3f(dr.select(rect & ~half, e0, dr.select(half, e0 + e1, e0)))
    b = mi.Vector3f(dr.select(rect & ~half, e0 + e1, e1))
    front = m & (dr.dot(x - p0, dr.cross(a, b)) > 0.0)
    om = dr.select(front, solid_angle(x, p0, a, b), 0.0)
    return Tri(p0=p0, e0=a, e1=b, L=L, front=front, omega=om)


def _density(x: mi.Point3f, tri: Tri, y: mi.Point3f, omega_total: mi.Float, use: mi.Bool) -> mi.Float:
    """Light density (solid angle) of the direction from ``x`` to ``y`` on ``tri``: 1/Omega
    where the triangle is sampled in solid angle, else its choice probability times the
    area density d^2 / (A cos)."""
    d = y - x
    d2 = dr.squared_norm(d)
    n = dr.cross(tri.e0, tri.e1)
    A2 = dr.norm(n)                                 # twice the area
    cos = dr.abs(dr.dot(n, d)) * dr.rsqrt(dr.maximum(d2, 1e-30)) / dr.maximum(A2, 1e-30)
    inv_total = dr.select(omega_total > 0.0, dr.rcp(dr.maximum(omega_total, 1e-30)), 0.0)
    area = tri.omega * inv_total * d2 / dr.maximum(0.5 * A2 * cos, 1e-30)
    return dr.select(use, inv_total, area)


def _uses_solid_angle(tri: Tri) -> mi.Bool:
    """The choice of :func:`sample_triangle` (a function of the point and the triangle)."""
    return tri.front & (tri.omega > OMEGA_MIN) & (tri.omega < OMEGA_MAX)


def _hit(x: mi.Point3f, w: mi.Vector3f, tri: Tri) -> tuple:
    """Where the ray ``x + t w`` meets the triangle's front (Moller-Trumbore): (hit, point)."""
    pv = dr.cross(w, tri.e1)
    det = dr.dot(tri.e0, pv)
    inv = dr.rcp(dr.select(det != 0.0, det, 1.0))
    s = x - tri.p0
    u = dr.dot(s, pv) * inv
    q = dr.cross(s, tri.e0)
    v = dr.dot(w, q) * inv
    t = dr.dot(tri.e1, q) * inv
    ok = tri.front & (det != 0.0) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > 0.0)
    return ok, dr.fma(w, t, x)


@dataclass
class LightWalk:
    """A polygon light seen from the pixels ``x``: its rows in the table (``off``, ``rect``),
    its ``n_tri`` triangles and the solid angle ``omega_total`` their front faces subtend."""
    table: object
    x: mi.Point3f
    off: mi.UInt32
    rect: mi.Bool
    n_tri: mi.UInt32
    omega_total: mi.Float | None = None

    def tri(self, t: mi.UInt32, m: mi.Bool) -> Tri:
        """Triangle ``t`` of the light (:func:`_tri`)."""
        return _tri(self.table, self.x, self.off, self.rect, t, m)


@drjit_struct
@dataclass
class PickLoop:
    """The state of the walk that picks the light sample's triangle (one lane per pixel): ``t``
    the triangles passed, ``run`` their summed solid angle, ``k`` the triangle picked (``n_tri``:
    none yet) and ``u`` the sample's first coordinate rescaled within it."""
    t: mi.UInt32 = field(default_factory=mi.UInt32)
    run: mi.Float = field(default_factory=mi.Float)
    k: mi.UInt32 = field(default_factory=mi.UInt32)
    u: mi.Float = field(default_factory=mi.Float)


@drjit_struct
@dataclass
class HitLoop:
    """The state of the walk that meets the BSDF sample's ray with the light (one lane per pixel):
    ``t`` the triangles tested, ``h`` whether the ray met a front face, ``y`` the first point met
    and ``k`` its triangle."""
    t: mi.UInt32 = field(default_factory=mi.UInt32)
    h: mi.Bool = field(default_factory=mi.Bool)
    y: mi.Point3f = field(default_factory=mi.Point3f)
    k: mi.UInt32 = field(default_factory=mi.UInt32)


def glossy_term(table, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, idx: mi.UInt32, active: mi.Bool,
                rng: mi.PCG32, S: int, c: mi.Color3f, tau: float, scene: mi.Scene | None = None,
                shadow: mi.Bool | None = None):
    """(the control-variate part of :math:`\\hat I`, the lanes it was made for, ``rng``) for
    polygon lights ``idx`` at the pixels ``si``: where the BSDF's peak density times the light's
    solid angle exceeds ``tau`` (a lobe not wide against the light), or ``shadow`` holds, ``S``
    sample pairs from ``rng`` of :math:`\\int (f - c \\cos\\theta) L` (module docstring): the
    light's solid angle (:func:`_omega_total`), then per pair a light sample
    (:func:`_light_sample`) and a BSDF sample (:func:`_bsdf_sample`).
    ``shadow`` (with ``scene``): lanes whose samples are shadowed by a ray each."""
    ctx = mi.BSDFContext()
    x = si.p
    m = mi.Bool(active)
    seg = dr.gather(mi.Point2f, table._seg, idx, m)
    off, cnt = mi.UInt32(seg.x), mi.UInt32(seg.y)
    rect = m & (dr.gather(mi.UInt32, table._e_kind, idx, m) == RECT)
    light = LightWalk(table, x, off, rect, dr.select(rect, 2 * cnt, cnt))
    N = dr.width(m)

    # ------------------------ the solid angle the light's front faces subtend
    light.omega_total = omega_total = _omega_total(light, m, N)
    wi = si.wi
    peak = bsdf.pdf(ctx, si, mi.Vector3f(-wi.x, -wi.y, wi.z), m & (omega_total > 0.0))
    partial = mi.Bool(shadow) if shadow is not None else mi.Bool(False)
    live = m & (omega_total > 0.0) & ((peak * omega_total > tau) | partial)

    # ------------------------ S pairs of samples: a (0, 2)-sequence per strategy, scrambled per pixel
    sc = [rng.next_uint32() for _ in range(4)]
    shift = rng.next_float32()

    def c_pair(s, acc):
        return live & (s < S)

    def b_pair(s, acc):
        u1, u2 = mi.radical_inverse_2(s, sc[0]), mi.sobol_2(s, sc[1])
        u3, u4 = mi.radical_inverse_2(s, sc[2]), mi.sobol_2(s, sc[3])
        u_l = dr.fma(mi.Float(s), 1.0 / max(int(S), 1), shift)
        u_l -= dr.floor(u_l)
        acc += _light_sample(light, si, bsdf, ctx, live, u1, u2, c, scene, shadow)
        acc += _bsdf_sample(light, si, bsdf, ctx, live, u_l, u3, u4, c, scene, shadow)
        return s + 1, acc

    _, acc = dr.while_loop(state=(mi.UInt32(0), dr.zeros(mi.Color3f, N)), cond=c_pair, body=b_pair)
    return acc * (1.0 / max(int(S), 1)), live, rng


def _omega_total(light: LightWalk, m: mi.Bool, N: int) -> mi.Float:
    """The solid angle the front faces of the light subtend at the lanes ``m``."""
    def c_total(t, om):
        return m & (t < light.n_tri)

    def b_total(t, om):
        return t + 1, om + light.tri(t, m & (t < light.n_tri)).omega

    _, omega_total = dr.while_loop(state=(mi.UInt32(0), dr.zeros(mi.Float, N)), cond=c_total, body=b_total)
    return omega_total


def _light_sample(light: LightWalk, si, bsdf, ctx, live: mi.Bool, u1: mi.Float, u2: mi.Float, c: mi.Color3f,
                  scene, shadow) -> mi.Color3f:
    """One light sample's term: a triangle in proportion to its solid angle (``u1``, reused
    within it), a point on it (:func:`slc.scene.spherical.sample_triangle`, by area where the map
    is not used), weighted by the balance heuristic."""
    x, n_tri, omega_total = light.x, light.n_tri, light.omega_total
    N = dr.width(live)

    def c_pick(st: PickLoop):
        return live & (st.t < n_tri)

    def b_pick(st: PickLoop):
        om = light.tri(st.t, live & (st.t < n_tri)).omega
        first = (st.run + om > u1 * omega_total) & (st.k == n_tri) & (om > 0.0)
        u_in = dr.clip((u1 * omega_total - st.run) / dr.select(om > 0.0, om, 1.0), 0.0, 0.99999994)
        st.t, st.run, st.k, st.u = st.t + 1, st.run + om, dr.select(first, st.t, st.k), dr.select(first, u_in, st.u)
        return (st,)

    st, = dr.while_loop(state=(PickLoop(mi.UInt32(0), dr.zeros(mi.Float, N), mi.UInt32(n_tri),
                                        dr.zeros(mi.Float, N)),), cond=c_pick, body=b_pick)
    k, u1 = st.k, st.u
    on_l = live & (k < n_tri)
    tri = light.tri(dr.select(on_l, k, 0), on_l)
    y, _, use, ok = sample_triangle(x, tri.p0, tri.e0, tri.e1, mi.Point2f(u1, u2), on_l)
    # by area where the map is not used: the triangle's square-root warp
    su = dr.sqrt(u1)
    y_area = tri.p0 + tri.e0 * (su * (1.0 - u2)) + tri.e1 * (su * u2)
    y = dr.select(use, y, y_area)
    ok = dr.select(use, ok, on_l)
    wl = dr.normalize(y - x)
    p_l = _density(x, tri, y, omega_total, use)
    lo = si.to_local(wl)
    f_l = bsdf.eval(ctx, si, lo, ok)
    pf_l = bsdf.pdf(ctx, si, lo, ok)
    den = p_l + pf_l
    if scene is not None:
        ok &= ~scene.ray_test(si.spawn_ray_to(y), ok & shadow)
    g_l = mi.Color3f(f_l) - c * dr.maximum(lo.z, 0.0)
    return dr.select(ok & (den > 0.0), g_l * tri.L / dr.select(den > 0.0, den, 1.0), 0.0)


def _bsdf_sample(light: LightWalk, si, bsdf, ctx, live: mi.Bool, u_l: mi.Float, u3: mi.Float, u4: mi.Float,
                 c: mi.Color3f, scene, shadow) -> mi.Color3f:
    """One BSDF sample's term, where its ray meets a front face of the light (at most 16
    triangles tested), weighted by the balance heuristic."""
    x, n_tri = light.x, light.n_tri
    N = dr.width(live)
    bs, wgt = bsdf.sample(ctx, si, u_l, mi.Point2f(u3, u4), live)
    wb = si.to_world(bs.wo)
    okb = live & (bs.pdf > 0.0) & dr.all(dr.isfinite(mi.Color3f(wgt)))

    def c_hit(st: HitLoop):
        return okb & (st.t < n_tri)

    def b_hit(st: HitLoop):
        tt = light.tri(st.t, okb & (st.t < n_tri))
        hit, p = _hit(x, wb, tt)
        new = hit & ~st.h
        st.t, st.h, st.y, st.k = st.t + 1, st.h | hit, dr.select(new, p, st.y), dr.select(new, st.t, st.k)
        return (st,)

    st, = dr.while_loop(state=(HitLoop(mi.UInt32(0), mi.Bool(False), dr.zeros(mi.Point3f, N), mi.UInt32(0)),),
                        cond=c_hit, body=b_hit)
    h, yh, kh = st.h, st.y, st.k
    tb = light.tri(kh, okb & h)
    if scene is not None:
        h &= ~scene.ray_test(si.spawn_ray_to(yh), okb & h & shadow)
    p_lb = _density(x, tb, yh, light.omega_total, _uses_solid_angle(tb))
    f_b = mi.Color3f(wgt) * bs.pdf - c * dr.maximum(bs.wo.z, 0.0)
    den_b = p_lb + bs.pdf
    return dr.select(okb & h & (den_b > 0.0), f_b * tb.L / dr.select(den_b > 0.0, den_b, 1.0), 0.0)


def polygon_term(table, scene: mi.Scene, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, idx: mi.UInt32,
                 active: mi.Bool, d: mi.Vector3f, w: mi.Color3f, v: mi.Float, rng: mi.PCG32, S: int):
    """(the term of polygon lights ``idx`` with visible fraction ``v`` at glossy pixels ``si``, the
    lanes it holds for, ``rng``): :math:`c E v` plus the sampled part (:func:`glossy_term`), times
    ``v`` where the light is wholly visible or hidden, shadowed by its rays where ``v`` is partial
    (there without the control variate). ``d``, ``w``: the light's vector-irradiance direction and
    irradiance per unit cosine along it (:math:`E = w\\, n \\cdot d`)."""
    part = mi.Float(v) < VIS_WHOLE
    c = dr.select(((mi.UInt32(bsdf.flags()) & DIFFUSE) == 0) | part, 0.0,
                  mi.Color3f(bsdf.eval_diffuse_reflectance(si, active)) * (1.0 / math.pi))
    t_p, used, rng = glossy_term(table, si, bsdf, idx, active, rng, S, c, PEAK_TAU, scene, part)
    t = c * w * dr.maximum(dr.dot(d, si.sh_frame.n), 0.0) * v + dr.select(part, t_p, t_p * v)
    return t, used, rng
