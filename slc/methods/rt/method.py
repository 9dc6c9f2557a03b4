"""RT-N: N random light samples per pixel, one shadow ray each."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.scene.lights import SurfaceBSDF, direct_sample, rng
from slc.methods import Method, Param, register


class RandomLightSampling(Method):
    r"""Random light sampling with N samples per pixel (``rt16``, ``rt48``, ``rtN``).

    .. math:: L_o(x) \approx \frac{1}{N}\sum_{k=1}^{N} f_r(x, \omega_k, \omega_o)
              \frac{L_e(y_k)\,G(x, y_k)\,V(x, y_k)}{p(y_k)}

    Each sample picks an emitter and a point on it (``slc.scene.lights.sample_light``:
    the scene's emitter table, or ``scene.sample_emitter_direction`` with
    ``SLC_EMITTER_SAMPLING=mitsuba``), traces one shadow ray and evaluates
    the BSDF (cosine included; :class:`slc.scene.lights.SurfaceBSDF`: diffuse
    BSDFs without the virtual call, their albedo read once per pixel). Emitted radiance of directly seen emitters is
    added by the pipeline (:func:`slc.scene.gbuffer.compose`).

    Memory: none beyond the frame (per-viewer output buffer of 12 bytes per
    pixel is counted).
    """
    name = "rt"
    params = (Param("n", 16, "light samples (and shadow rays) per pixel", lo=1),)

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.name = f"rt{self.n}"
        self._pixels = 0

    def shade(self, ctx, fr, v: int, gb) -> mi.Color3f:
        sc = self.scene.mi_scene
        sampler = rng(gb.size, self.seed_for(ctx.frame, v), stream=1)
        si, active = gb.si, gb.valid
        ctx = mi.BSDFContext()
        bsdf = SurfaceBSDF(sc, si, active, ctx)   # diffuse albedo read once per pixel, not per sample
        n_opaque = dr.opaque(mi.UInt32, self.n)

        # ------------------ N light samples in a symbolic loop ------------------
        def cond(i, L, sampler):
            return i < n_opaque

        def body(i, L, sampler):
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            L += direct_sample(sc, si, bsdf, u, active, ctx)
            return i + 1, L, sampler

        # every state variable changes in the body: no loop-invariant state to find, so the body
        # is traced once (with OptimizeLoops, Dr.Jit traces it a second time to look for some)
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
            _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                    labels=("i", "L", "sampler"))
        return L / float(max(self.n, 1))

    def finish(self, ctx, fr, gbuffers, outs, timer):
        self._pixels = sum(g.size for g in gbuffers)
        return outs

    def memory_bytes(self) -> int:
        return 12 * self._pixels


register("rt", lambda scene, n=16, **kw: RandomLightSampling(scene, n=n, **kw), pattern=r"rt(\d+)", cls=RandomLightSampling,
         help="rtN: N random light samples per pixel with shadow rays")
