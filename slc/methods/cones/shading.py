r"""Shading from the cones, no rays: multiple importance sampling of the cones'
radiance with the BSDF.

The cones of an entry define a piecewise-constant model of the incoming radiance

.. math:: \tilde L(\omega) = \sum_{c\,\ni\,\omega} L_c / \Omega_c,
          \qquad \Omega_c = 2\pi (1 - \cos\alpha_c),

(``L_c`` estimates the integral of the incoming radiance over cone ``c``, see
docs/cones.md; overlapping cones add up). The shading integrates
:math:`\int f_r \cos\theta\, \tilde L\, d\omega` with two strategies, combined by
the balance heuristic over all samples of a pixel (Veach's multi-sample MIS):

- cone sampling: ``n_C`` directions uniform in each live cone (pdf ``1/Omega_c``),
  a stratified spherical-Fibonacci pattern rotated per pixel;
- BSDF sampling: ``n_B`` directions from ``bsdf.sample`` (pdf ``p_B``), a
  rank-1 (R3) sequence rotated per pixel.

Every sample, whatever its strategy, contributes

.. math:: f_r \cos\theta\, \tilde L(\omega) \,/\, \Big(n_C \sum_{c\,\ni\,\omega} 1/\Omega_c + n_B\, p_B(\omega)\Big),

which is unbiased for the integral. Cones narrower than ``ALPHA_DELTA`` (point
lights) are Dirac cones: one evaluation on the axis, ``f_r cos L_c``, weight 1.
BSDF samples of a Dirac lobe (mirrors) see ``\tilde L`` with weight 1.
Purely Lambertian pixels use the exact cone integral (no loop):
``(rho/pi) sum_c L_c (n . d_c)(1 + cos alpha_c)/2`` for cones clear of the horizon, the
integral of the cosine over the part of the cap above it for cones across it.
Pixels with Mitsuba's ``principled`` BSDF (no clearcoat, sheen, flatness, anisotropy or
transmission) whose cones have that closed form skip the quadrature too (``principled="sg"``,
the default; :func:`_principled_cones`): the diffuse part in closed form with its angular
factor at each cone axis, the GGX lobe as a Gaussian around the mirror direction of which
each cap holds a fraction; an approximation, measured in docs/cones.md.
With ``conductor="sg"`` (an option, off by default) isotropic GGX ``roughconductor`` pixels
get the same Gaussian lobe plus GGX's tail at far cones' axes (:func:`_conductor_cones`).
Each kind of pixel runs in a symbolic branch of its own, and BSDFs without textures are read
from a per-scene table (:func:`bsdf_table`) instead of virtual calls (same images). Pixels
seen from behind whose BSDF only reflects and whose cones all lie in front give 0 without
the quadrature (it would sum zeros); with ``glossy="half"`` (an option) purely glossy BSDFs
(rough conductors) take half the directions. The pixels left to the quadrature are packed
into a launch of their own (``compact``, the default), and the Gaussian lobe's share of a cap
far from its peak (exactly 0) is not computed; both give the same values bit for bit.

Sample counts: ``n_samples`` (n_S) directions, fewer for rough lobes (``n_S' =
ceil(n_S clip(q, 1/4, 1))``), split per pixel into ``n_C`` cone directions per live cone
and ``n_B = n_S' - n_C`` BSDF directions per pixel by the lobe's width against the cones
(``q = p_B(mirror) max_c Omega_c``; at most 3/4 BSDF), so a pixel with ``n`` cones
evaluates its BSDF ``n n_C + n_B`` times (+1 pdf).
Random numbers are hashes of (pixel index, ``key``): deterministic for a given frame,
seed and tap. See docs/cones.md for the expectation.

Each :class:`ConeShading` (one per method instance) owns its own frozen function
(``dr.freeze``); see the class for animated scenes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.scene import bsdf_table as bsdf_tables
from slc.scene.bsdf_table import KIND_DIFFUSE, KIND_NOT_PRINCIPLED, KIND_OTHER, KIND_PRINCIPLED, ZERO_ATTRS
from slc.core.freeze import FrozenFunction
from slc.methods.cones.packing import gather_words, unpack

GOLDEN = 0.6180339887498949           # 1 / phi: azimuths of the spherical-Fibonacci pattern
R3 = 1.2207440846057596               # plastic constant of the 3-D Roberts (R3) sequence
B_MAX = 0.75                          # at most this share of the directions are BSDF samples
ROUGH_MIN = 0.25                      # rough lobes keep at least this share of the n_S directions per cone
ALPHA_DELTA = 1e-3                    # rad; narrower cones are Dirac cones (as in ConeParams.alpha_delta)
BACK_MARGIN = 1e-3                    # cos; a cap this far above the horizon holds no direction below it,
                                      # even with the quadrature's cap-membership tolerance


@dataclass
class ConeState:
    r"""The cones of the pixels' entries, as the shading reads them (docs/cones.md). Per cone
    ``c`` (lists of ``K`` arrays, one lane per pixel): ``axis`` (:math:`d_c`, world),
    ``alpha`` (:math:`\alpha_c` [rad]), ``L`` (:math:`L_c`), ``live`` (the cone exists:
    ``c < n``), ``h`` (:math:`1 - \cos\alpha_c`), ``dirac`` (a live cone narrower than
    ``ALPHA_DELTA``), ``dense`` (a live cone with a density), ``inv_omega``
    (:math:`1/\Omega_c`, 0 for Dirac cones), ``sin_alpha``, ``cos_alpha``. Per pixel: ``n``
    (the number of cones) and ``zero`` (a zero of the pixels' width). ``K`` the number of
    cone slots."""
    K: int
    axis: list
    alpha: list
    L: list
    n: mi.UInt32
    zero: mi.Float
    live: list
    h: list
    dirac: list
    dense: list
    inv_omega: list
    sin_alpha: list
    cos_alpha: list


@dataclass(frozen=True)
class ShadeOptions:
    """The shading's choices (part of a frozen recording's key), see :class:`ConeShading`:
    ``max_cones``, ``adaptive``, ``rotate``, ``horizon``, ``principled`` and ``conductor``
    (closed forms on), ``glossy_half``, ``compact``."""
    max_cones: int
    adaptive: bool = True
    rotate: bool = True
    horizon: bool = True
    principled: bool = True
    conductor: bool = False
    glossy_half: bool = False
    compact: bool = False


def cone_samples(Dw, A, s_idx: mi.UInt32, nS: int):
    """Direction ``s_idx`` of ``nS`` of the fixed stratified pattern in cone (Dw, A) (world)."""
    return cone_direction(Dw, A, (mi.Float(s_idx) + 0.5) * (1.0 / nS), mi.Float(s_idx) * GOLDEN)


def cone_direction(Dw, A, u, x):
    """The direction of cone (Dw, A) at ``1 - cos(theta) = u (1 - cos A)`` and azimuth
    ``2 pi frac(x)``: uniform in the cone's solid angle for uniform ``u``."""
    ph = 2.0 * math.pi * (x - dr.floor(x))
    h = 2.0 * dr.square(dr.sin(0.5 * A))            # 1 - cos(alpha), precise for tiny alpha
    x = u * h                                       # 1 - cos(theta)
    ct = 1.0 - x
    st = dr.sqrt(dr.maximum(x * (2.0 - x), 0.0))
    sp, cp = dr.sincos(ph)
    return mi.Frame3f(Dw).to_world(mi.Vector3f(st * cp, st * sp, ct))


