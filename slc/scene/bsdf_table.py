r"""One table of the scene's BSDFs, read once on the host, so that kernels gather a BSDF's
kind and constants instead of making a virtual call per point and attribute.

Indexed by the BSDF's registry id (``dr.reinterpret_array(mi.UInt32, bsdf)``). Per BSDF:

- ``diffuse``: Mitsuba's smooth ``diffuse`` (any reflectance, textured or not), the BSDFs whose
  value :class:`slc.scene.lights.SurfaceBSDF` evaluates without the virtual call;
- ``kind``: ``KIND_DIFFUSE`` (``diffuse`` with a constant reflectance: ``colour`` holds it),
  ``KIND_PRINCIPLED`` (``principled`` whose clearcoat, sheen, flatness, anisotropy and
  specular transmission are constant 0 and whose base colour, roughness and metallic are
  constant: ``colour``, ``roughness``, ``metallic`` hold those), ``KIND_NOT_PRINCIPLED``
  (other BSDFs without the ``clearcoat`` or ``base_color`` attribute), else ``KIND_OTHER``
  (textured parameters: the virtual calls);
- ``alpha``: the GGX roughness of a BSDF with Mitsuba's ``alpha`` attribute (rough conductors,
  plastics, dielectrics, also inside ``twosided``), else its ``roughness`` squared
  (``principled``), 0 for a BSDF with neither, ``ALPHA_TEXTURED`` where it is a texture (the
  kernels evaluate it per point then). The constants are the BSDF's own
  ``eval_attribute`` / ``eval_diffuse_reflectance`` values (a constant texture ignores the
  point), so kernels reading them give the images of the virtual calls bit for bit;
- ``two_sided``: the BSDF reflects or transmits light that arrives from behind its surface
  (Mitsuba's ``twosided``, dielectrics, ``null`` lobes; not ``principled`` without transmission,
  whose flags name a back side it never reflects from): light below a surface point's horizon
  reaches the pixels that see the surface's back (:func:`two_sided`).

The table is built once per scene, outside symbolic loops (:func:`for_scene`), and dropped
with the scene's last :class:`slc.scene.scenes.Scene` (a ``mi.Scene`` takes neither attributes nor
weak references, so the table is found by the scene's address and its first shape, held
alive by the entry: a new scene at a recycled address is never mistaken for an old one).
Scenes with instances have no table (their BSDFs are not listed by ``scene.shapes()``); XML
scenes load with theirs expanded (:mod:`slc.scene.instances`), scenes built in Python may keep them.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

KIND_OTHER, KIND_DIFFUSE, KIND_PRINCIPLED, KIND_NOT_PRINCIPLED = 0, 1, 2, 3
ALPHA_TEXTURED = -1.0
ZERO_ATTRS = ("clearcoat", "sheen", "flatness", "anisotropic", "spec_trans")
_DIFFUSE_CLASS = "SmoothDiffuse"


class BSDFTable:
    """The per-BSDF arrays (module docstring): ``width`` (the number of registry ids, an
    opaque UInt32), ``diffuse`` (Bool), ``kind`` (UInt32), ``colour`` (Color3f),
    ``roughness``, ``metallic``, ``alpha`` (Float), ``two_sided`` (Bool); on the host ``n`` (the width as an int),
    ``all_diffuse`` (every shape's BSDF is smooth diffuse), ``front_only`` (every shape's
    BSDF reflects light from its front side only, :func:`front_side_only`) and
    ``alpha_textured`` (some BSDF's GGX roughness is a texture). ``glossy_share`` (Float, not
    a kernel input of the table's users): the share of each BSDF's reflected light that its
    glossy and delta lobes carry (:func:`_glossy_share`)."""
    DRJIT_STRUCT = {"width": mi.UInt32, "diffuse": mi.Bool, "kind": mi.UInt32, "colour": mi.Color3f,
                    "roughness": mi.Float, "metallic": mi.Float, "alpha": mi.Float, "two_sided": mi.Bool}

    def __init__(self, width=None, diffuse=None, kind=None, colour=None, roughness=None, metallic=None,
                 alpha=None, two_sided=None):
        self.width, self.diffuse, self.kind = width, diffuse, kind
        self.colour, self.roughness, self.metallic, self.alpha = colour, roughness, metallic, alpha
        self.two_sided = two_sided
        self.n, self.all_diffuse, self.front_only, self.alpha_textured = 0, False, False, False
        self.glossy_share = None


_TABLES: dict[int, tuple] = {}


def for_scene(scene) -> BSDFTable | None:
    """The table of ``scene`` (a :class:`slc.scene.scenes.Scene` or a ``mi.Scene``), built on first
    use (outside symbolic loops), None for scenes with instances or without BSDFs."""
    ms = getattr(scene, "mi_scene", scene)
    shapes = ms.shapes()
    first = shapes[0] if shapes else None
    hit = _TABLES.get(id(ms))
    if hit is not None and hit[0] is first:
        return hit[1]
    if dr.flag(dr.JitFlag.SymbolicScope):
        raise RuntimeError("build the BSDF table (slc.scene.bsdf_table.for_scene) outside symbolic loops")
    table = _build(shapes)
    _TABLES[id(ms)] = (first, table)
    return table


def forget(scene_id: int) -> None:
    """Drop the table of the scene at address ``scene_id`` (its :class:`slc.scene.scenes.Scene`
    was freed): the entry holds the scene's shapes, which would otherwise stay in
    Mitsuba's registry, which every frozen function traverses."""
    _TABLES.pop(scene_id, None)


def _build(shapes) -> BSDFTable | None:
    if any(sh.class_name() in ("Instance", "ShapeGroup") for sh in shapes):
        return None
    bsdfs = {}
    for sh in shapes:
        b = sh.bsdf()
        if b is not None:
            bsdfs[int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0])] = b
    if not bsdfs:
        return None
    W = max(bsdfs) + 1
    diffuse = np.zeros(W, bool)
    kind = np.zeros(W, np.uint32)
    col = np.zeros((3, W), np.float32)
    rough = np.zeros(W, np.float32)
    metal = np.zeros(W, np.float32)
    alpha = np.zeros(W, np.float32)
    two = np.zeros(W, bool)
    gshare = np.zeros(W, np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    for rid, b in bsdfs.items():
        keys = list(mi.traverse(b).keys())

        def constant(name):
            own = [k for k in keys if k == name or k.startswith(name + ".")]
            return own == [name + ".value"]
        diffuse[rid] = b.class_name() == _DIFFUSE_CLASS
        if diffuse[rid] and constant("reflectance"):
            kind[rid] = KIND_DIFFUSE
            col[:, rid] = np.array(b.eval_diffuse_reflectance(si)).reshape(3)
        elif b.class_name() == "Principled" and all(constant(a) for a in ZERO_ATTRS + ("base_color", "roughness",
                                                                                      "metallic")) \
                and all(float(b.eval_attribute_1(a, si)[0]) == 0.0 for a in ZERO_ATTRS) \
                and _principled_flags(int(b.flags())):
            kind[rid] = KIND_PRINCIPLED
            col[:, rid] = np.array(b.eval_attribute_3("base_color", si)).reshape(3)
            rough[rid] = float(b.eval_attribute_1("roughness", si)[0])
            metal[rid] = float(b.eval_attribute_1("metallic", si)[0])
        elif not (b.has_attribute("clearcoat") and b.has_attribute("base_color")):
            kind[rid] = KIND_NOT_PRINCIPLED
        alpha[rid] = _ggx_alpha(b, keys, si)
        two[rid] = not _front_side(b)
        gshare[rid] = 0.0 if diffuse[rid] else _glossy_share(b)
    t = BSDFTable(dr.opaque(mi.UInt32, W), mi.Bool(diffuse), mi.UInt32(kind), mi.Color3f(col), mi.Float(rough),
                  mi.Float(metal), mi.Float(alpha), mi.Bool(two))
    t.n, t.all_diffuse = W, bool(all(diffuse[i] for i in bsdfs))
    t.alpha_textured = bool((alpha == ALPHA_TEXTURED).any())
    t.front_only = all(_front_side(b) for b in bsdfs.values())
    t.glossy_share = mi.Float(gshare)
    return t


GLOSSY_SAMPLES = 256


def _glossy_share(b) -> float:
    """The share of BSDF ``b``'s reflected light that its glossy and delta lobes carry: over
    ``GLOSSY_SAMPLES`` of its samples for light leaving at 45 degrees (at texture coordinates
    (0.5, 0.5)), the luminance of the weights of samples from such a lobe over the luminance of
    all weights. 0 for a Lambertian lobe, 1 for a conductor; a principled dielectric's specular
    layer or a blend's glossy component carry a share between."""
    n = GLOSSY_SAMPLES
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.n = mi.Vector3f(0.0, 0.0, 1.0)
    si.wi = mi.Vector3f(math.sqrt(0.5), 0.0, math.sqrt(0.5))
    si.uv = mi.Point2f(0.5, 0.5)
    k = mi.Float(dr.arange(mi.UInt32, n)) + 0.5
    u1 = k * (1.0 / n)                                   # stratified lobe choice
    a, c = k * 0.7548776662466927, k * 0.5698402909980532    # an R2 sequence (Roberts)
    u2 = mi.Point2f(a - dr.floor(a), c - dr.floor(c))
    bs, w = b.sample(mi.BSDFContext(), si, u1, u2)
    ok = (bs.pdf > 0.0) & (mi.Frame3f.cos_theta(bs.wo) > 0.0) & dr.all(dr.isfinite(w))
    y = dr.select(ok, mi.luminance(mi.Color3f(w)), 0.0)
    g = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy) | mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    total, glossy = float(dr.sum(y)[0]), float(dr.sum(dr.select(g, y, 0.0))[0])
    return glossy / total if total > 0.0 else 0.0


