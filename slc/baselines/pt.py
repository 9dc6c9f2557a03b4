"""PT: path tracing at N paths per pixel, the equal-time baseline of the indirect-light methods."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..lights import direct_sample, rng
from ..methods import MethodError, Param, register
from ..methods import Method
from ..references import indirect_light


class PathTracing(Method):
    r"""Path tracing with ``spp`` paths per pixel from the G-buffer point (``pt``).

    Indirect light is the estimator of the indirect reference (:func:`slc.references.indirect_light`:
    BSDF-sampled bounces, next-event estimation at every vertex after the first, emitters hit by
    bounce rays not counted) with this method's own per-frame seed, so at ``spp`` = the reference's
    sample count it is the reference's estimator with other random numbers:

    .. math:: L_{ind}(x_0) \approx \frac{1}{n}\sum_{s=1}^{n}\sum_{b=1}^{B}
              \beta_b \frac{f(x_b) L_e G V}{p}

    ``output=full`` adds direct light by ``spp`` light samples with shadow rays
    (:func:`slc.lights.direct_sample`). No state is kept across frames (no temporal reuse).
    """

    name = "pt"
    output = "full"
    params = (
        Param("spp", 1, "paths (and direct light samples) per pixel", lo=1, hi=1 << 16),
        Param("bounces", 2, "indirect bounces", lo=1, hi=16),
        Param("output", "full", "direct + indirect, or indirect light only", choices=("full", "indirect")),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.label = f"pt{self.spp}" + ("" if self.output == "full" else ":indirect")
        self._pixels = 0

    def validate(self):
        if self.output not in ("full", "indirect"):
            raise MethodError(f"{self.name}: output must be full or indirect")

    def shade(self, gb, frame: int, v: int) -> mi.Color3f:
        sc, seed = self.scene.mi_scene, self.seed_for(frame, v)
        L = indirect_light(sc, gb, self.spp, self.bounces, seed=seed)
        if self.output == "full":
            si, active, bsdf, ctx = gb.si, gb.valid, gb.si.bsdf(), mi.BSDFContext()
            sampler = rng(gb.size, seed, stream=3)
            n = dr.opaque(mi.UInt32, self.spp)

            # ------------------ direct light: spp light samples ------------------
            def cond(i, Ld, sampler):
                return i < n

            def body(i, Ld, sampler):
                u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
                return i + 1, Ld + direct_sample(sc, si, bsdf, u, active, ctx), sampler

            _, Ld, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                     labels=("i", "Ld", "sampler"))
            L = L + Ld / float(self.spp)
        return L

    def render(self, ctx, gbuffers, timer):
        self._pixels = sum(g.size for g in gbuffers)
        with timer.stage("shade") as st:
            outs = [self.shade(gb, ctx.frame, v) for v, gb in enumerate(gbuffers)]
            st.outputs(*outs)
        return outs

    def memory_bytes(self) -> int:
        return 12 * self._pixels


register("pt", PathTracing, help="path tracing, spp paths per pixel (full or indirect light), equal-time baseline")