def _hash_float(pid: mi.UInt32, key: mi.UInt32, j: int) -> mi.Float:
    """Uniform float in [0, 1) from (pixel, key, stream j)."""
    v0, v1 = mi.sample_tea_32(pid, key ^ mi.UInt32((0x9E3779B9 * (j + 1)) & 0xFFFFFFFF), 4)
    return mi.Float(v0 >> 8) * (1.0 / 16777216.0)


def _frac(x):
    return x - dr.floor(x)


def _lambertian(bsdf, si, active):
    flags = mi.UInt32(bsdf.flags())
    return active & mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & (mi.Frame3f.cos_theta(si.wi) > 0.0)


def _schlick_weight(c):
    m = dr.clip(1.0 - c, 0.0, 1.0)
    return dr.square(dr.square(m)) * m


def _principled_cones(bsdf, si, ctx, active, cones: ConeState, term, below, consts=None):
    r"""Cone shading of pixels with Mitsuba's ``principled`` BSDF, no quadrature
    (``principled="sg"``, the default). Returns (value, mask of the pixels it applies to).

    It applies to pixels whose BSDF is ``principled`` (has the ``clearcoat`` and
    ``base_color`` attributes, diffuse + glossy reflection, no transmission) with
    clearcoat, sheen, flatness, anisotropy and specular transmission all 0 at the pixel,
    and whose cones all have the Lambertian closed form; the other pixels keep the MIS
    quadrature. The parameters are read once per pixel (``eval_attribute``), and the BSDF
    is evaluated once, at the mirror direction ``r`` of ``w_o``. Per live cone ``c``:

    - diffuse (exact in Mitsuba's model but for its angular factor): ``(1 - metallic)
      base_color / pi * (f_diff + f_retro)(w_o, d_c) * L_c (1/Omega_c) int_c cos``, the
      Disney diffuse and retro-reflection factor evaluated once, at the cone axis ``d_c``
      (the cosine integral is the Lambertian closed form, horizon-clipped);
    - specular (approximated): the GGX lobe ``f_s cos`` as a spherical Gaussian around
      ``r``, ``S_r exp(lambda_l (w . r - 1))``, ``lambda_l = 1 / (2 alpha^2 cos theta_o)``
      (the SG fit of GGX, ``lambda_h = 2 / alpha^2``, warped to reflected directions;
      Wang et al. 2009), of integral ``E = S_r 2 pi (1 - e^{-2 lambda_l}) / lambda_l``, with
      its peak ``S_r = f cos(r) - diffuse(r)`` taken from Mitsuba's own ``eval`` (so the
      Fresnel term, metallic and tint included, is exact at ``r`` and held over the lobe).
      The cone's part is ``(L_c / Omega_c) E Psi``, ``Psi`` the fraction of the lobe (a
      planar Gaussian of std ``sigma = lambda_l^-1/2``) inside the cap (radius ``alpha_c``,
      axis at angle ``t`` from ``r``): ``Psi = [Phi((alpha_c - t)/sigma) - Phi((-alpha_c -
      t)/sigma)] (1 - e^{-alpha_c^2 / 2 sigma^2}) / (2 Phi(alpha_c/sigma) - 1)``, exact at
      ``t = 0``, the cap's straight edge for ``alpha_c >> sigma`` and area x density for
      ``alpha_c << sigma``. A Dirac cone takes the lobe at its axis,
      ``L_c S_r exp(lambda_l (d_c . r - 1))``. A cap wholly under the horizon adds nothing;
      the lobe's part under the horizon is not clipped.
    """
    K, live, delta, A = cones.K, cones.live, cones.dirac, cones.alpha
    inv_om, L, Dw = cones.inv_omega, cones.L, cones.axis
    # ------------------- which pixels, and their parameters (one read per pixel) -------------------
    # (BSDFs without textures: from the table ``consts``, see :func:`bsdf_table`; BSDFs of
    # kind KIND_NOT_PRINCIPLED are not read: they lack the attributes ``read`` asks for)
    if consts is not None:
        tab = active & (consts[0] == KIND_PRINCIPLED) & (mi.Frame3f.cos_theta(si.wi) > 0.0)
        active = active & (consts[0] == KIND_OTHER)
    def read(active):
        """The parameters through the BSDF's virtual calls (and whether it qualifies)."""
        flags = mi.UInt32(bsdf.flags())
        m = active & bsdf.has_attribute("clearcoat", active) & bsdf.has_attribute("base_color", active) & \
            mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) & \
            ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
            (mi.Frame3f.cos_theta(si.wi) > 0.0)
        for name in ZERO_ATTRS:
            m &= bsdf.eval_attribute_1(name, si, m) == 0.0
        return (m, mi.Color3f(bsdf.eval_attribute_3("base_color", si, m)), bsdf.eval_attribute_1("roughness", si, m),
                bsdf.eval_attribute_1("metallic", si, m))

    if consts is None:
        m, base, rough, metal = read(active)
    else:
        m, base, rough, metal = dr.if_stmt(
            args=(active,), cond=active, true_fn=read,
            false_fn=lambda a: (mi.Bool(False), mi.Color3f(0.0), mi.Float(0.0), mi.Float(0.0)), label="read")
    if consts is not None:
        base = dr.select(tab, consts[1](), base)
        rough = dr.select(tab, consts[2](), rough)
        metal = dr.select(tab, consts[3](), metal)
        m |= tab
    ci = dr.maximum(mi.Frame3f.cos_theta(si.wi), 1e-4)
    kd = base * ((1.0 - metal) * (1.0 / math.pi))
    Fi = _schlick_weight(ci)

    def fdiff(wl):
        """Mitsuba's principled diffuse + retro-reflection factor for the local direction wl."""
        co = dr.maximum(mi.Frame3f.cos_theta(wl), 0.0)
        Fo = _schlick_weight(co)
        cd = dr.dot(dr.normalize(si.wi + wl), wl)
        Rr = 2.0 * rough * dr.square(cd)
        return (1.0 - 0.5 * Fi) * (1.0 - 0.5 * Fo) + Rr * (Fo + Fi + Fo * Fi * (Rr - 1.0))

    # ------------------- the specular lobe's peak and width -------------------
    r_loc = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
    f_r = mi.Color3f(bsdf.eval(ctx, si, r_loc, m))
    S_r = dr.maximum(f_r - kd * (fdiff(r_loc) * ci), 0.0)
    lobe = _sg_lobe(si, dr.maximum(dr.square(rough), 1e-3), ci)

    # ------------------- per cone: diffuse at the axis, the part of the lobe in the cap -------------------
    out = mi.Color3f(cones.zero)
    for i in range(K):
        d_loc = si.to_local(Dw[i])
        diff = kd * (fdiff(d_loc) * term[i])
        sg, _, _ = _sg_cone(lobe, Dw[i], A[i], inv_om[i], delta[i])
        spec = dr.select(below[i], 0.0, S_r * (L[i] * sg))
        out += dr.select(live[i], diff + spec, 0.0)
    return out, m


