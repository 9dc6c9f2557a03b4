"""The registered ``slc`` method: Surface Light Cones on the on-surface cache."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.scene.bsdf_table import front_side_only
from slc.core.keys import INVALID
from slc.methods import Param, register
from slc.methods.cache_method import PayloadMethod, RayPolicy
from slc.osc.protocol import BILINEAR_TAPS
from slc.lib.cones.packing import words_per_entry
from slc.lib.cones.shading import shade_key, shader_for
from slc.lib.cones.update import ConeParams
from slc.methods.cones.update_kernel import update_entries, updater_for


class SurfaceLightCones(PayloadMethod):
    r"""Surface Light Cones (Stadlbauer et al. 2023) in the on-surface cache.

    Each cache entry (a texel = a surface point) keeps up to ``max_cones`` cones
    (axis :math:`D_c` in the entry's local frame, half-angle :math:`\alpha_c`,
    RGB :math:`L_c`), an accumulation count :math:`C` and a cone count, packed in
    286 bits (3 RGB32 texels, 36 bytes) for 3 cones.

    Estimator. :math:`L_c` is a running estimate of
    :math:`E_c = \int_{\Omega_c} L_i(x,\omega)\,d\omega` (incoming radiance integrated
    over the cone's solid angle, no cosine). One update cycle draws ``n`` light samples
    at the entry's own surface point with weights
    :math:`w_k = L_e G / p \cdot V` (``slc.scene.lights.sample_light`` + shadow ray),
    inserts them one after another (cases A-D) and sets

    .. math:: L_c \leftarrow L_c (1 - 1/C) + \frac{1}{C}\,\frac{1}{n}\sum_k [\omega_k \in c]\, w_k,

    with :math:`C` incremented by the cycle's samples (capped at 255, or at 8 cycles
    while the entry is new or moving) and reduced by
    :math:`\min(\max(1 + 0.05\,\beta, 1.01), 3)` (:math:`\beta` in degrees) when a cone
    turned. Shading (no rays): the cones define a radiance density
    :math:`\tilde L(\omega) = \sum_{c \ni \omega} L_c / \Omega_c`; ``shade_samples`` directions per
    cone, split per pixel between uniform cone sampling and BSDF sampling, are combined by
    multiple importance sampling (balance heuristic over both strategies),

    .. math:: L_o = \sum_k \frac{f_r(x, \omega_k, \omega_o)\cos\theta_k\, \tilde L(\omega_k)}
              {n_C \sum_{c \ni \omega_k} 1/\Omega_c + n_B\, p_B(\omega_k)},

    and purely Lambertian pixels use the exact cone integral (docs/cones.md).

    Ray policy (docs/cones.md, "Ray budget"): a new entry gets ``rays_new`` rays,
    halved every ``halve_every`` updates down to ``rays_settled`` over its first
    ``new_updates`` updates (32, 16, 8, 4, 2, then 1: 248 samples in 20 updates);
    ``rays_moving`` rays for 8 updates after detected motion; ``rays_settled``
    otherwise; ``ray_budget`` (> 0) caps a frame's rays per active entry (the
    rays above the settled ones scaled down together; off by default). Update samples
    (``samples=r2``) follow a per-entry R2 sequence over the entry's life. A
    shrink-test ray that hits the front side of an emitter emitting nothing there
    (a light switched off) means the light left, and the entry forgets fast (a
    missed rim test on a wide cone that got no sample is followed by a ray on its
    axis, which finds such a light). With ``gone_test=axis`` (an option; off by
    default) any miss on the axis counts so.
    """

    name = "slc"
    params = (
        Param("max_cones", 3, "cones per entry", lo=1, hi=4),
        Param("shade_samples", 16, "shading directions per cone", lo=1, hi=1024),
        *PayloadMethod.ray_policy_params,
        Param("ray_budget", 0.0, "mean update rays per active entry and frame that new and moving entries may "
              "take (0: no cap)", lo=0.0, hi=1024.0),
        Param("epsilon", 0.1, "shrink test at (1 - epsilon) alpha", lo=1e-6, hi=1 - 1e-6),
        Param("shrink_period", 4, "settled entries run the shrink test every k-th frame", lo=1, hi=1024),
        Param("beta_min", 1.0, "degrees: smaller cone turns neither reduce C nor count as motion", lo=0.0),
        Param("shrink_keeps", "energy", "a cone shrunk by a missed test keeps its integral L_c (the paper) or its "
              "density L_c / Omega_c", choices=("energy", "density")),
        Param("gone_test", "off", "axis: a cone whose rim test missed (and that got no sample) is tested on its axis, "
              "and a miss there too counts as a light that left (C / 3, motion); off: only a hit on a dark "
              "emitter does",
              choices=("off", "axis")),
        Param("samples", "r2", "update samples: a per-entry R2 sequence stratified over the entry's life, or "
              "independent random numbers per cycle", choices=("r2", "random")),
        Param("fetch", "nearest", "the nearest entry (the paper's), the 4 surrounding entries weighted bilinearly, "
              "or one of the 4 drawn per pixel and frame with the bilinear weights as probabilities",
              choices=("nearest", "bilinear", "stochastic")),
        Param("horizon", "clip", "Lambertian pixels with a cone across the horizon: the exact integral over the "
              "part of the cone above it (clip) or MIS sampling as for glossy pixels (sample)",
              choices=("clip", "sample")),
        Param("principled", "sg", "pixels with the principled BSDF: diffuse part in closed form and specular lobe as a "
              "spherical Gaussian over each cone (sg), or the MIS quadrature (sample)", choices=("sg", "sample")),
        Param("conductor", "sample", "pixels with an isotropic GGX roughconductor: the MIS quadrature (sample) or the "
              "lobe as a spherical Gaussian over each cone (sg; scenes whose roughconductors are all GGX)",
              choices=("sg", "sample")),
        Param("glossy", "full", "pixels whose BSDF is purely glossy (rough conductors) on the MIS quadrature: all "
              "the shading directions (full) or half of them (half; faster, noisier: docs/cones.md)",
              choices=("full", "half")),
        Param("compact", "on", "on: the pixels that take the MIS quadrature shaded in a launch of their own, packed "
              "(the same images; off: in the launch of all pixels, in a branch)", choices=("on", "off")),
        Param("batch", "viewers", "viewers: shade all viewers' pixels in one launch (nearest fetch; the same images "
              "as per viewer); off: one launch per viewer", choices=("off", "viewers")),
        Param("freeze", True, "the update, the shading and the cache's entry interactions traced once and replayed "
              "(dr.freeze; the same images); off: traced every frame"),
    ) + PayloadMethod.cache_params

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.cone_params = ConeParams(max_cones=self.max_cones, epsilon=self.epsilon,
                                      shrink_period=self.shrink_period, beta_min_deg=self.beta_min,
                                      stratified=self.samples == "r2", shrink_keeps=self.shrink_keeps,
                                      gone_test=self.gone_test == "axis", front_only=front_side_only(scene))
        self.words = words_per_entry(self.max_cones)
        self.needs = frozenset({BILINEAR_TAPS}) if self.fetch in ("bilinear", "stochastic") else frozenset()

    def ray_policy(self) -> RayPolicy:
        return self.settings_ray_policy(budget=self.ray_budget)

    # ------------------------------------------------------------------ update
    def update(self, ctx, fr, policy):
        info = {}
        moving = policy.moving
        self.storage, motion = update_entries(
            self.scene.mi_scene, self.storage, fr.active, fr.si, policy.rays, policy.unsettled, fr.is_new,
            fr.seed_slot, fr.keys, ctx.frame, self.seed, self.cone_params, info,
            moving=moving, first_sample=policy.first_sample, strata=~moving,
            updater=updater_for(self))
        self._info = info
        return motion

    # ------------------------------------------------------------------ shade
    def shade(self, ctx, fr, v, gb):
        slot = mi.UInt32(fr.pixel_slot[v])
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        if self.fetch == "bilinear":
            # each entry's own local frame (the cones live in it)
            tf = dr.gather(mi.Frame3f, fr.si.sh_frame, fr.pixel_index[v], ok)
            return self._shade_bilinear(gb, slot, ok, tf, ctx.frame)
        if self.fetch == "stochastic":
            slot = self._stochastic_tap(gb, slot, ctx.frame)
        # each pixel's entry frame gathered inside the launch (an index into the entries' frames:
        # no kernel of its own writing nine arrays per pixel; the same values)
        return shader_for(self, self.max_cones)(self.storage, slot, ok, gb.si, mi.UInt32(fr.pixel_index[v]),
                                                self.shade_samples, shade_key(ctx.frame, self.seed), None,
                                                fr.si.sh_frame)

    def shade_all(self, ctx, fr, gbuffers):
        """All viewers' pixels. With ``batch=viewers`` (the default) and the nearest
        fetch, all viewers' pixels are shaded in one launch, then split: each pixel
        keeps the random-number key it has per viewer (its index within its own
        viewer, the frame's key), so the images are the per-viewer ones bit for bit.
        The G-buffers' surface interactions come from the frame's layered G-buffer
        (``gb.layers``, :func:`slc.scene.gbuffer.attach_layers`) when there is one, else
        they are concatenated here; the cache's slots come laid out the same way
        (``fr.layer_slot``, ``fr.layer_index``) or are concatenated here. Otherwise (and for one viewer) :meth:`shade` per viewer."""
        if self.batch != "viewers" or self.fetch != "nearest" or len(gbuffers) < 2:
            return super().shade_all(ctx, fr, gbuffers)
        px = self.pixel_batch(fr, gbuffers)
        # ------------------- one launch, split per viewer -------------------
        # (each pixel's entry frame is gathered inside the launch: ``index`` into the frames)
        out = shader_for(self, self.max_cones)(self.storage, px.slot, px.active, px.si, px.index, self.shade_samples,
                                               shade_key(ctx.frame, self.seed), px.pid, fr.si.sh_frame)
        return px.split(out)

    def _shade_bilinear(self, gb, slot, ok, tf, frame):
        """Bilinear fetch: the 4 entries around the pixel's cache coordinate, each
        shaded with ``shade_samples`` directions per cone (as the nearest fetch) and
        weighted bilinearly. Splitting the directions over the taps (``shade_samples
        / 4`` each) made the quadrature error of every tap 4x coarser: on surfaces
        that miss the Lambertian closed form (a two-sided wall seen from its back,
        glossy BSDFs) it doubled FLIP (docs/cones.md, "Bilinear fetch"). The cones
        of every tap are read in the frame of the pixel's own entry (taps lie on
        the same island, so their normals agree to within its bound). Taps are
        limited to the entries this viewer requested this frame, so that another
        viewer cannot change this one's image. Pixels with no usable tap fall back
        to the nearest entry."""
        K = self.max_cones
        taps, weights = self.cache.bilinear_taps(gb, slot)     # this viewer's own entries only
        nS = self.shade_samples
        shade = shader_for(self, K)
        acc = dr.zeros(mi.Color3f, gb.size)
        for j, (s_j, w_j) in enumerate(zip(taps, weights)):
            m = ok & (w_j > 0.0)
            acc += w_j * shade(self.storage, s_j, m, gb.si, tf, nS, shade_key(frame, self.seed, j))
        total = weights[0] + weights[1] + weights[2] + weights[3]
        near = shade(self.storage, slot, ok & (total <= 0.0), gb.si, tf, self.shade_samples,
                     shade_key(frame, self.seed, 4))
        return dr.select(total > 0.0, acc, near)

    def _stochastic_tap(self, gb, slot, frame):
        """Stochastic bilinear fetch: one of the 4 bilinear taps per pixel, drawn
        with probability equal to its bilinear weight (a hash of the pixel index
        and an opaque per-frame key), so that the expected shading is the
        bilinear fetch's at the cost of one quadrature, as the nearest fetch.
        Pixels with no usable tap keep their nearest entry."""
        taps, weights = self.cache.bilinear_taps(gb, slot)     # this viewer's own entries only
        key = dr.opaque(mi.UInt32, shade_key(frame, self.seed, 5))
        h, _ = mi.sample_tea_32(dr.arange(mi.UInt32, gb.size), key, 4)
        u = mi.Float(h >> 8) * (1.0 / 16777216.0)
        chosen, cdf, done = mi.UInt32(slot), mi.Float(0.0), mi.Bool(False)
        for s_j, w_j in zip(taps, weights):
            cdf += w_j
            take = ~done & (w_j > 0.0) & (u < cdf)
            chosen = dr.select(take, s_j, chosen)
            done |= take
        return chosen

    def stats(self) -> dict:
        out = super().stats()
        for k in ("shrunk", "dropped"):
            v = getattr(self, "_info", {}).get(k)
            out[f"{k}_entries"] = float(int(dr.count(v)[0]) if v is not None and dr.width(v) else 0)
        return out


register("slc", SurfaceLightCones,
         help="Surface Light Cones: up to 3 cones per on-surface cache entry, 16 shading samples per cone")
