"""PT: path tracing at N paths per pixel, the equal-time baseline of the indirect-light methods."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.freeze import FrozenFunction
from slc.scene.lights import direct_sample, light_inputs, stream_state
from slc.methods import Method, MethodError, Param, register
from slc.reference.references import STREAM_INDIRECT, indirect_paths

_STREAM_DIRECT = 3


def _pt_kernel(scene, lights, si0, active0, s_ind, s_dir, spp: int, bounces: int, full: bool):
    """The estimator of :class:`PathTracing` for the points ``si0`` (``active0`` valid), random
    streams from the init states ``s_ind`` / ``s_dir``. The indirect part is
    :func:`slc.reference.references.indirect_light` line for line (same streams: the same numbers for the
    same seed); ``lights`` (:func:`slc.scene.lights.light_inputs`) declares the emitter table
    read by the project's light sampling (direct part) as an input."""
    idx = dr.arange(mi.UInt64, dr.width(active0))

    # ------------------ indirect: BSDF-sampled bounces, NEE after each ------------------
    sampler = mi.PCG32(size=dr.width(active0), initstate=s_ind, initseq=idx)
    L = indirect_paths(scene, si0, active0, sampler, spp, bounces)
    if full:
        # ------------------ direct light: spp light samples ------------------
        bsdf, ctx, n = si0.bsdf(), mi.BSDFContext(), dr.opaque(mi.UInt32, spp)
        sd = mi.PCG32(size=dr.width(active0), initstate=s_dir, initseq=idx)

        def cond_d(i, Ld, sd):
            return i < n

        def body_d(i, Ld, sd):
            u = mi.Point2f(sd.next_float32(), sd.next_float32())
            return i + 1, Ld + direct_sample(scene, si0, bsdf, u, active0, ctx), sd

        _, Ld, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sd), cond=cond_d, body=body_d,
                                 labels=("i", "Ld", "sd"))
        L = L + Ld / float(spp)
    dr.eval(L)
    return L


class PathTracing(Method):
    r"""Path tracing with ``spp`` paths per pixel from the G-buffer point (``pt``).

    Indirect light is the estimator of the indirect reference (:func:`slc.reference.references.indirect_light`:
    BSDF-sampled bounces, next-event estimation at every vertex after the first, emitters hit by
    bounce rays not counted) with this method's own per-frame seed, so at ``spp`` = the reference's
    sample count it is the reference's estimator with other random numbers:

    .. math:: L_{ind}(x_0) \approx \frac{1}{n}\sum_{s=1}^{n}\sum_{b=1}^{B}
              \beta_b \frac{f(x_b) L_e G V}{p}

    ``output=full`` adds direct light by ``spp`` light samples with shadow rays
    (:func:`slc.scene.lights.direct_sample`). No state is kept across frames (no temporal reuse).

    ``freeze`` (on): the estimator is traced once and replayed (:class:`slc.core.freeze.FrozenFunction`,
    the frame's random streams passed in as opaque arrays): tracing it (BSDF and emitter calls) cost
    most of a frame at small resolutions, host time that a real-time renderer does not pay. The
    images are those of the traced estimator (``freeze=0``) bit for bit.
    """

    name = "pt"
    output = "full"
    params = (
        Param("spp", 1, "paths (and direct light samples) per pixel", lo=1, hi=1 << 16),
        Param("bounces", 2, "indirect bounces", lo=1, hi=16),
        Param("output", "full", "direct + indirect, or indirect light only", choices=("full", "indirect")),
        Param("freeze", True, "trace the estimator once and replay it (dr.freeze)"),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.label = f"pt{self.spp}" + ("" if self.output == "full" else ":indirect")
        self._pixels = 0
        self._kernel = None

    def validate(self):
        if self.output not in ("full", "indirect"):
            raise MethodError(f"{self.name}: output must be full or indirect")

    def shade(self, ctx, fr, v: int, gb) -> mi.Color3f:
        if self._kernel is None:
            self._kernel = FrozenFunction(_pt_kernel, bool(self.freeze))
        sc, seed = self.scene.mi_scene, self.seed_for(ctx.frame, v)
        return self._kernel(sc, light_inputs(sc), gb.si, mi.Bool(gb.valid),
                            stream_state(seed, STREAM_INDIRECT + int(self.bounces)),
                            stream_state(seed, _STREAM_DIRECT), int(self.spp), int(self.bounces),
                            self.output == "full")

    def finish(self, ctx, fr, gbuffers, outs, timer):
        self._pixels = sum(g.size for g in gbuffers)
        return outs

    def memory_bytes(self) -> int:
        return 12 * self._pixels


register("pt", PathTracing, help="path tracing, spp paths per pixel (full or indirect light), equal-time baseline")