def _sg_lobe(si, alpha, ci):
    r"""The GGX lobe of roughness ``alpha`` (GGX's own) around the mirror direction ``r``
    of ``w_o`` as an anisotropic Gaussian (see :func:`_principled_cones`): (r, E_s,
    sigma_par, sigma_perp, e_par, e_perp), ``E_s`` its integral over its peak."""
    lam_l = dr.rcp(2.0 * dr.square(alpha) * ci)
    r_loc = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
    r = si.to_world(r_loc)
    E_s = (2.0 * math.pi) * dr.rcp(lam_l) * (1.0 - dr.exp(-2.0 * lam_l))      # int of the SG lobe / S_r
    # the lobe's widths: a half vector tilted by an angle b moves r by 2b in the plane of
    # incidence and by 2 cos(theta_o) b across it, so sigma_par = 2 sigma_h, sigma_perp =
    # 2 cos(theta_o) sigma_h, sigma_h^2 = alpha^2 / 2 (sigma_par sigma_perp = 1 / lambda_l)
    s_par = math.sqrt(2.0) * alpha
    s_perp = s_par * ci
    e_perp = dr.cross(si.sh_frame.n, r)
    e_perp = dr.select(dr.squared_norm(e_perp) > 1e-12, dr.normalize(e_perp), si.sh_frame.s)
    e_par = dr.cross(e_perp, r)
    return r, E_s, s_par, s_perp, e_par, e_perp


def _sg_cone(lobe, Dw, A, inv_om, delta):
    r"""The share of the lobe ``lobe`` (:func:`_sg_lobe`) that cone (``Dw``, ``A``) sees,
    per unit of its peak and of the cone's ``L_c``: ``E Psi / Omega_c``, or for a Dirac
    cone the lobe's value on its axis (see :func:`_principled_cones`)."""
    r, E_s, s_par, s_perp, e_par, e_perp = lobe
    v = Dw - r
    dd = dr.squared_norm(v)                             # |r - d|^2 = 2 (1 - r . d), precise near 0
    # t: the angle from r to the cone axis; m: its Mahalanobis length in the lobe's widths
    th = 2.0 * dr.asin(dr.minimum(0.5 * dr.sqrt(dd), 1.0))
    sc = th * dr.rsqrt(dr.maximum(dd, 1e-30))
    m2 = dr.square(dr.dot(v, e_par) * sc / s_par) + dr.square(dr.dot(v, e_perp) * sc / s_perp)
    # the fraction Psi of the lobe inside the cap (radius a = alpha_c): a Gaussian edge across
    # the cap's rim, scaled to GGX's own fraction in a disc centred on the peak (its slopes
    # are a bivariate Student t with 2 degrees of freedom: a disc of slope radius rho holds
    # rho^2 / (alpha^2 + rho^2), where a Gaussian of the same peak holds 1 - e^{-rho^2/alpha^2}).
    # With sigma_t = t / m the lobe's width towards the axis (sqrt(s_par s_perp) at t = 0)
    # and x = a^2 / (2 s_par s_perp) = rho^2 / alpha^2:
    # Psi ~ [Phi((a - t)/sigma_t) - Phi((-a - t)/sigma_t)] (x / (1 + x)) / (2 Phi(a/sigma_t) - 1):
    # GGX's fraction at t = 0 (round lobe), the cap's edge for a >> sigma, area x density
    # for a << sigma
    sig = dr.select(m2 > 1e-12, th * dr.rsqrt(dr.maximum(m2, 1e-30)), dr.sqrt(s_par * s_perp))
    isg = dr.rcp(sig)

    def t2(u):
        return dr.erf(u * math.sqrt(0.5))                              # 2 Phi(u) - 1

    def share(A, th, isg, E_s, inv_om):
        edge = 0.5 * (t2((A - th) * isg) - t2((-A - th) * isg))
        x = dr.square(A) * (0.5 / (s_par * s_perp))
        psi = edge * (x * dr.rcp(1.0 + x)) * dr.rcp(dr.maximum(t2(A * isg), 1e-30))
        return E_s * psi * inv_om

    # A cap whose near rim lies 4 sqrt(2) widths or more beyond the peak holds none of the
    # lobe: there Dr.Jit's erf is -1 exactly for both rims (it is for arguments <= -3.92),
    # so edge = 0 and the share is +0 exactly; such lanes skip the erf's (a symbolic branch:
    # the same values bit for bit, tests/test_cones_compact.py)
    far = ((A - th) * isg) * math.sqrt(0.5) <= -4.0
    sg = dr.if_stmt(args=(A, th, isg, E_s, inv_om), cond=~far, true_fn=share,
                    false_fn=lambda *a: mi.Float(0.0), label="sg_share")
    return dr.select(delta, dr.exp(-0.5 * m2), sg), m2, th


