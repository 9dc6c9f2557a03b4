r"""Shading from a cached incident-radiance field, no rays: the diffuse
closed form and BSDF samples of the radiance.

:func:`shade_radiance` is shared by the caches that store incident radiance
per entry and shade a pixel from it: the ``sh`` method
(:mod:`slc.methods.sh.method`, world-frame coefficients) and the adaptive cache's SH
pool (:mod:`slc.methods.adaptive.sh_rep`, coefficients in the entry's local frame)
and the GI caches' primary entries (:mod:`slc.methods.oscgi.method`, 8x8 hemisphere
texels and an irradiance sum).
The field is passed as two callables, so the estimator stays one piece of
code whatever the field's storage:

.. math::

    L_o = \begin{cases}
      \frac{\rho}{\pi} E(\mathbf n) & \text{diffuse-only BSDF, } \omega_o
                                         \text{ above the surface}\\
      \frac{1}{n} \sum_{j=1}^{n} w_j\, \tilde L_i(\omega_j),
      \quad \omega_j \sim f_r, \; w_j = \frac{f_r \cos\theta_j}{p(\omega_j)}
      & \text{otherwise,}
    \end{cases}

with :math:`E` the field's irradiance at the shading normal and
:math:`\tilde L_i` its reconstructed radiance.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi


def diffuse_only(bsdf: mi.BSDFPtr) -> mi.Bool:
    """Pixels whose BSDF has neither a glossy nor a delta lobe."""
    flags = bsdf.flags()
    return ~mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Delta)


def shade_radiance(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, active: mi.Bool, irradiance_fn, radiance_fn,
                   sampler: mi.PCG32, glossy_samples: int, two=None) -> mi.Color3f:
    """:math:`L_o` of the pixels ``si`` (see the module) where ``active``.

    - ``irradiance_fn()``: :class:`mi.Color3f` irradiance :math:`E` at each
      pixel's shading normal (used on diffuse-only pixels);
    - ``radiance_fn(d, m)``: (:class:`mi.Color3f` radiance towards world
      direction ``d``, mask of the lanes where it exists) for the lanes ``m``;
    - ``sampler``: one PCG32 stream per pixel for the BSDF samples;
    - ``glossy_samples``: BSDF samples per glossy pixel (a baked constant: the
      average's factor; the loop bound is opaque);
    - ``two``: pixels on two-sided BSDFs (:func:`slc.scene.bsdf_table.two_sided`; None: none),
      which are shaded from behind too (``irradiance_fn`` then gives the irradiance at the
      normal turned towards the viewer, :func:`slc.scene.bsdf_table.side_normal`).

    Raw values are returned (no clamp); lanes outside ``active`` are 0."""
    active = mi.Bool(active)
    diff = diffuse_only(bsdf)

    # ------------------- diffuse: closed-form irradiance -------------------
    E = mi.Color3f(irradiance_fn())
    rho = mi.Color3f(bsdf.eval_diffuse_reflectance(si, active & diff))
    front = si.wi.z > 0.0
    L = dr.select(active & diff & (front if two is None else front | two), rho * E * (1.0 / math.pi), 0.0)

    # -------------- glossy: BSDF samples of the reconstructed radiance --------------
    g = active & ~diff
    ns = dr.opaque(mi.UInt32, glossy_samples)
    ctx_b = mi.BSDFContext()

    def cond(i, Lg, sampler):
        return (i < ns) & g

    def body(i, Lg, sampler):
        u1 = sampler.next_float32()
        u2 = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        bs, bw = bsdf.sample(ctx_b, si, u1, u2, g)
        okj = g & (bs.pdf > 0.0)
        Li, okj = radiance_fn(si.to_world(bs.wo), okj)
        return i + 1, Lg + dr.select(okj, mi.Color3f(bw) * mi.Color3f(Li), 0.0), sampler

    _, Lg, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                             labels=("i", "Lg", "sampler"))
    L += Lg * (1.0 / float(glossy_samples))
    return dr.select(active, L, 0.0)
