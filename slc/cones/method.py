"""The registered ``slc`` method: Surface Light Cones on the on-surface cache."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..methods import Method, MethodError, register
from .packing import bytes_per_entry, words_per_entry
from .shading import shade_key, shader_for
from .update import INVALID, ConeParams, update_entries


class SurfaceLightCones(Method):
    r"""Surface Light Cones (Stadlbauer et al. 2023) in the on-surface cache.

    Each cache entry (a texel = a surface point) keeps up to ``max_cones`` cones
    (axis :math:`D_c` in the entry's local frame, half-angle :math:`\alpha_c`,
    RGB :math:`L_c`), an accumulation count :math:`C` and a cone count, packed in
    286 bits (3 RGB32 texels, 36 bytes) for 3 cones.

    Estimator. :math:`L_c` is a running estimate of
    :math:`E_c = \int_{\Omega_c} L_i(x,\omega)\,d\omega` (incoming radiance integrated
    over the cone's solid angle, no cosine). One update cycle draws ``n`` light samples
    at the entry's own surface point with weights
    :math:`w_k = L_e G / p \cdot V` (``scene.sample_emitter_direction`` + shadow ray),
    inserts them one after another (cases A-D) and sets

    .. math:: L_c \leftarrow L_c (1 - 1/C) + \frac{1}{C}\,\frac{1}{n}\sum_k [\omega_k \in c]\, w_k,

    with :math:`C` incremented once per cycle (capped at 255) and reduced by
    :math:`\min(\max(1 + 0.05\,\beta, 1.01), 3)` (:math:`\beta` in degrees) when a cone
    turned. Shading (no rays, ``shade_samples`` stratified directions per cone):

    .. math:: L_o = \sum_c \sum_{s=1}^{n_S} f_r(x, \omega_{c,s}, \omega_o)\cos\theta_{c,s}\, L_c / n_S .

    Parameters (defaults): ``max_cones=3`` (1-4), ``shade_samples=16``,
    ``rays_new=8`` (update rays of new / moving entries, their first 8 updates),
    ``rays_settled=1``, ``bias=1.0`` (cache mip bias), ``block=8`` (block size),
    ``evict_after=60`` (frames), ``epsilon=0.1`` (shrink test at (1-epsilon) alpha),
    ``shrink_period=4`` (settled entries test every k-th frame), ``beta_min=1.0``
    (degrees: smaller cone turns neither reduce C nor count as motion).
    See docs/cones.md.
    """

    name = "slc"
    shared = True

    def __init__(self, scene, max_cones: int = 3, shade_samples: int = 16, rays_new: int = 8,
                 rays_settled: int = 1, bias: float = 1.0, block: int = 8, evict_after: int = 60,
                 epsilon: float = 0.1, shrink_period: int = 4, beta_min: float = 1.0, fetch: str = "nearest",
                 cache=None, **kw):
        super().__init__(scene, **kw)
        if not 1 <= int(max_cones) <= 4:
            raise MethodError(f"slc: max_cones must be 1-4 (got {max_cones})")
        if not 0.0 < float(epsilon) < 1.0:
            raise MethodError(f"slc: epsilon must be in (0, 1) (got {epsilon})")
        self.params = ConeParams(max_cones=int(max_cones), epsilon=float(epsilon),
                                 shrink_period=int(shrink_period), beta_min_deg=float(beta_min),
                                 rays_settled=float(rays_settled))
        self.shade_samples = int(shade_samples)
        self.rays_new, self.rays_settled = int(rays_new), int(rays_settled)
        self.bias, self.block, self.evict_after = float(bias), int(block), int(evict_after)
        if fetch not in ("nearest", "bilinear"):
            raise MethodError(f"slc: fetch must be 'nearest' or 'bilinear' (got {fetch})")
        self.fetch = fetch
        self._cache_arg = cache
        self.cache = None
        self.storage = None
        self._last = {}

    def settings(self):
        return {"max_cones": self.params.max_cones, "shade_samples": self.shade_samples,
                "rays_new": self.rays_new, "rays_settled": self.rays_settled, "bias": self.bias,
                "block": self.block, "evict_after": self.evict_after, "epsilon": self.params.epsilon,
                "shrink_period": self.params.shrink_period, "beta_min": self.params.beta_min_deg}

    # ------------------------------------------------------------------ state
    def reset(self):
        self.cache = None
        self.storage = None
        self._last = {}

    def _make_cache(self):
        from ..osc import cache_for
        self.cache = cache_for(self.scene, self._cache_arg, self.block, self.bias, self.evict_after,
                               bytes_per_entry(self.params.max_cones))

    def _ensure_storage(self):
        need = int(self.cache.capacity) * words_per_entry(self.params.max_cones)
        if self.storage is None:
            self.storage = dr.zeros(mi.UInt32, max(need, 1))
        elif dr.width(self.storage) < need:
            old = self.storage
            self.storage = dr.zeros(mi.UInt32, need)
            dr.scatter(self.storage, old, dr.arange(mi.UInt32, dr.width(old)))
            dr.eval(self.storage)

    def _rays(self, rays):
        rays = mi.UInt32(rays)
        if self.rays_new == 8 and self.rays_settled == 1:
            return rays
        return dr.select(rays > 1, mi.UInt32(self.rays_new), mi.UInt32(self.rays_settled))

    # ------------------------------------------------------------------ frame
    def render(self, ctx, gbuffers, timer):
        if self.cache is None:
            self._make_cache()
        fr = self.cache.begin_frame(ctx.frame, gbuffers, timer)
        self._ensure_storage()
        K = self.params.max_cones
        st_info = {}
        with timer.stage("update") as st:
            n_active = dr.width(fr.active)
            motion = mi.Bool()
            if n_active > 0:
                keys = self.cache.entry_keys(fr.active) if hasattr(self.cache, "entry_keys") else None
                self.storage, motion = update_entries(
                    self.scene.mi_scene, self.storage, fr.active, fr.si, self._rays(fr.rays), fr.is_new,
                    fr.seed_slot, ctx.frame, self.seed, self.params, st_info, keys=keys)
                self.cache.mark_motion(fr.active, motion)
                st.outputs(self.storage)
        with timer.stage("shade") as st:
            outs = []
            for v, gb in enumerate(gbuffers):
                if n_active == 0:
                    outs.append(dr.zeros(mi.Color3f, gb.size))
                    continue
                slot = mi.UInt32(fr.pixel_slot[v])
                ok = mi.Bool(gb.valid) & (slot != INVALID)
                # each entry's own local frame (the cones live in it)
                tf = dr.gather(mi.Frame3f, fr.si.sh_frame, fr.pixel_index[v], ok)
                if self.fetch == "bilinear" and hasattr(self.cache, "bilinear_taps"):
                    outs.append(self._shade_bilinear(gb, slot, ok, tf, K, ctx.frame))
                else:
                    outs.append(shader_for(self, K)(self.storage, slot, ok, gb.si, tf, self.shade_samples,
                                                    shade_key(ctx.frame, self.seed)))
            st.outputs(*outs)
        self._last = {"active_entries": n_active, "motion_entries": motion,
                      "shrunk_entries": st_info.get("shrunk"), "dropped_entries": st_info.get("dropped")}
        return outs

    def _shade_bilinear(self, gb, slot, ok, tf, K, frame=0):
        """Bilinear fetch: the 4 entries around the pixel's cache coordinate, each
        shaded with ``shade_samples / 4`` directions per cone and weighted
        bilinearly (the same number of BSDF evaluations as a nearest fetch). The
        cones of every tap are read in the frame of the pixel's own entry (taps
        lie on the same island, so their normals agree to within its bound).
        Pixels with no usable tap fall back to the nearest entry."""
        taps, weights = self.cache.bilinear_taps(gb)
        nS = max(self.shade_samples // 4, 1)
        shade = shader_for(self, K)
        acc = dr.zeros(mi.Color3f, gb.size)
        for j, (s_j, w_j) in enumerate(zip(taps, weights)):
            m = ok & (w_j > 0.0)
            acc += w_j * shade(self.storage, s_j, m, gb.si, tf, nS, shade_key(frame, self.seed, j))
        total = weights[0] + weights[1] + weights[2] + weights[3]
        near = shade(self.storage, slot, ok & (total <= 0.0), gb.si, tf, self.shade_samples,
                     shade_key(frame, self.seed, 4))
        return dr.select(total > 0.0, acc, near)

    def memory_bytes(self) -> int:
        return int(self.cache.memory_bytes()) if self.cache is not None else 0

    def stats(self) -> dict:
        out = dict(self.cache.stats()) if self.cache is not None else {}
        for k, v in self._last.items():
            if isinstance(v, mi.Bool):
                v = int(dr.count(v)[0]) if dr.width(v) > 0 else 0
            out[k] = float(v or 0)
        return out


def _factory(scene, **kw):
    return SurfaceLightCones(scene, **kw)


register("slc", _factory,
         help="Surface Light Cones: up to 3 cones per on-surface cache entry, 16 shading samples per cone "
              "(settings: max_cones, shade_samples, rays_new, rays_settled, bias, block, epsilon)")