def _conductor_cones(bsdf, si, ctx, active, cones: ConeState, below):
    r"""Cone shading of pixels with Mitsuba's isotropic GGX ``roughconductor``, no
    quadrature (``conductor="sg"``): the lobe ``f_s cos`` as the Gaussian of
    :func:`_principled_cones`'s specular part, of peak ``S_r = f cos(r)`` from Mitsuba's
    own ``eval`` at the mirror direction ``r`` (the conductor's Fresnel term exact at ``r``
    and held over the lobe) and width from the BSDF's ``alpha`` (read per pixel). It
    applies to pixels whose BSDF has the ``alpha`` attribute and only glossy reflection
    (no diffuse, Dirac or transmissive lobe; the caller passes only when every
    roughconductor of the scene uses the GGX distribution). Returns (value, mask)."""
    flags = mi.UInt32(bsdf.flags())
    m = active & bsdf.has_attribute("alpha", active) & mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) & \
        ~mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Delta) & (mi.Frame3f.cos_theta(si.wi) > 0.0)
    K, live, delta, A = cones.K, cones.live, cones.dirac, cones.alpha
    inv_om, L, Dw = cones.inv_omega, cones.L, cones.axis
    alpha = dr.maximum(bsdf.eval_attribute_1("alpha", si, m), 1e-3)
    ci = dr.maximum(mi.Frame3f.cos_theta(si.wi), 1e-4)
    r_loc = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
    S_r = dr.maximum(mi.Color3f(bsdf.eval(ctx, si, r_loc, m)), 0.0)
    lobe = _sg_lobe(si, alpha, ci)
    out = mi.Color3f(cones.zero)
    for i in range(K):
        sg, m2, th = _sg_cone(lobe, Dw[i], A[i], inv_om[i], delta[i])
        # GGX's tail (a Student t) far outweighs the Gaussian's away from r: what the
        # Gaussian misses at the cone's axis, f cos(d_c) - S_r e^{-m^2/2}, is held over the cap
        f_c = mi.Color3f(bsdf.eval(ctx, si, si.to_local(Dw[i]), m & live[i]))
        tail = dr.maximum(f_c - S_r * dr.exp(-0.5 * m2), 0.0)
        # ... only for caps away from r (inside, the Student-t fraction of the lobe holds its tail)
        tail *= dr.select(delta[i], 1.0, dr.clip((th - A[i]) * dr.rcp(dr.maximum(A[i], 1e-6)), 0.0, 1.0))
        # a cap narrower than the lobe sees f cos nearly constant: f cos(d_c) L_c (blended in
        # from caps of twice the lobe's width down to caps of its width)
        b = dr.select(delta[i], 1.0, dr.clip(2.0 - A[i] * dr.rsqrt(lobe[2] * lobe[3]), 0.0, 1.0))
        val = L[i] * dr.lerp(S_r * sg + tail, f_c, b)
        out += dr.select(live[i] & ~below[i], val, 0.0)
    return out, m


