"""The registered ``sh`` method: incident direct radiance as SH (YCoCg with
compressed chrominance) in the on-surface cache."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..lights import finite, sample_light, visible
from ..methods import Method, MethodError, register
from .project import irradiance, project, radiance
from .ycocg import ENCODINGS, encoding as get_encoding

INVALID = 0xFFFFFFFF


def _slot_rng(slots: mi.UInt32, seed: int, frame: int) -> mi.PCG32:
    """One PCG32 stream per cache slot and frame (independent of how many
    slots are active); the key is opaque, so no recompilation per frame."""
    s = mi.PCG32(size=dr.width(slots))
    key = dr.opaque(mi.UInt32, (int(seed) * 0x9E3779B1 + int(frame) * 0x85EBCA77 + 0x27D4EB2F) & 0xFFFFFFFF)
    v0, v1 = mi.sample_tea_32(mi.UInt32(slots), key, 4)
    s.inc = (mi.UInt64(slots) << 1) | 1
    s.state = (mi.UInt64(v0) << 32) | mi.UInt64(v1)
    s.next_uint32()
    return s


class SHSurfaceCache(Method):
    r"""SH radiance cache on the on-surface cache (``sh``).

    Each entry (texel = surface point x of its own) stores the incident
    direct radiance :math:`L_i(x, \omega)` projected onto real SH in the
    chosen encoding (default Y3Co1Cg1, 11 coefficients; ``rgb3``,
    ``y3co3cg3``, ``y3co2cg2``). One update draws ``rays`` light samples at x
    (``slc.lights.sample_light`` + shadow ray; lights below the
    texel's surface are dropped) and estimates

    .. math:: \hat\lambda_{lm} = \frac{1}{n}\sum_k \frac{L_e(\omega_k) V}{p(\omega_k)} Y_{lm}(\omega_k),
              \qquad \lambda \leftarrow \lambda + (\hat\lambda - \lambda)/C,

    with :math:`C` the update count capped at ``max_count`` (an exponential
    moving average once capped, so moving lights fade in). A new entry
    starts from its LOD seed (a coarser entry) when there is one.

    Shading per pixel, no rays: diffuse-only BSDFs in closed form,
    :math:`L_o = \rho/\pi\, E(n)` with the Ramamoorthi-Hanrahan irradiance;
    other BSDFs by ``glossy_samples`` BSDF samples of the reconstructed
    radiance, :math:`L_o = \frac{1}{n}\sum_j w_j\, \tilde L_i(\omega_j)`.
    Suited to smooth direct light (environment maps, large lights); small
    lights are blurred by the 3-band truncation.

    Parameters (defaults): ``encoding`` ("y3co1cg1"), ``max_count`` (16),
    ``glossy_samples`` (8), ``bias`` (1.0), ``block`` (8), ``evict_after``
    (60), ``presence``/``bleeding`` (1, 1). Memory: the OSC's allocated
    blocks x (4 bytes x coefficients + 4 bytes count).
    """

    name = "sh"
    shared = True

    def __init__(self, scene, encoding: str = "y3co1cg1", max_count: int = 16, glossy_samples: int = 8,
                 bias: float = 1.0, block: int = 8, evict_after: int = 60, presence: float = 1.0,
                 bleeding: float = 1.0, cache=None, **kw):
        super().__init__(scene, **kw)
        try:
            self.enc = get_encoding(encoding)
        except ValueError as e:
            raise MethodError(f"sh: {e}") from None
        self.max_count = max(int(max_count), 1)
        self.glossy_samples = max(int(glossy_samples), 1)
        self.bias, self.block, self.evict_after = float(bias), int(block), int(evict_after)
        self.presence, self.bleeding = float(presence), float(bleeding)
        self._cache_arg = cache
        if self.enc.name != "y3co1cg1":
            self.label = f"sh:{self.enc.name}"
        self.reset()

    def settings(self):
        return {"encoding": self.enc.name, "max_count": self.max_count, "glossy_samples": self.glossy_samples,
                "bias": self.bias, "block": self.block, "evict_after": self.evict_after}

    # ------------------------------------------------------------------ state
    def reset(self):
        self.cache = None
        self.coeffs = None   # capacity x n floats, slot-major
        self.count = None    # capacity update counts
        self._last = {}

    def _make_cache(self):
        from ..osc import cache_for
        self.cache = cache_for(self.scene, self._cache_arg, self.block, self.bias, self.evict_after,
                               4 * self.enc.n + 4)

    def _ensure_storage(self):
        cap = max(int(self.cache.capacity), 1)
        n = self.enc.n
        if self.coeffs is None:
            self.coeffs = dr.zeros(mi.Float, cap * n)
            self.count = dr.zeros(mi.UInt32, cap)
        elif dr.width(self.count) < cap:
            old_c, old_n = self.coeffs, self.count
            self.coeffs = dr.zeros(mi.Float, cap * n)
            self.count = dr.zeros(mi.UInt32, cap)
            dr.scatter(self.coeffs, old_c, dr.arange(mi.UInt32, dr.width(old_c)))
            dr.scatter(self.count, old_n, dr.arange(mi.UInt32, dr.width(old_n)))
            dr.eval(self.coeffs, self.count)

    # ----------------------------------------------------------------- update
    def _update(self, frame, fr):
        sc, enc, n = self.scene.mi_scene, self.enc, self.enc.n
        slots, si = fr.active, fr.si
        rays = dr.maximum(mi.UInt32(fr.rays), 1)
        sampler = _slot_rng(slots, self.seed, frame)
        ng = mi.Vector3f(si.n)

        # ------------------- light samples at the texel's own point -------------------
        def cond(i, acc, sampler):
            return i < rays

        def body(i, acc, sampler):
            u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            ds, w, ok = sample_light(sc, si, u, i < rays)
            ok &= dr.dot(ds.d, ng) > 0.0
            ok = visible(sc, si, ds, ok)
            c = project(enc, ds.d, finite(dr.select(ok, w, 0.0)))
            return i + 1, [a + b for a, b in zip(acc, c)], sampler

        acc0 = [mi.Float(0.0) for _ in range(n)]
        _, acc, _ = dr.while_loop(state=(mi.UInt32(0), acc0, sampler), cond=cond, body=body,
                                  labels=("i", "acc", "sampler"))
        inv = dr.rcp(mi.Float(rays))

        # ------------------------- running mean, LOD seeding -------------------------
        is_new = mi.Bool(fr.is_new)
        seed_slot = mi.UInt32(fr.seed_slot)
        seeded = is_new & (seed_slot != INVALID)
        C_old = dr.select(is_new, dr.select(seeded, 1, 0), dr.gather(mi.UInt32, self.count, slots))
        C = dr.minimum(C_old + 1, self.max_count)
        a = dr.rcp(mi.Float(C))
        src = dr.select(seeded, seed_slot, slots)
        for c in range(n):
            old = dr.gather(mi.Float, self.coeffs, src * n + c, ~is_new | seeded)
            dr.scatter(self.coeffs, dr.fma(a, acc[c] * inv - old, old), slots * n + c)
        dr.scatter(self.count, C, slots)

    # ------------------------------------------------------------------ shade
    def _shade(self, gb, slot):
        enc, n = self.enc, self.enc.n
        si = gb.si
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        coeffs = [dr.gather(mi.Float, self.coeffs, slot * n + c, ok) for c in range(n)]
        bsdf = si.bsdf()
        ctx = mi.BSDFContext()
        flags = bsdf.flags()
        diffuse_only = ~mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Delta)

        # ------------------- diffuse: closed-form irradiance -------------------
        nrm = mi.Vector3f(si.sh_frame.n)
        E = mi.Color3f(*irradiance(enc, coeffs, nrm, self.presence, self.bleeding))
        rho = mi.Color3f(bsdf.eval_diffuse_reflectance(si, ok & diffuse_only))
        L = dr.select(diffuse_only & (si.wi.z > 0.0), rho * E * (1.0 / math.pi), 0.0)

        # -------------- glossy: BSDF samples of the reconstructed radiance --------------
        g = ok & ~diffuse_only
        sampler = _slot_rng(dr.arange(mi.UInt32, gb.size), self.seed, 0x5A5A)
        ns = dr.opaque(mi.UInt32, self.glossy_samples)

        def cond(i, Lg, sampler):
            return i < ns

        def body(i, Lg, sampler):
            u1 = sampler.next_float32()
            u2 = mi.Point2f(sampler.next_float32(), sampler.next_float32())
            bs, bw = bsdf.sample(ctx, si, u1, u2, g)
            okj = g & (bs.pdf > 0.0)
            Li = mi.Color3f(*radiance(enc, coeffs, si.to_world(bs.wo), self.presence, self.bleeding))
            return i + 1, Lg + dr.select(okj, mi.Color3f(bw) * Li, 0.0), sampler

        if dr.any(g):
            _, Lg, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                     labels=("i", "Lg", "sampler"))
            L += Lg * (1.0 / float(self.glossy_samples))
        return finite(dr.select(ok, L, 0.0))

    # ------------------------------------------------------------------ frame
    def render(self, ctx, gbuffers, timer):
        if self.cache is None:
            self._make_cache()
        fr = self.cache.begin_frame(ctx.frame, gbuffers, timer)
        self._ensure_storage()
        n_active = dr.width(fr.active)
        with timer.stage("update") as st:
            if n_active > 0:
                self._update(ctx.frame, fr)
                st.outputs(self.coeffs, self.count)
        with timer.stage("shade") as st:
            outs = []
            for gb, slot in zip(gbuffers, fr.pixel_slot):
                if n_active == 0:
                    outs.append(dr.zeros(mi.Color3f, gb.size))
                else:
                    outs.append(self._shade(gb, mi.UInt32(slot)))
            st.outputs(*outs)
        self._last = {"active_entries": n_active}
        return outs

    def memory_bytes(self) -> int:
        return int(self.cache.memory_bytes()) if self.cache is not None else 0

    def stats(self) -> dict:
        out = dict(self.cache.stats()) if self.cache is not None else {}
        out.update({k: float(v) for k, v in self._last.items()})
        return out


register("sh", lambda scene, **kw: SHSurfaceCache(scene, **kw),
         help="SH (YCoCg, compressed chrominance) incident direct radiance in the on-surface cache; "
              f"settings: encoding ({'/'.join(ENCODINGS)}), max_count, glossy_samples, bias, block")