def _ggx_alpha(b, keys: list, si) -> float:
    """The ``alpha`` column of BSDF ``b`` (module docstring); ``keys``: its parameters' names
    (a nested BSDF's, as in ``twosided``, carry its prefix)."""
    for name, squared in (("alpha", False), ("roughness", True)):
        if b.has_attribute(name):
            if not any(k.endswith(name + ".value") for k in keys):
                return ALPHA_TEXTURED
            a = float(b.eval_attribute_1(name, si)[0])
            return a * a if squared else a
    return 0.0


def front_side_only(scene) -> bool:
    """Whether every BSDF of ``scene`` reflects light that arrives on its front side only (no
    transmission, no null lobe, no back side; Mitsuba's ``principled`` without transmission
    reflects nothing from behind although its flags name a back side): then light from below
    a surface point's horizon never reaches its pixels. False for scenes without a table
    (instances)."""
    t = for_scene(scene)
    return bool(t is not None and t.front_only)


def two_sided(scene, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.Bool | None:
    """The lanes whose BSDF ``bsdf`` reflects or transmits light arriving from behind its
    surface (the table's ``two_sided`` column; the BSDF's flags in scenes without a table),
    or None where no BSDF of ``scene`` does (:func:`front_side_only`: callers then trace
    nothing for the back side). A frozen function that calls it declares
    :func:`side_inputs` among its inputs."""
    t = for_scene(scene)
    if t is not None and t.front_only:
        return None
    active = mi.Bool(active)
    if t is None:
        F = mi.BSDFFlags
        back = int(F.BackSide) | int(F.Transmission) | int(F.Null)
        return active & ((mi.UInt32(bsdf.flags()) & back) != 0)
    rid = dr.reinterpret_array(mi.UInt32, bsdf)
    ok = active & (rid < t.width)
    return ok & dr.gather(mi.Bool, t.two_sided, rid, ok)


def glossy_lobes(scene, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.Float:
    """The share of the lanes' reflected light that their BSDF's glossy and delta lobes carry
    (the table's ``glossy_share``; in scenes without a table 1 for a BSDF with such a lobe)."""
    t = for_scene(scene)
    active = mi.Bool(active)
    if t is None:
        f = mi.UInt32(bsdf.flags())
        g = ((f & (int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta))) != 0) & active
        return dr.select(g, 1.0, 0.0)
    rid = dr.reinterpret_array(mi.UInt32, bsdf)
    ok = active & (rid < t.width)
    return dr.gather(mi.Float, t.glossy_share, rid, ok)


def side_inputs(scene) -> list:
    """The arrays :func:`two_sided` reads (inputs of a frozen function that calls it)."""
    t = for_scene(scene)
    return [t.width, t.two_sided] if t is not None and not t.front_only else []


def facing(n: mi.Vector3f, d: mi.Vector3f, two: mi.Bool | None) -> mi.Vector3f:
    """The normal ``n`` turned towards direction ``d`` on the ``two`` lanes (two-sided BSDFs: the
    hemisphere a light arrives from is the one its pixels see), else ``n``."""
    if two is None:
        return mi.Vector3f(n)
    return mi.Vector3f(dr.select(two, dr.mulsign(n, dr.dot(n, d)), n))


def side_normal(si: mi.SurfaceInteraction3f) -> mi.Vector3f:
    """The pixels' shading normal turned towards their viewer (``si.wi``): the hemisphere whose
    light a pixel on a two-sided surface sees (a one-sided BSDF seen from behind is 0 on
    either side)."""
    return mi.Vector3f(dr.mulsign(si.sh_frame.n, si.wi.z))


def _front_side(b) -> bool:
    F, f = mi.BSDFFlags, int(b.flags())
    if f & (int(F.Transmission) | int(F.Null)):
        return False
    return not (f & int(F.BackSide)) or b.class_name() == "Principled"


def _principled_flags(f: int) -> bool:
    """Diffuse + glossy reflection, no transmission, no Dirac lobe (the flags the cones'
    principled closed form asks for)."""
    F = mi.BSDFFlags
    return bool(f & int(F.DiffuseReflection)) and bool(f & int(F.GlossyReflection)) and \
        not (f & int(F.Transmission)) and not (f & int(F.Delta))