def shade_kernel(storage: mi.UInt32, slot: mi.UInt32, active: mi.Bool, si: mi.SurfaceInteraction3f,
                 bsdf: mi.BSDFPtr, texel_frame: mi.Frame3f, n_total: mi.UInt32, key: mi.UInt32,
                 pid: mi.UInt32 | None, table, entry_frames, opts: ShadeOptions) -> mi.Color3f:
    """Direct illumination of the pixels ``si`` (BSDFs ``bsdf``) from the entries
    ``slot``; ``texel_frame`` is the local frame of each pixel's entry (the frame its
    cone directions are stored in). ``n_total`` directions per live cone and ``key``
    are opaque scalars; ``opts`` the shading's choices (:class:`ShadeOptions`, see
    :class:`ConeShading`). ``pid``
    keys each pixel's random numbers (None: its index in the arrays; several viewers
    shaded in one launch pass each pixel's index within its own viewer). ``table``
    (:func:`bsdf_table`, optional) gives the constants of BSDFs without textures. With
    ``entry_frames`` (the entries' frames), ``texel_frame`` is instead each pixel's index
    into them (the gather then runs inside this kernel, not as a kernel of its own).
    Entries without cones and inactive pixels give 0."""
    K = opts.max_cones
    tf_in = texel_frame
    cones = _cone_state(storage, slot, active, texel_frame, entry_frames, K)
    n = cones.n
    ctx = mi.BSDFContext()
    if pid is None:
        pid = dr.arange(mi.UInt32, dr.width(slot))
    # each pixel's BSDF kind and constants from the table (KIND_OTHER: virtual calls)
    kind, consts = _table_consts(table, bsdf, active)

    # ------------------- Lambertian pixels: the cone integral in closed form -------------------
    # A cone clear of the horizon: (1/Omega_c) int_c cos = (n . d_c)(1 + cos alpha_c)/2. With
    # ``horizon``, a cone across it (alpha_c < pi/2) takes the exact integral of cos over the
    # part of its cap above the horizon (Snyder 1996; Lagarde and de Rousiers 2014, sphere
    # lights): int = (cos_d acos(y) - x sin_d sqrt(1 - y^2)) sin^2(alpha) + atan(sin_d sqrt(1 - y^2) / x),
    # x = cot(alpha), y = -x cos_d / sin_d; a cap wholly below (or a Dirac cone below) adds 0.
    # Cones wider than a hemisphere across the horizon still go to sampling.
    closed, cones_ok, clear, term, below_c = _horizon_terms(si, active, cones, opts.horizon)
    lambert = _lambertian(bsdf, si, active) & cones_ok

    # Each kind of pixel runs in a symbolic branch of its own (Lambertian closed form,
    # principled closed form, quadrature): on the LLVM backend a SIMD packet skips a branch
    # none of its lanes takes, so a pixel pays only for its own kind (the images are the
    # same bit for bit as with every kind computed for every pixel and selected).
    def lambert_fn(closed):
        if consts is None:
            rho = mi.Color3f(bsdf.eval_diffuse_reflectance(si, lambert))
        else:
            tab = kind == KIND_DIFFUSE
            rho = dr.select(tab, consts[1](), mi.Color3f(bsdf.eval_diffuse_reflectance(si, lambert & ~tab)))
        return rho * closed * (1.0 / math.pi)

    closed = dr.if_stmt(args=(closed,), cond=lambert, true_fn=lambert_fn,
                        false_fn=lambda closed: mi.Color3f(0.0), label="lambert")

    # ------------------- principled (and GGX conductor) pixels: closed forms -------------------
    prin, pfast = _glossy_closed(bsdf, si, ctx, active & cones_ok & ~lambert, cones, term, below_c, consts,
                                 opts.principled, opts.conductor)
    # ------------------- pixels seen from behind whose cones are all in front: 0, no quadrature -------------------
    # A BSDF without transmission (or null) lobes reflects only into the side of w_i: with
    # cos(theta_i) <= 0 and every cone wholly above the horizon, f_r = 0 for every direction
    # in the cones, and a BSDF sample (on w_i's side) lies in no cone (L~ = 0): the quadrature
    # sums zeros. (The meeting rig's viewers 4 and 12 see only such pixels: 12 % of its pixels.)
    flags = mi.UInt32(bsdf.flags())
    backside = active & clear & (mi.Frame3f.cos_theta(si.wi) <= 0.0) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & ~mi.has_flag(flags, mi.BSDFFlags.Null)
    sampled = active & ~lambert & ~pfast & (n > 0) & ~backside

    if not opts.compact:
        n_px = _samples_px(bsdf, n_total, opts.glossy_half)

        def sampled_fn(sampled):
            return _quadrature(bsdf, si, ctx, sampled, cones, n_px, key, pid, opts)

        acc = dr.if_stmt(args=(sampled,), cond=sampled, true_fn=sampled_fn,
                         false_fn=lambda sampled: mi.Color3f(0.0), label="quadrature")

        # raw values: a NaN or Inf made here reaches the image, where check mode names it
        return dr.select(lambert, closed, dr.select(pfast, prin, acc))

    # ------------------- the quadrature's pixels compacted into a launch of their own -------------------
    # A SIMD packet (16 lanes with AVX-512 on the LLVM backend) holding one quadrature pixel
    # runs the quadrature's loops for all its lanes; on the atrium 3 % of the pixels (rough
    # conductors) take it, spread over 14 % of the packets. This launch evaluates the closed
    # forms and which pixels are left; the next takes the indices of those (``dr.compress``;
    # the last pixel always taken, masked off unless it is one: no launch of width 0), gathers
    # their inputs, recomputes their cone state from them (the same operations: the same
    # values), and its values are scattered back. Same images bit for bit
    # (tests/test_cones_compact.py); measured in docs/cones.md (packed quadrature pixels).
    out = dr.select(lambert, closed, dr.select(pfast, prin, 0.0))
    dr.eval(out, sampled)
    N = dr.width(slot)
    idx = dr.compress(sampled | (dr.arange(mi.UInt32, N) == (N - 1)))
    on = dr.gather(mi.Bool, sampled, idx)
    si_c, bsdf_c = dr.gather(type(si), si, idx), dr.gather(mi.BSDFPtr, bsdf, idx)
    cones_c = _cone_state(storage, dr.gather(mi.UInt32, slot, idx), on, dr.gather(type(tf_in), tf_in, idx),
                          entry_frames, K)
    acc = _quadrature(bsdf_c, si_c, ctx, on, cones_c, _samples_px(bsdf_c, n_total, opts.glossy_half), key,
                      dr.gather(mi.UInt32, pid, idx), opts)
    dr.scatter(out, acc, idx, on)
    # raw values: a NaN or Inf made here reaches the image, where check mode names it
    return out


def _glossy_closed(bsdf, si, ctx, pm, cones: ConeState, term, below_c, consts, principled, conductor):
    """The closed forms of the candidate pixels ``pm`` (Lambertian closed form for every
    cone, not Lambertian): principled (``principled``), GGX conductor (``conductor``), each
    in a symbolic branch. Returns (value, mask of the pixels that have one)."""
    if principled:
        prin, pfast = dr.if_stmt(
            args=(pm,), cond=pm,
            true_fn=lambda pm: _principled_cones(bsdf, si, ctx, pm, cones, term, below_c, consts),
            false_fn=lambda pm: (mi.Color3f(0.0), mi.Bool(False)), label="principled")
    else:
        prin, pfast = mi.Color3f(cones.zero), pm & False
    # ------------------- GGX conductor pixels: the lobe as an SG (an option) -------------------
    if conductor:
        cm = pm & ~pfast
        cond_v, cfast = dr.if_stmt(
            args=(cm,), cond=cm,
            true_fn=lambda cm: _conductor_cones(bsdf, si, ctx, cm, cones, below_c),
            false_fn=lambda cm: (mi.Color3f(0.0), mi.Bool(False)), label="conductor")
        prin = dr.select(pfast, prin, cond_v)
        pfast = pfast | cfast
    return prin, pfast


def _table_consts(table, bsdf, active):
    """Each pixel's BSDF kind and constants from the table (:func:`bsdf_table`; ``KIND_OTHER``:
    virtual calls): (kind, consts or None), the constants read lazily."""
    if table is None:
        return mi.UInt32(KIND_OTHER), None
    rid = dr.reinterpret_array(mi.UInt32, bsdf)
    t_ok = active & (bsdf != None) & (rid < table.width)  # noqa: E711 (BSDFPtr comparison)
    kind = dr.gather(mi.UInt32, table.kind, rid, t_ok)
    return kind, (kind, lambda: dr.gather(mi.Color3f, table.colour, rid, t_ok),
                  lambda: dr.gather(mi.Float, table.roughness, rid, t_ok),
                  lambda: dr.gather(mi.Float, table.metallic, rid, t_ok))


