r"""Shading from the cones, no rays: multiple importance sampling of the cones'
radiance with the BSDF.

The cones of an entry define a piecewise-constant model of the incoming radiance

.. math:: \tilde L(\omega) = \sum_{c\,\ni\,\omega} L_c / \Omega_c,
          \qquad \Omega_c = 2\pi (1 - \cos\alpha_c),

(``L_c`` estimates the integral of the incoming radiance over cone ``c``, see
docs/cones.md; overlapping cones add up). The shading integrates
:math:`\int f_r \cos\theta\, \tilde L\, d\omega` with two strategies, combined by
the balance heuristic over all samples of a pixel (Veach's multi-sample MIS):

- cone sampling: ``n_C`` directions uniform in each live cone (pdf ``1/Omega_c``),
  a stratified spherical-Fibonacci pattern rotated per pixel;
- BSDF sampling: ``n_B`` directions from ``bsdf.sample`` (pdf ``p_B``), a
  rank-1 (R3) sequence rotated per pixel.

Every sample, whatever its strategy, contributes

.. math:: f_r \cos\theta\, \tilde L(\omega) \,/\, \Big(n_C \sum_{c\,\ni\,\omega} 1/\Omega_c + n_B\, p_B(\omega)\Big),

which is unbiased for the integral. Cones narrower than ``ALPHA_DELTA`` (point
lights) are Dirac cones: one evaluation on the axis, ``f_r cos L_c``, weight 1.
BSDF samples of a Dirac lobe (mirrors) see ``\tilde L`` with weight 1.
Purely Lambertian pixels use the exact cone integral (no loop):
``(rho/pi) sum_c L_c (n . d_c)(1 + cos alpha_c)/2`` for cones clear of the horizon, the
integral of the cosine over the part of the cap above it for cones across it.
Pixels with Mitsuba's ``principled`` BSDF (no clearcoat, sheen, flatness, anisotropy or
transmission) whose cones have that closed form skip the quadrature too (``principled="sg"``,
the default; :func:`slc.lib.cones.closedforms._principled_cones`): the diffuse part in closed form with its angular
factor at each cone axis, the GGX lobe as a Gaussian around the mirror direction of which
each cap holds a fraction; an approximation, measured in docs/cones.md.
With ``conductor="sg"`` (an option, off by default) isotropic GGX ``roughconductor`` pixels
get the same Gaussian lobe plus GGX's tail at far cones' axes (:func:`slc.lib.cones.closedforms._conductor_cones`).
Each kind of pixel runs in a symbolic branch of its own, and BSDFs without textures are read
from a per-scene table (:func:`bsdf_table`) instead of virtual calls (same images). Pixels
seen from behind whose BSDF only reflects and whose cones all lie in front give 0 without
the quadrature (it would sum zeros); with ``glossy="half"`` (an option) purely glossy BSDFs
(rough conductors) take half the directions. The pixels left to the quadrature are packed
into a launch of their own (``compact``, the default), and the Gaussian lobe's share of a cap
far from its peak (exactly 0) is not computed; both give the same values bit for bit.

Sample counts: ``n_samples`` (n_S) directions, fewer for rough lobes (``n_S' =
ceil(n_S clip(q, 1/4, 1))``), split per pixel into ``n_C`` cone directions per live cone
and ``n_B = n_S' - n_C`` BSDF directions per pixel by the lobe's width against the cones
(``q = p_B(mirror) max_c Omega_c``; at most 3/4 BSDF), so a pixel with ``n`` cones
evaluates its BSDF ``n n_C + n_B`` times (+1 pdf).
Random numbers are hashes of (pixel index, ``key``): deterministic for a given frame,
seed and tap. See docs/cones.md for the expectation.

Each :class:`ConeShading` (one per method instance) owns its own frozen function
(``dr.freeze``), in static and animated scenes alike.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from slc.scene import bsdf_table as bsdf_tables
from slc.scene.bsdf_table import KIND_DIFFUSE, KIND_OTHER
from slc.core.freeze import FrozenFunction
from slc.lib.cones.closedforms import glossy_closed, horizon_terms, lambertian
from slc.lib.cones.conestate import ShadeOptions, cone_state
from slc.lib.cones.quadrature import quadrature, samples_px


def shade_kernel(storage: mi.UInt32, slot: mi.UInt32, active: mi.Bool, si: mi.SurfaceInteraction3f,
                 bsdf: mi.BSDFPtr, texel_frame: mi.Frame3f, n_total: mi.UInt32, key: mi.UInt32,
                 pid: mi.UInt32 | None, table, entry_frames, opts: ShadeOptions) -> mi.Color3f:
    """Direct illumination of the pixels ``si`` (BSDFs ``bsdf``) from the entries
    ``slot``; ``texel_frame`` is the local frame of each pixel's entry (the frame its
    cone directions are stored in). ``n_total`` directions per live cone and ``key``
    are opaque scalars; ``opts`` the shading's choices (:class:`ShadeOptions`, see
    :class:`ConeShading`). ``pid``
    keys each pixel's random numbers (None: its index in the arrays; several viewers
    shaded in one launch pass each pixel's index within its own viewer). ``table``
    (:func:`bsdf_table`, optional) gives the constants of BSDFs without textures. With
    ``entry_frames`` (the entries' frames), ``texel_frame`` is instead each pixel's index
    into them (the gather then runs inside this kernel, not as a kernel of its own).
    Entries without cones and inactive pixels give 0. One traced kernel whose branches
    (Lambertian, principled, quadrature, the compacted quadrature: :func:`_compact_quadrature`)
    share the cone state and the pixel masks."""
    # ------------------- the entries' cones, the pixels' BSDF kinds -------------------
    K = opts.max_cones
    tf_in = texel_frame
    cones = cone_state(storage, slot, active, texel_frame, entry_frames, K, opts.front_only)
    n = cones.n
    ctx = mi.BSDFContext()
    if pid is None:
        pid = dr.arange(mi.UInt32, dr.width(slot))
    # each pixel's BSDF kind and constants from the table (KIND_OTHER: virtual calls)
    kind, consts = _table_consts(table, bsdf, active)

    # ------------------- Lambertian pixels: the cone integral in closed form -------------------
    # A cone clear of the horizon: (1/Omega_c) int_c cos = (n . d_c)(1 + cos alpha_c)/2. With
    # ``horizon``, a cone across it (alpha_c < pi/2) takes the exact integral of cos over the
    # part of its cap above the horizon (Snyder 1996; Lagarde and de Rousiers 2014, sphere
    # lights): int = (cos_d acos(y) - x sin_d sqrt(1 - y^2)) sin^2(alpha) + atan(sin_d sqrt(1 - y^2) / x),
    # x = cot(alpha), y = -x cos_d / sin_d; a cap wholly below (or a Dirac cone below) adds 0.
    # Cones wider than a hemisphere across the horizon still go to sampling.
    closed, cones_ok, clear, term, below_c = horizon_terms(si, active, cones, opts.horizon)
    lambert = lambertian(bsdf, si, active) & cones_ok

    # Each kind of pixel runs in a symbolic branch of its own (Lambertian closed form,
    # principled closed form, quadrature): on the LLVM backend a SIMD packet skips a branch
    # none of its lanes takes, so a pixel pays only for its own kind (the images are the
    # same bit for bit as with every kind computed for every pixel and selected).
    closed = _lambert_branch(bsdf, si, lambert, closed, kind, consts)

    # ------------------- principled (and GGX conductor) pixels: closed forms -------------------
    prin, pfast = glossy_closed(bsdf, si, ctx, active & cones_ok & ~lambert, cones, term, below_c, consts,
                                 opts.principled, opts.conductor)
    # ------------------- pixels seen from behind whose cones are all in front: 0, no quadrature -------------------
    # A BSDF without transmission (or null) lobes reflects only into the side of w_i: with
    # cos(theta_i) <= 0 and every cone wholly above the horizon, f_r = 0 for every direction
    # in the cones, and a BSDF sample (on w_i's side) lies in no cone (L~ = 0): the quadrature
    # sums zeros. (The meeting rig's viewers 4 and 12 see only such pixels: 12 % of its pixels.)
    flags = mi.UInt32(bsdf.flags())
    backside = active & clear & (mi.Frame3f.cos_theta(si.wi) <= 0.0) & \
        ~mi.has_flag(flags, mi.BSDFFlags.Transmission) & ~mi.has_flag(flags, mi.BSDFFlags.Null)
    sampled = active & ~lambert & ~pfast & (n > 0) & ~backside

    if not opts.compact:
        n_px = samples_px(bsdf, n_total, opts.glossy_half)

        def sampled_fn(sampled):
            return quadrature(bsdf, si, ctx, sampled, cones, n_px, key, pid, opts)

        acc = dr.if_stmt(args=(sampled,), cond=sampled, true_fn=sampled_fn,
                         false_fn=lambda sampled: mi.Color3f(0.0), label="quadrature")

        # raw values: a NaN or Inf made here reaches the image, where check mode names it
        return dr.select(lambert, closed, dr.select(pfast, prin, acc))

    # ------------------- the quadrature's pixels compacted into a launch of their own -------------------
    out = dr.select(lambert, closed, dr.select(pfast, prin, 0.0))
    return _compact_quadrature(out, sampled, storage, slot, si, bsdf, tf_in, n_total, key, pid, entry_frames,
                               ctx, opts)


def _lambert_branch(bsdf, si, lambert: mi.Bool, closed: mi.Color3f, kind, consts) -> mi.Color3f:
    """The Lambertian pixels ``lambert``: their diffuse reflectance (from the table where it has
    their BSDF) times ``closed`` (the cone integral) over pi, in a symbolic branch; 0 elsewhere."""
    def lambert_fn(closed):
        if consts is None:
            rho = mi.Color3f(bsdf.eval_diffuse_reflectance(si, lambert))
        else:
            tab = kind == KIND_DIFFUSE
            rho = dr.select(tab, consts[1](), mi.Color3f(bsdf.eval_diffuse_reflectance(si, lambert & ~tab)))
        return rho * closed * (1.0 / math.pi)

    return dr.if_stmt(args=(closed,), cond=lambert, true_fn=lambert_fn,
                      false_fn=lambda closed: mi.Color3f(0.0), label="lambert")


def _compact_quadrature(out: mi.Color3f, sampled: mi.Bool, storage, slot, si, bsdf, tf_in, n_total, key, pid,
                        entry_frames, ctx, opts: ShadeOptions) -> mi.Color3f:
    """``out`` (the closed forms) with the quadrature of the pixels ``sampled`` scattered in,
    computed in a launch of their own.

    A SIMD packet (16 lanes with AVX-512 on the LLVM backend) holding one quadrature pixel
    runs the quadrature's loops for all its lanes; on the atrium 3 % of the pixels (rough
    conductors) take it, spread over 14 % of the packets. This launch evaluates the closed
    forms and which pixels are left; the next takes the indices of those (``dr.compress``;
    the last two pixels always taken, masked off unless they are ones: no launch of width 0
    or 1; a frozen function recorded on a width-1 launch loads its inputs as scalars and
    replays that on every later call: in a frame where no pixel took the quadrature, e.g.
    the adaptive cache's warm-up with no entry in cones, every later frame's quadrature
    pixels got the first one's value), gathers
    their inputs, recomputes their cone state from them (the same operations: the same
    values), and its values are scattered back. Same images bit for bit
    (tests/test_cones_compact.py); measured in docs/cones.md (packed quadrature pixels)."""
    dr.eval(out, sampled)
    N = dr.width(slot)
    idx = dr.compress(sampled | (dr.arange(mi.UInt32, N) + 2 >= N))
    on = dr.gather(mi.Bool, sampled, idx)
    si_c, bsdf_c = dr.gather(type(si), si, idx), dr.gather(mi.BSDFPtr, bsdf, idx)
    cones_c = cone_state(storage, dr.gather(mi.UInt32, slot, idx), on, dr.gather(type(tf_in), tf_in, idx),
                          entry_frames, opts.max_cones, opts.front_only)
    acc = quadrature(bsdf_c, si_c, ctx, on, cones_c, samples_px(bsdf_c, n_total, opts.glossy_half), key,
                      dr.gather(mi.UInt32, pid, idx), opts)
    dr.scatter(out, acc, idx, on)
    # raw values: a NaN or Inf made here reaches the image, where check mode names it
    return out


def _table_consts(table, bsdf, active):
    """Each pixel's BSDF kind and constants from the table (:func:`bsdf_table`; ``KIND_OTHER``:
    virtual calls): (kind, consts or None), the constants read lazily."""
    if table is None:
        return mi.UInt32(KIND_OTHER), None
    rid = dr.reinterpret_array(mi.UInt32, bsdf)
    t_ok = active & (bsdf != None) & (rid < table.width)  # noqa: E711 (BSDFPtr comparison)
    kind = dr.gather(mi.UInt32, table.kind, rid, t_ok)
    return kind, (kind, lambda: dr.gather(mi.Color3f, table.colour, rid, t_ok),
                  lambda: dr.gather(mi.Float, table.roughness, rid, t_ok),
                  lambda: dr.gather(mi.Float, table.metallic, rid, t_ok))


def shade_key(frame: int, seed: int, tap: int = 0) -> int:
    """The random-number key of one shading call (frame, seed, bilinear tap)."""
    x = (int(frame) * 0x9E3779B1 + int(seed) * 0x85EBCA77 + int(tap) * 0xC2B2AE3D) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    return x ^ (x >> 15)


class ConeShading(FrozenFunction):
    r"""Shading of pixels from their cache entries' cones: MIS of cone sampling and
    BSDF sampling (module docstring and docs/cones.md).

    Parameters (defaults): ``max_cones`` (as stored), ``adaptive=True`` (split each
    cone's ``n_samples`` between the strategies by the lobe's width against the cones;
    False: half and half), ``rotate=True`` (rotate the patterns per pixel and key; False:
    the same pattern everywhere), ``freeze=True`` (record the kernel launches once and
    replay them), ``max_recordings=4``,
    ``horizon=True`` (Lambertian pixels whose cones cross the horizon use the exact
    clipped-cap integral; False: they are sampled by the MIS quadrature),
    ``principled="sg"`` (pixels with Mitsuba's ``principled`` BSDF: diffuse part in
    closed form, specular lobe as a spherical Gaussian, see :func:`slc.lib.cones.closedforms._principled_cones`;
    ``"sample"``: the MIS quadrature), ``conductor="sample"`` (pixels with an
    isotropic GGX ``roughconductor``: the MIS quadrature; ``"sg"``: the lobe as a spherical
    Gaussian over each cone, see :func:`slc.lib.cones.closedforms._conductor_cones`; only for scenes whose
    roughconductors all use GGX, :func:`shader_for` checks), ``glossy="full"`` (``"half"``:
    pixels whose BSDF is purely glossy, e.g. rough conductors, take half of ``n_samples``
    on the quadrature: faster, noisier, see docs/cones.md), ``compact=True`` (the pixels that
    take the MIS quadrature packed into a launch of their own, so that SIMD packets of
    closed-form pixels do not run its loops; False: in a branch of the launch of all pixels;
    the same images bit for bit), ``front_only=False`` (the update took light from above each
    entry's horizon only, ``ConeParams.front_only``: a cone across the horizon spreads its
    ``L_c`` over its part above it, :func:`slc.lib.cones.conestate.cone_state`).

    Freezing pays only while its recordings are replayed. Each instance owns its frozen
    function, so recordings are freed with the method and never shared between scenes.
    A frozen function traverses every object of Mitsuba's registry (shapes, BSDFs,
    emitters, the scene) on each call; moving meshes keep its recordings as long as their
    new buffers are made as :mod:`slc.core.freeze` says (the street: one recording, replayed
    in every later frame). A function recorded more than ``max_recordings`` times is
    dropped.
    """

    def __init__(self, max_cones: int, adaptive: bool = True, rotate: bool = True, freeze: bool = True,
                 max_recordings: int = 4, horizon: bool = True,
                 principled: str = "sg", conductor: str = "sample", table=None, glossy: str = "full",
                 compact: bool = True, front_only: bool = False, scene=None):
        self.table = table
        self.compact = bool(compact)
        if glossy not in ("half", "full"):
            raise ValueError(f"glossy must be 'half' or 'full', not {glossy!r}")
        self.glossy = glossy
        if principled not in ("sg", "sample"):
            raise ValueError(f"principled must be 'sg' or 'sample', not {principled!r}")
        if conductor not in ("sg", "sample"):
            raise ValueError(f"conductor must be 'sg' or 'sample', not {conductor!r}")
        self.conductor = conductor
        self.max_cones = int(max_cones)
        self.adaptive, self.rotate, self.horizon = bool(adaptive), bool(rotate), bool(horizon)
        self.principled = principled
        self.opts = ShadeOptions(self.max_cones, adaptive=bool(adaptive), rotate=bool(rotate), horizon=bool(horizon),
                                 principled=principled == "sg", conductor=conductor == "sg",
                                 glossy_half=glossy == "half", compact=bool(compact), front_only=bool(front_only))
        # the entries' frames (``entry_frames``) are read through each pixel's index: a table whose
        # length changes every frame (slc.core.freeze: tables)
        super().__init__(shade_kernel, freeze, max_recordings, tables=("entry_frames",), scene=scene)

    def __call__(self, storage, slot, active, si, texel_frame, n_samples: int = 16, key: int = 0,
                 pid: mi.UInt32 | None = None, entry_frames=None) -> mi.Color3f:
        """Shade the pixels ``si``; ``pid``: the random-number key per pixel (default:
        the index in the arrays); ``entry_frames``: ``texel_frame`` is an index into
        them (see :func:`shade_kernel`)."""
        # (no garbage collection inside the call: slc.core.freeze.FrozenFunction)
        return super().__call__(storage, mi.UInt32(slot), mi.Bool(active), si, si.bsdf(), texel_frame,
                                dr.opaque(mi.UInt32, max(int(n_samples), 1)), dr.opaque(mi.UInt32, int(key)), pid,
                                self.table, entry_frames, self.opts)


def shader_for(owner, max_cones: int) -> ConeShading:
    """The :class:`ConeShading` of ``owner`` (a method instance), made on first use
    (frozen unless the owner's ``freeze`` setting is off; the horizon
    treatment from the owner's ``horizon`` setting, default ``clip``; the principled
    pixels' from its ``principled`` setting, default ``sg``)."""
    sh = getattr(owner, "_cone_shading", None)
    if sh is None or sh.max_cones != int(max_cones):
        scene = getattr(owner, "scene", None)
        conductor = getattr(owner, "conductor", "sample")
        if conductor == "sg" and scene is not None and not _ggx_conductors_only(scene):
            conductor = "sample"
        sh = ConeShading(max_cones, freeze=bool(getattr(owner, "freeze", True)),
                         horizon=getattr(owner, "horizon", "clip") == "clip",
                         principled=getattr(owner, "principled", "sg"), conductor=conductor,
                         glossy=getattr(owner, "glossy", "full"), compact=getattr(owner, "compact", "on") == "on",
                         front_only=getattr(getattr(owner, "cone_params", None), "front_only", False),
                         table=bsdf_table(scene) if scene is not None else None,
                         scene=getattr(scene, "mi_scene", scene))
        owner._cone_shading = sh
    return sh


def bsdf_table(scene):
    """The scene's :class:`slc.scene.bsdf_table.BSDFTable` (the kinds and constants the shading
    kernel reads instead of virtual calls), None for scenes with instances."""
    return bsdf_tables.for_scene(scene)


def _ggx_conductors_only(scene) -> bool:
    """Whether every ``roughconductor`` of the scene (``slc`` scene or ``mi.Scene``) is
    GGX (the closed form of :func:`slc.lib.cones.closedforms._conductor_cones` assumes it)."""
    ms = getattr(scene, "mi_scene", scene)
    for sh in ms.shapes():
        text = str(sh.bsdf()) if sh.bsdf() is not None else ""
        if text.startswith("RoughConductor") and "distribution = ggx" not in text:
            return False
    return True


def shade_pixels(storage, slot, active, si, texel_frame, max_cones: int, n_samples: int = 16, key: int = 0,
                 principled: str = "sg", conductor: str = "sample"):
    """Unfrozen one-off shading (tests, notebooks)."""
    return ConeShading(max_cones, freeze=False, principled=principled, conductor=conductor)(storage, slot, active, si, texel_frame,
                                                                      n_samples, key)
