r"""The closed forms of the cone shading, no quadrature: Lambertian pixels (the integral of the
cosine over each cone, clipped at the horizon for cones across it), pixels with Mitsuba's
``principled`` BSDF (the diffuse part at each cone's axis, the GGX lobe as a spherical Gaussian
of which each cap holds a fraction) and, as an option, isotropic GGX ``roughconductor`` pixels
(the same Gaussian plus GGX's tail at far cones' axes). :func:`slc.lib.cones.shading.shade_kernel`
runs each kind of pixel in a symbolic branch of its own; the model is described in the docstring
of :mod:`slc.lib.cones.shading` and measured in docs/cones.md."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from slc.scene.bsdf_table import KIND_OTHER, KIND_PRINCIPLED, ZERO_ATTRS
from slc.lib.cones.conestate import ConeState, cap_cosine_integral

BACK_MARGIN = 1e-3                    # cos; a cap this far above the horizon holds no direction below it,
                                      # even with the quadrature's cap-membership tolerance


def lambertian(bsdf, si, active):
    flags = mi.UInt32(bsdf.flags())
    return active & mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & (mi.Frame3f.cos_theta(si.wi) > 0.0)


def _schlick_weight(c):
    m = dr.clip(1.0 - c, 0.0, 1.0)
    return dr.square(dr.square(m)) * m


def _principled_cones(bsdf, si, ctx, active, cones: ConeState, term, below, consts=None):
    r"""One function because it is one traced branch whose stages (the pixels' parameters, the
    specular lobe, the per-cone sum) share the per-pixel BSDF parameters; its stages are marked
    by banner comments.

    Cone shading of pixels with Mitsuba's ``principled`` BSDF, no quadrature
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
    # (BSDFs without textures: from the table ``consts``, see
    # :func:`slc.lib.cones.shading.bsdf_table`; BSDFs of
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


def glossy_closed(bsdf, si, ctx, pm, cones: ConeState, term, below_c, consts, principled, conductor):
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


def horizon_terms(si, active, cones: ConeState, horizon: bool):
    """Per cone the Lambertian closed form ``L_c (1/Omega_c) int_c cos`` (horizon-clipped
    with ``horizon``; 0 if not live) and whether its cap lies wholly below the horizon;
    their sum, and per pixel whether every live cone has the closed form (``cones_ok``)
    and lies wholly above the horizon with a margin (``clear``). See
    :func:`slc.lib.cones.shading.shade_kernel`."""
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


def _across_cap(cos_d, sin_d, sa, ca, A, L, delta, h):
    """L_c (1/Omega_c) times the integral of cos over the part of the cap (axis at
    ``cos_d`` from the normal, half-angle ``A``) above the horizon (Snyder 1996)."""
    part = cap_cosine_integral(cos_d, sin_d, sa, ca)
    inv_om_i = dr.rcp(dr.maximum(2.0 * math.pi * h, 1e-30))
    return dr.select(delta, L * dr.maximum(cos_d, 0.0), L * (part * inv_om_i))