def _horizon_terms(si, active, cones: ConeState, horizon: bool):
    """Per cone the Lambertian closed form ``L_c (1/Omega_c) int_c cos`` (horizon-clipped
    with ``horizon``; 0 if not live) and whether its cap lies wholly below the horizon;
    their sum, and per pixel whether every live cone has the closed form (``cones_ok``)
    and lies wholly above the horizon with a margin (``clear``). See :func:`shade_kernel`."""
    K, A, L, Dw, live, delta, h = cones.K, cones.alpha, cones.L, cones.axis, cones.live, cones.dirac, cones.h
    sin_a, cos_a = cones.sin_alpha, cones.cos_alpha
    nrm = si.sh_frame.n
    closed = mi.Color3f(cones.zero)
    cones_ok = mi.Bool(active)                 # every live cone has a closed form
    clear = mi.Bool(active)                    # every live cone wholly above the horizon (with a margin)
    term, below_c = [], []                     # per cone: L_c (1/Omega_c) int_c cos (0 if not live); cap below
    for i in range(K):
        cos_d = dr.dot(nrm, Dw[i])
        sin_d = dr.safe_sqrt(1.0 - dr.square(cos_d))
        # above the horizon: angle(n, d) + alpha < pi/2  <=>  cos(angle + alpha) > 0
        sa, ca = sin_a[i], cos_a[i]
        above = (cos_d * ca - sin_d * sa) > 0.0
        clear &= ~live[i] | ((cos_d * ca - sin_d * sa) > BACK_MARGIN)
        full = L[i] * (cos_d * 0.5 * (1.0 + ca))
        if horizon:
            below = (cos_d * ca + sin_d * sa) <= 0.0                      # the whole cap under the horizon
            # the clipped-cap integral only where a live cone crosses the horizon (a symbolic
            # branch: SIMD packets without such a lane skip it)
            across = dr.if_stmt(
                args=(cos_d, sin_d, sa, ca, A[i], L[i], delta[i], h[i]),
                cond=live[i] & ~above & ~below,
                true_fn=_across_cap, false_fn=lambda *a: mi.Color3f(0.0), label="across")
            cones_ok &= ~live[i] | above | (A[i] < 0.5 * math.pi)
            t = dr.select(live[i], dr.select(above, full, dr.select(below, 0.0, across)), 0.0)
        else:
            below = (cos_d * ca + sin_d * sa) <= 0.0
            cones_ok &= ~live[i] | above
            t = dr.select(live[i], full, 0.0)
        closed += t
        term.append(t)
        below_c.append(below | (delta[i] & (cos_d <= 0.0)))
    return closed, cones_ok, clear, term, below_c

def _cone_state(storage, slot, active, texel_frame, entry_frames, K):
    """The cones of each pixel's entry, read from ``storage`` (:class:`ConeState`)."""
    if entry_frames is not None:
        texel_frame = dr.gather(mi.Frame3f, entry_frames, texel_frame, active)
    D, A, L, C, n = unpack(gather_words(storage, slot, K, active), K)
    Dw = [dr.normalize(texel_frame.to_world(D[i])) for i in range(K)]
    zero = dr.select(active, mi.Float(0.0), mi.Float(0.0))     # a zero of the pixels' width

    # ------------------- the cones: live, Dirac, solid angle, density -------------------
    live = [active & (n > i) for i in range(K)]
    h = [2.0 * dr.square(dr.sin(0.5 * A[i])) for i in range(K)]           # 1 - cos(alpha_c)
    delta = [live[i] & (A[i] < ALPHA_DELTA) for i in range(K)]
    area = [live[i] & ~delta[i] for i in range(K)]                        # cones with a density
    inv_om = [dr.select(area[i], dr.rcp(dr.maximum(2.0 * math.pi * h[i], 1e-30)), 0.0) for i in range(K)]
    return ConeState(K, axis=Dw, alpha=A, L=L, n=n, zero=zero, live=live, h=h, dirac=delta, dense=area,
                     inv_omega=inv_om, sin_alpha=[dr.sin(a) for a in A], cos_alpha=[dr.cos(a) for a in A])


def _samples_px(bsdf, n_total, glossy_half):
    """n_S per pixel: ``n_total``, halved for purely glossy BSDFs with ``glossy_half``."""
    n_px = mi.UInt32(n_total)
    if glossy_half:
        flags = mi.UInt32(bsdf.flags())
        glossy_only = mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) & \
            ~mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
            ~mi.has_flag(flags, mi.BSDFFlags.Transmission)
        n_px = dr.select(glossy_only, dr.maximum(n_px >> 1, 1), n_px)
    return n_px


def _across_cap(cos_d, sin_d, sa, ca, A, L, delta, h):
    """L_c (1/Omega_c) times the integral of cos over the part of the cap (axis at
    ``cos_d`` from the normal, half-angle ``A``) above the horizon (Snyder 1996)."""
    x = ca * dr.rcp(dr.maximum(sa, 1e-30))
    y = dr.clip(-x * cos_d * dr.rcp(dr.maximum(sin_d, 1e-30)), -1.0, 1.0)
    sy = sin_d * dr.safe_sqrt(1.0 - dr.square(y))
    part = (cos_d * dr.acos(y) - x * sy) * dr.square(sa) + dr.atan2(sy, x)
    inv_om_i = dr.rcp(dr.maximum(2.0 * math.pi * h, 1e-30))
    return dr.select(delta, L * dr.maximum(cos_d, 0.0), L * (dr.maximum(part, 0.0) * inv_om_i))


