r"""VISIBILITY representation: per-light visibility of the few delta lights
(point, spot, directional) that matter at an entry, plus a residual.

Modules: :mod:`.record` (the record and its packing), :mod:`.lights` (the listed lights'
exact terms at a point, the update's shadow rays), :mod:`.update` (the update cycle in
stages), :mod:`.shading`, :mod:`.frozen` (both as frozen functions); here the
:class:`VisibilityRep` that the adaptive cache runs.

Record (``K + 2`` words, ``K = vis_lights``, default 12)::

    K x [ light index (16) | visibility v (unorm 10, stochastically rounded) | count (6) ]
    residual irradiance E_r (3 x 18-bit e6m12) | its count C_r (8) | converted (1) | spare (1)
    with an environment: [ v_u (unorm 16) | its count n_u (8) | spare (8) ],
                         [ v_s (unorm 16) | its weight sum W_s (16, units of 1/16) ]
    in scenes with two-sided BSDFs: the residual behind the surface E_b (3 x 18-bit e6m12) | spare (10)

Two-sided surfaces (Mitsuba's ``twosided``, dielectrics; :func:`slc.scene.bsdf_table.two_sided`):
an entry there takes light from both hemispheres (its pixels on the back see the light
behind the surface), so its samples and listed lights count with :math:`|\cos\theta|`, a
polygon light's term is the sum of its parts clipped to either hemisphere, and the residual
is kept per side (:math:`E_r` in front of the normal, :math:`E_b` behind it, one count).
A pixel is shaded on its own side: the listed lights' terms with the normal turned towards
its viewer, the residual of its side along that normal.

Shading at a pixel x (no rays): the lights' unoccluded contribution is
evaluated exactly at x (the emitter's own ``sample_direction``, which is
deterministic for a delta light), the visibility comes from the entry:

.. math:: L_o(x) = \sum_{i \le K} f_r(x, \omega_i, \omega_o) \frac{I_i(\omega_i)}{d_i^2}\, v_i
          \;+\; f_r(x, n, \omega_o)\, E_r ,

the residual (light of other emitters and of delta lights outside the list)
treated as arriving along the normal for a diffuse-only BSDF (exact for a Lambertian lobe) and
as uniform radiance over the hemisphere for another BSDF (its directional albedo times
:math:`E_r/\pi`, :mod:`.shading`). A light with hard shadow edges (a delta light, the sun as a
region of the environment) whose visible fraction at the entry is strictly between 0 and 1
(measured over the entry's footprint, :func:`.lights.footprint_ray`) has its visibility traced
at the pixel, one shadow ray.

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

Small sphere lights (:mod:`slc.lib.lights.sphere_lights`, ``sph``) are listed
like delta lights where they are small at the entry (:math:`r/d` below
``sph.max_sin``): their :math:`v_i` is the running mean of shadow rays to
sampled points on the sphere and their unoccluded term is the closed form
:math:`\pi L r^2/d^2` towards the current centre.

Bright small regions of the environment map (:mod:`slc.lib.lights.env_lights`,
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

import drjit as dr
import mitsuba as mi

from slc.methods.adaptive.choice import VIS
from slc.methods.adaptive.representation import Entries, Pixels, Representation, Updated
from slc.methods.adaptive.sampling import SampleStats
from slc.methods.adaptive.visibility import frozen, record
from slc.methods.adaptive.visibility.lights import has_delta, light_at, traced_rays
from slc.methods.adaptive.visibility.record import EMPTY, RESIDUAL_ALPHA, residual, unpack


class VisibilityRep(Representation):
    """The VISIBILITY representation of the adaptive cache (see the module): ``K =
    cache.vis_k`` slots, the environment regions' word where the scene lists regions, the
    residual behind the surface where it has two-sided BSDFs. Its entries whose listed lights
    bring nearly all their light trace ``cache.vis_rays`` of the policy's rays
    (:func:`~.lights.traced_rays`); a listed light gone dark or moved reports motion and
    restarts the entry's statistics (``restarts_stats``)."""

    tag, name = VIS, "visibility"
    restarts_stats = True

    def words(self) -> int:
        c = self.cache
        return record.words(c.vis_k, c.env is not None, c._back)

    def update(self, e: Entries) -> Updated:
        c = self.cache
        rays = traced_rays(e.rays, e.s_delta, e.fresh, c.prior == VIS, c._vis_share)
        fn = self.frozen("update_fn", lambda fz: frozen.VisUpdate(c.vis_k, c.seed, c.sph, c.env, fz))
        out, motion, st = fn(c.scene.mi_scene, e.rec, e.si, e.key, rays, e.moving, e.fresh, e.on, e.frame, e.texel)
        return Updated(out, motion, SampleStats.of(st), rays)

    def shade(self, px: Pixels) -> mi.Color3f:
        c = self.cache
        fn = self.frozen("shade_fn", lambda fz: frozen.VisShading(c.vis_k, c.sph, c.env, fz, c.polygon_glossy,
                                                                    c.polygon_samples, c.seed, back=c._back))
        return fn(self.pool.gather(px.slot, px.active), px.active, px.si, c.scene.mi_scene, px.frame, px.viewer,
                  px.pid, px.n_viewers)

    def lobes(self, rec, si, active) -> list:
        """The record as lobes: one Dirac lobe per listed light (I/d^2 v at the entry) and the
        residual (with the unlisted regions) as a 60-degree cone about the normal (its
        irradiance / mean cosine); the residual behind the surface as one about the reversed
        normal."""
        c = self.cache
        scene, K, sph, env = c.scene.mi_scene, c.vis_k, c.sph, c.env
        em_dr, dl = scene.emitters_dr(), has_delta(scene)
        r = unpack(rec, K, env is not None, c._back)
        out = []
        for i in range(K):
            m = mi.Bool(active) & (r.idx[i] != EMPTY)
            d, w = light_at(em_dr, si, r.idx[i], m, sph, env, dl)
            out.append((si.sh_frame.to_local(d), mi.Float(0.0), w * r.vis[i], m & (dr.max(w * r.vis[i]) > 0.0)))
        mean_cos = 0.5 * (1.0 + math.cos(RESIDUAL_ALPHA))
        E = residual(r, si.sh_frame.n, env, active)
        out.append((mi.Vector3f(0.0, 0.0, 1.0), mi.Float(RESIDUAL_ALPHA), E * (1.0 / mean_cos),
                    mi.Bool(active) & (dr.max(E) > 0.0)))
        if c._back:
            out.append((mi.Vector3f(0.0, 0.0, -1.0), mi.Float(RESIDUAL_ALPHA), r.Eb * (1.0 / mean_cos),
                        mi.Bool(active) & (dr.max(r.Eb) > 0.0)))
        return out

    def convert(self, src, rec, lobes, n: int) -> list:
        """A record with no listed light and the source's irradiance at the normal as its
        residual (and at the reversed normal behind the surface); the lights come in with the
        next samples."""
        c = self.cache
        return record.from_irradiance(src.irradiance(rec, lobes, 1.0), n, c.vis_k, c.env is not None,
                                      src.irradiance(rec, lobes, -1.0) if c._back else None)
