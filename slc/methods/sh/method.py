"""The registered ``sh`` method: incident direct radiance as SH (YCoCg with
compressed chrominance) in the on-surface cache."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.core.keys import INVALID, STREAM_SH_SHADE, STREAM_SH_UPDATE, keyed_rng
from slc.methods import Param, register
from slc.methods.cache_method import PayloadMethod, RayPolicy, entry_start
from slc.lib.sh.project import irradiance, radiance
from slc.lib.sh.shading import shade_radiance
from slc.lib.sh.update import project_samples, running_mean, world_frame
from slc.lib.sh.ycocg import ENCODINGS, encoding as get_encoding
from slc.scene.bsdf_table import side_normal, two_sided


class SHSurfaceCache(PayloadMethod):
    r"""SH radiance cache on the on-surface cache (``sh``).

    Each entry (texel = surface point x of its own) stores the incident
    direct radiance :math:`L_i(x, \omega)` projected onto real SH in the
    chosen encoding (default Y3Co1Cg1, 11 coefficients; ``rgb3``,
    ``y3co3cg3``, ``y3co2cg2``). One update draws ``rays`` light samples at x
    (``slc.scene.lights.sample_light`` + shadow ray; lights below the
    texel's surface are dropped) and estimates

    .. math:: \hat\lambda_{lm} = \frac{1}{n}\sum_k \frac{L_e(\omega_k) V}{p(\omega_k)} Y_{lm}(\omega_k),
              \qquad \lambda \leftarrow \lambda + \min(n/C, 1)(\hat\lambda - \lambda),

    with :math:`C` the sample count capped at ``max_count`` (an exponential
    moving average once capped, so moving lights fade in; :mod:`slc.lib.sh.update`,
    shared with the adaptive cache's SH records): a new entry's ``rays_new``-sample
    updates average evenly until the cap, a settled entry's 1-sample update
    weighs ``1/max_count``. A new entry starts from its LOD seed (a coarser
    entry, weighing as one update of ``rays_new`` samples) when there is one.

    Shading per pixel, no rays: diffuse-only BSDFs in closed form,
    :math:`L_o = \rho/\pi\, E(n)` with the Ramamoorthi-Hanrahan irradiance;
    other BSDFs by ``glossy_samples`` BSDF samples of the reconstructed
    radiance, :math:`L_o = \frac{1}{n}\sum_j w_j\, \tilde L_i(\omega_j)`.
    Suited to smooth direct light (environment maps, large lights); small
    lights are blurred by the 3-band truncation.

    Storage per entry: the coefficients and the count, one float word each
    (4 bytes x (coefficients + 1)). Ray policy: ``rays_new`` for an entry's
    first 8 updates, ``rays_settled`` afterwards (SH reports no motion).
    """

    name = "sh"
    params = (
        Param("encoding", "y3co1cg1", "SH encoding (bands per channel)", choices=tuple(ENCODINGS)),
        Param("max_count", 64, "running-mean cap on the sample count, then an exponential moving average "
              "[samples]", lo=1),
        Param("glossy_samples", 8, "BSDF samples of the reconstructed radiance per glossy pixel", lo=1, hi=1024),
        Param("rays_new", 8, "update rays of new entries", lo=1, hi=1024),
        Param("rays_settled", 1, "update rays of settled entries", lo=1, hi=1024),
        Param("presence", 1.0, "presence scale of the chrominance reconstruction", lo=0.0),
        Param("bleeding", 1.0, "colour-bleeding scale of the chrominance reconstruction", lo=0.0),
    ) + PayloadMethod.cache_params
    storage_type = mi.Float

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.enc = get_encoding(self.encoding)
        self.words = self.enc.n + 1          # coefficients, then the count
        if self.enc.name != "y3co1cg1":
            self.label = f"sh:{self.enc.name}"

    def ray_policy(self) -> RayPolicy:
        return RayPolicy(new=self.rays_new, settled=self.rays_settled, moving=self.rays_new)

    # ----------------------------------------------------------------- update
    def update(self, ctx, fr, policy):
        sc, enc, n, rays = self.scene.mi_scene, self.enc, self.enc.n, policy.rays
        slots, si = fr.active, fr.si
        sampler = keyed_rng(fr.keys, self.seed, ctx.frame, STREAM_SH_UPDATE)
        acc, _ = project_samples(sc, si, world_frame(), rays, sampler, si.is_valid(), enc,
                                 two=two_sided(sc, si.bsdf(), si.is_valid()))

        # ------------------------- running mean, LOD seeding -------------------------
        # a new entry starts empty, or from its LOD seed (a coarser entry) weighing as one update
        # of a new entry (rays_new samples)
        start = entry_start(fr.is_new, fr.seed_slot, slots)
        C_old = dr.select(fr.is_new, dr.select(start.seeded, float(self.rays_new), 0.0), self.read(slots, n))
        old = [self.read(start.src, c, start.keep) for c in range(n)]
        coeffs, C = running_mean(old, C_old, acc, rays, self.max_count)
        for c in range(n):
            self.write(coeffs[c], slots, c)
        self.write(C, slots, n)
        return dr.zeros(mi.Bool, dr.width(slots))

    # ------------------------------------------------------------------ shade
    def shade(self, ctx, fr, v, gb):
        enc, n = self.enc, self.enc.n
        slot = mi.UInt32(fr.pixel_slot[v])
        si = gb.si
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        coeffs = self.read(slot, 0, ok, n=n)
        bsdf = si.bsdf()
        two = two_sided(self.scene.mi_scene, bsdf, ok)
        nrm = mi.Vector3f(si.sh_frame.n) if two is None else side_normal(si)
        # world-frame coefficients: the irradiance at the shading normal (turned towards the
        # viewer on two-sided BSDFs), the radiance towards d
        return shade_radiance(
            si, bsdf, ok,
            lambda: mi.Color3f(*irradiance(enc, coeffs, nrm, self.presence, self.bleeding)),
            lambda d, m: (mi.Color3f(*radiance(enc, coeffs, d, self.presence, self.bleeding)), m),
            keyed_rng(dr.arange(mi.UInt32, gb.size), self.seed, 0, STREAM_SH_SHADE), self.glossy_samples, two)


register("sh", SHSurfaceCache,
         help="SH (YCoCg, compressed chrominance) incident direct radiance in the on-surface cache")