def _quadrature(bsdf, si, ctx, sampled, cones: ConeState, n_total, key, pid, opts: ShadeOptions):
    """The MIS quadrature of the pixels ``sampled`` (the module docstring): returns
    the sum over their cone and BSDF samples."""
    K, A, L, Dw, live, delta, area, h = cones.K, cones.alpha, cones.L, cones.axis, cones.live, cones.dirac, \
        cones.dense, cones.h
    inv_om, zero = cones.inv_omega, cones.zero
    def density(w, own=None):
        """(sum over cones holding w of L_c/Omega_c, of 1/Omega_c); cone ``own`` holds w."""
        Lt, dt = mi.Color3f(zero), mi.Float(zero)
        for j in range(K):
            inside = area[j] & ((1.0 - dr.dot(w, Dw[j])) <= h[j] * (1.0 + 1e-5) + 1e-7)
            if own == j:
                inside = area[j]
            Lt += dr.select(inside, L[j] * inv_om[j], 0.0)
            dt += dr.select(inside, inv_om[j], 0.0)
        return Lt, dt

    def mis(pdf_cones, pdf_b):
        """Balance heuristic: a sample's weight over its pdf, 1 / (n_C sum_c 1/Omega_c + n_B p_B)."""
        den = nc_f * pdf_cones + nb_f * pdf_b
        return dr.select(den > 0.0, dr.rcp(den), 0.0)

    # ------------------- allocation: how narrow is the lobe against the cones? -------------------
    # q = p_B(r) max_c Omega_c, with r the mirror direction of w_o (the peak of a glossy lobe),
    # compares the cone's solid angle with the lobe's (about 1 / p_B(r)). n_S cone directions
    # are spaced about Omega / n_S apart: they resolve the lobe while q < n_S. Of the n_S
    # directions per cone, n_B = round(n_S min(q / (q + n_S), 3/4)) are BSDF samples: none
    # for rough lobes (a diffuse lobe has p_B <= 1/pi), up to three quarters for lobes far
    # narrower than the cones; at least a quarter stay cone samples (a glossy coat's diffuse
    # base, e.g. plastic, is cheaper by cone sampling). The allocation is fixed before any
    # sample is drawn, so the MIS estimator stays unbiased for any q.
    #
    # Rough lobes (q < 1: the lobe is wider than the widest cone, so f_r cos varies little
    # inside a cone) need fewer directions: n_S' = ceil(n_S clip(q, 1/4, 1)) per cone
    # (at least a quarter of n_S). The BSDF directions are drawn per pixel, not per cone:
    # their density does not depend on the cones, and a lobe narrower than the cones sees
    # a nearly constant L~ whatever the cone count (docs/cones.md, "Per-viewer cost").
    ns_f = mi.Float(n_total)
    if opts.adaptive:
        om_max = mi.Float(zero)
        for i in range(K):
            om_max = dr.maximum(om_max, dr.select(area[i], 2.0 * math.pi * h[i], 0.0))
        r = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
        q = bsdf.pdf(ctx, si, r, sampled) * om_max
        n_dir = dr.maximum(mi.UInt32(dr.ceil(ns_f * dr.clip(q, ROUGH_MIN, 1.0))), 1)
        nd_f = mi.Float(n_dir)
        n_b = mi.UInt32(dr.round(nd_f * dr.minimum(q / (q + nd_f), B_MAX)))
    else:
        n_dir = mi.UInt32(n_total)
        n_b = mi.UInt32(ns_f * 0.5)
    n_b = dr.minimum(n_b, n_dir - 1)                                      # n_C >= 1: Dirac cones need it
    n_c = n_dir - n_b
    nc_f, nb_f = mi.Float(n_c), mi.Float(n_b)                             # per cone / per pixel
    nc_rcp = dr.rcp(dr.maximum(nc_f, 1.0))

    # per-pixel rotations of the two patterns
    if opts.rotate:
        rot = [(_hash_float(pid, key, 2 * i), _hash_float(pid, key, 2 * i + 1)) for i in range(K)]
    else:
        rot = [(mi.Float(0.5), mi.Float(0.0)) for i in range(K)]
    rb = (_hash_float(pid, key, 2 * K), _hash_float(pid, key, 2 * K + 1), _hash_float(pid, key, 2 * K + 2))

    # ------------------- cone sampling: n_C directions in each live cone -------------------
    # iteration j draws pattern direction j of every live cone (the cones unrolled: measured
    # 30 % cheaper than one loop over all (cone, j) pairs with a single BSDF call site).
    # A Dirac cone is evaluated once, on its axis.
    def cone_cond(j, acc):
        return (j < n_c) & sampled

    def cone_body(j, acc):
        jf = mi.Float(j)
        for i in range(K):
            u = _frac((jf + rot[i][0]) * nc_rcp)
            wi = dr.select(delta[i], Dw[i], cone_direction(Dw[i], A[i], u, jf * GOLDEN + rot[i][1]))
            m = sampled & live[i] & (~delta[i] | (j == 0))
            f, pdf_b = bsdf.eval_pdf(ctx, si, si.to_local(wi), m)
            Lt, dt = density(wi, own=i)
            w = dr.select(delta[i], L[i], Lt * mis(dt, pdf_b))
            acc += dr.select(m, mi.Color3f(f) * w, 0.0)
        return j + 1, acc

    _, acc = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(zero)), cond=cone_cond, body=cone_body,
                           labels=("j", "acc"))

    # ------------------- BSDF sampling: n_B directions per pixel -------------------
    def bsdf_cond(t, acc):
        return (t < n_b) & sampled

    def bsdf_body(t, acc):
        k = mi.Float(t)
        u1 = _frac(rb[0] + k * (1.0 / R3))
        u2 = mi.Point2f(_frac(rb[1] + k * (1.0 / R3 ** 2)), _frac(rb[2] + k * (1.0 / R3 ** 3)))
        bs, bw = bsdf.sample(ctx, si, u1, u2, sampled)
        wi = si.to_world(bs.wo)
        ok = sampled & (bs.pdf > 0.0)
        Lt, dt = density(wi)
        dirac = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        # bw = f cos / p_B, so the sample's f cos Lt / den is bw * p_B * Lt / den;
        # a Dirac lobe cannot be reached by cone sampling: weight 1 / n_B
        w = dr.select(dirac, dr.rcp(dr.maximum(nb_f, 1.0)), bs.pdf * mis(dt, bs.pdf))
        acc += dr.select(ok, mi.Color3f(bw) * Lt * w, 0.0)
        return t + 1, acc

    _, acc = dr.while_loop(state=(mi.UInt32(0), acc), cond=bsdf_cond, body=bsdf_body, labels=("t", "acc"))
    return acc


def shade_key(frame: int, seed: int, tap: int = 0) -> int:
    """The random-number key of one shading call (frame, seed, bilinear tap)."""
    x = (int(frame) * 0x9E3779B1 + int(seed) * 0x85EBCA77 + int(tap) * 0xC2B2AE3D) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    return x ^ (x >> 15)


class ConeShading(FrozenFunction):
    r"""Shading of pixels from their cache entries' cones: MIS of cone sampling and
    BSDF sampling (module docstring and docs/cones.md).

    Parameters (defaults): ``max_cones`` (as stored), ``adaptive=True`` (split each
    cone's ``n_samples`` between the strategies by the lobe's width against the cones;
    False: half and half), ``rotate=True`` (rotate the patterns per pixel and key; False:
    the same pattern everywhere), ``freeze=True`` (record the kernel launches once and
    replay them), ``animated=False`` (the scene's meshes move), ``max_recordings=4``,
    ``horizon=True`` (Lambertian pixels whose cones cross the horizon use the exact
    clipped-cap integral; False: they are sampled, as before December 2026),
    ``principled="sg"`` (pixels with Mitsuba's ``principled`` BSDF: diffuse part in
    closed form, specular lobe as a spherical Gaussian, see :func:`_principled_cones`;
    ``"sample"``: the MIS quadrature, as before), ``conductor="sample"`` (pixels with an
    isotropic GGX ``roughconductor``: the MIS quadrature; ``"sg"``: the lobe as a spherical
    Gaussian over each cone, see :func:`_conductor_cones`; only for scenes whose
    roughconductors all use GGX, :func:`shader_for` checks), ``glossy="full"`` (``"half"``:
    pixels whose BSDF is purely glossy, e.g. rough conductors, take half of ``n_samples``
    on the quadrature: faster, noisier, see docs/cones.md), ``compact=True`` (the pixels that
    take the MIS quadrature packed into a launch of their own, so that SIMD packets of
    closed-form pixels do not run its loops; False: in a branch of the launch of all pixels;
    the same images bit for bit).

    Freezing pays only while its recordings are replayed. Each instance owns its frozen
    function, so recordings are freed with the method and never shared between scenes.
    A frozen function traverses every object of Mitsuba's registry (shapes, BSDFs,
    emitters, the scene) on each call; when meshes move, that state changes from frame to
    frame and the function would be recorded again on most frames' first call (measured
    on ``street``: one recording per frame). So in an animated scene the shading is traced
    on every call, never recorded (:mod:`slc.freeze`): no frame after the first builds a
    kernel. In a static scene a function recorded more than ``max_recordings`` times is
    dropped.
    """

    def __init__(self, max_cones: int, adaptive: bool = True, rotate: bool = True, freeze: bool = True,
                 animated: bool = False, max_recordings: int = 4, horizon: bool = True,
                 principled: str = "sg", conductor: str = "sample", table=None, glossy: str = "full",
                 compact: bool = True):
        self.table = table
        self.compact = bool(compact)
        if glossy not in ("half", "full"):
            raise ValueError(f"glossy must be 'half' or 'full', not {glossy!r}")
        self.glossy = glossy
        if principled not in ("sg", "sample"):
            raise ValueError(f"principled must be 'sg' or 'sample', not {principled!r}")
        if conductor not in ("sg", "sample"):
            raise ValueError(f"conductor must be 'sg' or 'sample', not {conductor!r}")
        self.conductor = conductor
        self.max_cones = int(max_cones)
        self.adaptive, self.rotate, self.horizon = bool(adaptive), bool(rotate), bool(horizon)
        self.principled = principled
        self.opts = ShadeOptions(self.max_cones, adaptive=bool(adaptive), rotate=bool(rotate), horizon=bool(horizon),
                                 principled=principled == "sg", conductor=conductor == "sg",
                                 glossy_half=glossy == "half", compact=bool(compact))
        super().__init__(shade_kernel, freeze, animated, max_recordings)

    def __call__(self, storage, slot, active, si, texel_frame, n_samples: int = 16, key: int = 0,
                 pid: mi.UInt32 | None = None, entry_frames=None) -> mi.Color3f:
        """Shade the pixels ``si``; ``pid``: the random-number key per pixel (default:
        the index in the arrays); ``entry_frames``: ``texel_frame`` is an index into
        them (see :func:`shade_kernel`)."""
        # (no garbage collection inside the call: slc.core.freeze.FrozenFunction)
        return super().__call__(storage, mi.UInt32(slot), mi.Bool(active), si, si.bsdf(), texel_frame,
                                dr.opaque(mi.UInt32, max(int(n_samples), 1)), dr.opaque(mi.UInt32, int(key)), pid,
                                self.table, entry_frames, self.opts)


def shader_for(owner, max_cones: int) -> ConeShading:
    """The :class:`ConeShading` of ``owner`` (a method instance), made on first use
    (animated when the owner's scene is, see :class:`ConeShading`; the horizon
    treatment from the owner's ``horizon`` setting, default ``clip``; the principled
    pixels' from its ``principled`` setting, default ``sg``)."""
    sh = getattr(owner, "_cone_shading", None)
    if sh is None or sh.max_cones != int(max_cones):
        scene = getattr(owner, "scene", None)
        conductor = getattr(owner, "conductor", "sample")
        if conductor == "sg" and scene is not None and not _ggx_conductors_only(scene):
            conductor = "sample"
        sh = ConeShading(max_cones, animated=bool(getattr(scene, "dynamic", False)),
                         horizon=getattr(owner, "horizon", "clip") == "clip",
                         principled=getattr(owner, "principled", "sg"), conductor=conductor,
                         glossy=getattr(owner, "glossy", "full"), compact=getattr(owner, "compact", "on") == "on",
                         table=bsdf_table(scene) if scene is not None else None)
        owner._cone_shading = sh
    return sh


def bsdf_table(scene):
    """The scene's :class:`slc.scene.bsdf_table.BSDFTable` (the kinds and constants the shading
    kernel reads instead of virtual calls), None for scenes with instances."""
    return bsdf_tables.for_scene(scene)


def _ggx_conductors_only(scene) -> bool:
    """Whether every ``roughconductor`` of the scene (``slc`` scene or ``mi.Scene``) is
    GGX (the closed form of :func:`_conductor_cones` assumes it)."""
    ms = getattr(scene, "mi_scene", scene)
    for sh in ms.shapes():
        text = str(sh.bsdf()) if sh.bsdf() is not None else ""
        if text.startswith("RoughConductor") and "distribution = ggx" not in text:
            return False
    return True


def shade_pixels(storage, slot, active, si, texel_frame, max_cones: int, n_samples: int = 16, key: int = 0,
                 principled: str = "sg", conductor: str = "sample"):
    """Unfrozen one-off shading (tests, notebooks)."""
    return ConeShading(max_cones, freeze=False, principled=principled, conductor=conductor)(storage, slot, active, si, texel_frame,
                                                                      n_samples, key)
