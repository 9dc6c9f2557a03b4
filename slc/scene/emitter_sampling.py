"""A per-scene emitter sampler in one kernel, without a virtual call over
emitters: table lookups for the emitter and (on meshes) the triangle, then
closed-form sampling of the chosen entry.

``scene.sample_emitter_direction`` picks an emitter uniformly and calls
its ``sample_direction`` through a virtual call (on the LLVM backend, one
indirect call per emitter kind per lane, after a gather of the pointer),
and a mesh emitter then samples a triangle from its own area table. Here
both choices are O(1) table lookups (alias tables built once per
scene); a sample reads two packed records (its alias cell, then its entry's
row of 16 floats: geometry, radiance, probability, emitter), each by one
packet gather. Emitters the table does not model (spot, directional,
environment and constant lights, textured radiance, shapes other than
meshes, rectangles and spheres) are sampled by Mitsuba, in a masked call
that runs for their lanes only.

The table's layout and its set-up per emitter kind are
:mod:`slc.scene.emitter_table`; its sampling and pdf kernels here must agree
with them exactly (tested by chi-square). See ``docs/emitter-sampling.md`` for
the densities.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.scene import spherical
from slc.scene.emitter_table import (MESH, OTHER, POINT, RECT, ROW, ROW_E0, ROW_E1, ROW_EM, ROW_L, ROW_P0, ROW_PA,
                                     SPHERE, EmitterTable, outside_symbolic)

# Emitter choice of the per-scene samplers (for_scene). 'uniform' (Mitsuba's) by default: the power-
# proportional choice raised RT-16's relMSE on atrium, sponza, garden, street and (28x) village, where a
# bright distant moon takes the samples of nearby torches (docs/emitter-sampling.md).
DEFAULT_CHOICE = os.environ.get("SLC_EMITTER_CHOICE", "uniform")


@dataclass
class SampledEntry:
    """The table entry a light sample chose, per lane: its ``row`` (16 floats), the fractions
    ``u2`` of ``u`` the lookups left, its emitter ``em``, the probability factor ``pa``, its point
    ``p0`` (a triangle's corner, a sphere's centre, a point light) and its ``kind``."""
    row: mi.ArrayXf
    u2: mi.Point2f
    em: mi.UInt32
    pa: mi.Float
    p0: mi.Point3f
    kind: mi.UInt32


@dataclass
class PointSample:
    """What the branch of each kind writes to its lanes of a light sample: the point ``p``, its
    normal ``n``, the solid-angle density ``pdf`` (emitter choice in it), ``delta`` (a point light)
    and the radiance ``Le`` (a point light's intensity over d^2)."""
    p: mi.Point3f
    n: mi.Vector3f
    pdf: mi.Float
    delta: mi.Bool
    Le: mi.Color3f


class EmitterSampler(EmitterTable):
    r"""Light sampling from a combined alias table over emissive triangles and emitters.

    Estimator (one sample, as :func:`slc.scene.lights.sample_light`):

    .. math:: \langle L \rangle = \frac{L_e(y)}{p(\omega)}, \qquad
              p(\omega) = P(e)\, p_e(\omega),

    where :math:`P(e)` is the probability of choosing emitter ``e`` and
    :math:`p_e` the solid-angle density of its own sampling:

    * area light on a mesh or rectangle: a point uniform in area,
      :math:`p_e = \frac{1}{A_e}\frac{d^2}{|\cos\theta_y|}` with the
      *geometric* normal of the triangle (the true Jacobian; Mitsuba uses
      the interpolated shading normal of smooth meshes), one-sided;
    * sphere: uniform in the cone it subtends seen from outside,
      :math:`p_e = 1/(2\pi(1-\cos\theta_{max}))`; from inside by area;
    * point light: :math:`P(e)` alone (``ds.delta``), weight
      :math:`I/(d^2 P(e))`;
    * others: Mitsuba's ``sample_direction`` / ``pdf_direction``, times
      :math:`P(e)`.

    Two lookups, no search: the emitter by ``u.x`` (uniform: Mitsuba's own
    mapping, index ``floor(N u.x)``; power: an alias table over
    :math:`P(e)`), then the triangle of a mesh emitter by ``u.y`` from an
    alias table over its triangles' areas (:math:`P(t|e) = A_t/A_e`; other
    emitters have one entry). The fractions of ``u.x`` and ``u.y`` left by
    the lookups are reused inside the entry, so that a single quad light or
    a sphere gets exactly Mitsuba's mapping of ``u``.

    Emitter choice ``choice``: ``'uniform'`` (default): :math:`P(e) = 1/N`
    as Mitsuba; ``'power'`` gives infinite lights and those sampled by
    Mitsuba their uniform share :math:`1/N`, and splits the rest of the
    probability among the tabled emitters in proportion to their power
    (:math:`\pi L A` for area lights, :math:`4\pi I` for point lights, by
    luminance). Power ignores distance: it measured worse than uniform on
    most built-in scenes (see ``docs/emitter-sampling.md``).
    An emitter of zero power is never chosen and contributes nothing.
    Every density above is the one the sampling follows, so the estimator
    is unbiased either way.

    Parameters: ``scene`` (``mi.Scene``), ``choice`` (``'uniform'``),
    ``subset`` (indices into ``scene.emitters()`` to sample from, default
    all; ReSTIR uses the local lights). Emitter indices returned are
    indices into ``scene.emitters()``.

    Moving emitters: area lights on meshes are re-read when their vertex
    buffer changes (:meth:`refresh`, called by :func:`for_scene` on every
    use); rectangles, spheres and point lights are assumed static (slc's
    scenes move meshes only).
    """

    # ------------------------------------------------------------------ sampling

    def sample(self, si: mi.SurfaceInteraction3f, u: mi.Point2f, active: mi.Bool, solid_angle: bool = False):
        r"""One light sample from ``si``: (DirectionSample3f, L_e/pdf as
        Color3f, mask, emitter index). ``ds.pdf`` is the solid-angle density
        with the emitter choice in it (the choice probability alone for
        point lights, ``ds.delta``); the mask is false where no sample exists
        (pdf 0, back side of a one-sided emitter, zero radiance).

        ``solid_angle``: a mesh triangle is sampled uniformly in the solid angle
        it subtends (:func:`slc.scene.spherical.sample_triangle`; by area where
        that is small or nearly a hemisphere), density
        :math:`P(e) P(t|e) / \Omega_t`. :meth:`pdf` knows only area sampling:
        use it for estimators without MIS (the cache updates).

        Stages: the emitter and the entry within it (:meth:`_entry`), one branch per kind
        present that writes its lanes of the sample (:class:`PointSample`), the weight."""
        active = mi.Bool(active)
        row, u2 = self._entry(u, active)
        em = mi.UInt32(row[ROW_EM])
        pa = row[ROW_PA]
        p0 = mi.Point3f(row[ROW_P0], row[ROW_P0 + 1], row[ROW_P0 + 2])
        Le = mi.Color3f(row[ROW_L], row[ROW_L + 1], row[ROW_L + 2])
        present = set(self.kinds_present)
        if len(present) == 1:   # one kind (e.g. emissive meshes only): no per-lane kind
            kind = mi.UInt32(self.kinds_present[0])
        else:
            kind = dr.gather(mi.UInt32, self._e_kind, em, active)

        e = SampledEntry(row=row, u2=u2, em=em, pa=pa, p0=p0, kind=kind)
        out = PointSample(p=mi.Point3f(p0), n=dr.zeros(mi.Vector3f, dr.width(active)),
                          pdf=dr.zeros(mi.Float, dr.width(active)), delta=dr.zeros(mi.Bool, dr.width(active)), Le=Le)
        if present & {MESH, RECT}:
            self._sample_flat(si, e, active, solid_angle and MESH in present, out)
        if SPHERE in present:
            self._sample_sphere(si, e, active, out)

        # ------------------ point lights: a delta in position ------------------
        if POINT in present:
            pt = active & (kind == POINT)
            d2 = dr.squared_norm(p0 - si.p)
            out.pdf = dr.select(pt, pa, out.pdf)
            out.delta |= pt
            out.Le = dr.select(pt, out.Le / dr.select(d2 > 0.0, d2, 1.0), out.Le)

        ds_o = self._sample_other(si, e, active, out) if OTHER in present else None

        # ------------------ direction sample and weight ------------------
        p, pdf = out.p, out.pdf
        ds = dr.zeros(mi.DirectionSample3f, dr.width(active))
        to = p - si.p
        dist = dr.norm(to)
        d = to / dr.select(dist > 0.0, dist, 1.0)
        if ds_o is not None:
            far = active & (kind == OTHER)
            d = dr.select(far, ds_o.d, d)
            dist = dr.select(far, ds_o.dist, dist)
        ds.p, ds.n, ds.d, ds.dist = p, mi.Normal3f(out.n), d, dist
        ds.pdf, ds.delta, ds.time = pdf, out.delta, si.time
        ds.emitter = dr.gather(mi.EmitterPtr, self._emitters_dr, em, active)
        ok = active & (pdf > 0.0)
        w = dr.select(ok, out.Le / dr.select(ok, pdf, 1.0), 0.0)
        ok &= dr.max(w) > 0.0
        return ds, w, ok, em

    def _entry(self, u: mi.Point2f, active: mi.Bool):
        """The chosen entry's row (two lookups) and the fractions ``u2`` of ``u`` the lookups left."""
        # ------------------------ emitter: by u.x ------------------------
        if self.n_emitters == 1:
            k, ux = mi.UInt32(0), mi.Float(u.x)
        elif self._uniform:   # Mitsuba's own mapping (index and reused fraction)
            x = u.x * self._N
            k = dr.minimum(mi.UInt32(x), self._N1)
            ux = x - mi.Float(k)
        else:
            k, ux = _alias_lookup(u.x, self._N, self._N1, self._eq, self._ealias, active)

        # ------------------------ entry within it: by u.y ------------------------
        # the emitter's segment of the table, its alias cell j (q, alias), then the chosen entry's row
        if self._seg_params is not None:
            off, cnt_f = self._seg_params[0]
            for e, (o, c) in enumerate(self._seg_params[1:], start=1):
                pick = k == e
                off, cnt_f = dr.select(pick, o, off), dr.select(pick, c, cnt_f)
        else:
            seg = dr.gather(mi.Point2f, self._seg, k, active)
            off, cnt_f = mi.UInt32(seg.x), seg.y
        x = u.y * cnt_f
        j = dr.minimum(mi.UInt32(x), mi.UInt32(cnt_f) - 1)
        frac = x - mi.Float(j)
        cell = dr.gather(mi.Point2f, self._cells, off + j, active)
        q = cell.x
        keep = frac < q
        row = _row(self._rows, off + dr.select(keep, j, mi.UInt32(cell.y)), active)
        uy = dr.select(keep, frac / dr.select(q > 0.0, q, 1.0), (frac - q) / dr.select(q < 1.0, 1.0 - q, 1.0))
        return row, mi.Point2f(ux, dr.clip(uy, 0.0, 0.99999994))

    def _sample_flat(self, si, e: "SampledEntry", active: mi.Bool, solid_angle: bool, out: "PointSample"):
        """Triangles and rectangles: uniform in area (mesh triangles with ``solid_angle``: in the
        solid angle they subtend where :func:`slc.scene.spherical.sample_triangle` does)."""
        row, kind, p0, pa, u2 = e.row, e.kind, e.p0, e.pa, e.u2
        flat = active & ((kind == MESH) | (kind == RECT))
        e0 = mi.Vector3f(row[ROW_E0], row[ROW_E0 + 1], row[ROW_E0 + 2])
        e1 = mi.Vector3f(row[ROW_E1], row[ROW_E1 + 1], row[ROW_E1 + 2])
        nf = dr.normalize(dr.cross(e0, e1))   # the geometric normal (rectangles: oriented at set-up)
        b = mi.warp.square_to_uniform_triangle(u2)
        b = dr.select(kind == MESH, mi.Vector2f(b), mi.Vector2f(u2))
        pf = p0 + e0 * b.x + e1 * b.y
        sa = None
        if solid_angle:
            ps, omega, sa, ok_sa = spherical.sample_triangle(si.p, p0, e0, e1, u2, flat & (kind == MESH))
            pf = dr.select(sa, ps, pf)
        to = pf - si.p
        d2 = dr.squared_norm(to)
        cos_y = -dr.dot(to, nf) * dr.rsqrt(dr.select(d2 > 0.0, d2, 1.0))
        ok_f = flat & (cos_y > 0.0) & (d2 > 0.0)
        out.p = dr.select(flat, pf, out.p)
        out.n = dr.select(flat, nf, out.n)
        pdf_f = pa * d2 / dr.select(ok_f, cos_y, 1.0)
        if sa is not None:
            # P(e) P(t|e) / Omega_t, with P(e) P(t|e) = pa A_t
            ok_f &= ~sa | ok_sa
            a_t = 0.5 * dr.norm(dr.cross(e0, e1))
            pdf_f = dr.select(sa, pa * a_t / dr.select(sa & (omega > 0.0), omega, 1.0), pdf_f)
        out.pdf = dr.select(ok_f, pdf_f, out.pdf)

    def _sample_sphere(self, si, e: "SampledEntry", active: mi.Bool, out: "PointSample"):
        """Spheres: uniform in the cone they subtend from outside, by area from inside."""
        em, kind, p0, pa, u2 = e.em, e.kind, e.p0, e.pa, e.u2
        sph = active & (kind == SPHERE)
        r = dr.gather(mi.Float, self._e_r, em, sph)
        dc = p0 - si.p
        dc2 = dr.squared_norm(dc)
        outside = dc2 > dr.square(r * (1.0 - 1e-4))
        inv_dc = dr.rsqrt(dr.select(dc2 > 0.0, dc2, 1.0))
        sin_max = r * inv_dc
        sin2_max = dr.square(sin_max)
        cos_max = dr.safe_sqrt(1.0 - sin2_max)
        sin2 = dr.select(sin2_max > 0.00068523,
                         1.0 - dr.square(dr.fma(cos_max - 1.0, u2.x, 1.0)), sin2_max * u2.x)
        cos_t = dr.safe_sqrt(1.0 - sin2)
        inv_sin_max = dr.rcp(dr.select(sin_max > 0.0, sin_max, 1.0))
        cos_a = sin2 * inv_sin_max + cos_t * dr.safe_sqrt(dr.fma(-sin2, dr.square(inv_sin_max), 1.0))
        sin_a = dr.safe_sqrt(dr.fma(-cos_a, cos_a, 1.0))
        sp, cp = dr.sincos(u2.y * (2.0 * math.pi))
        v_cone = mi.Frame3f(-dc * inv_dc).to_world(mi.Vector3f(cp * sin_a, sp * sin_a, cos_a))
        v_in = mi.warp.square_to_uniform_sphere(u2)
        v = dr.select(outside, v_cone, v_in)
        ps = dr.fma(v, r, p0)
        to = ps - si.p
        d2 = dr.squared_norm(to)
        cos_y = dr.abs(dr.dot(to, v)) * dr.rsqrt(dr.select(d2 > 0.0, d2, 1.0))
        cone_pdf = dr.rcp(dr.select(cos_max < 1.0, 2.0 * math.pi * (1.0 - cos_max), 0.0))
        area_pdf = dr.gather(mi.Float, self._e_inv_area, em, sph) * d2 / dr.select(cos_y > 0.0, cos_y, 1.0)
        pdf_s = pa * dr.select(outside, cone_pdf, dr.select(cos_y > 0.0, area_pdf, 0.0))
        ok_s = sph & (d2 > 0.0) & dr.isfinite(pdf_s)
        out.p = dr.select(sph, ps, out.p)
        out.n = dr.select(sph, v, out.n)
        out.pdf = dr.select(ok_s, pdf_s, out.pdf)

    def _sample_other(self, si, e: "SampledEntry", active: mi.Bool, out: "PointSample") -> mi.DirectionSample3f:
        """Everything else: Mitsuba's ``sample_direction``, for those lanes only; its sample."""
        oth = active & (e.kind == OTHER)
        ptr = dr.gather(mi.EmitterPtr, self._emitters_dr, e.em, oth)
        ds_o, w_o = ptr.sample_direction(si, e.u2, oth)
        pdf_o = ds_o.pdf * e.pa
        oth &= ds_o.pdf > 0.0
        out.p = dr.select(oth, ds_o.p, out.p)
        out.n = dr.select(oth, mi.Vector3f(ds_o.n), out.n)
        out.pdf = dr.select(oth, pdf_o, out.pdf)
        out.delta = dr.select(oth, ds_o.delta, out.delta)
        # w_o = L_e / p_e: turn it into L_e so that the common division applies
        out.Le = dr.select(oth, mi.Color3f(w_o) * ds_o.pdf, out.Le)
        return ds_o

    # ------------------------------------------------------------------ densities

    def kind(self, index: mi.UInt32, active: mi.Bool) -> mi.UInt32:
        """Entry kind (MESH, RECT, SPHERE, POINT or OTHER) of emitters (indices into ``scene.emitters()``)."""
        return dr.gather(mi.UInt32, self._e_kind, index, active)

    def choice_pmf(self, index: mi.UInt32, active: mi.Bool) -> mi.Float:
        """P(e) of emitters (indices into ``scene.emitters()``; 0 outside the subset)."""
        return dr.gather(mi.Float, self._e_pmf, index, active)

    def index_of(self, emitter: mi.EmitterPtr, active: mi.Bool) -> tuple[mi.UInt32, mi.Bool]:
        """Index into ``scene.emitters()`` of emitter pointers; mask of valid ones."""
        rid = dr.reinterpret_array(mi.UInt32, emitter)
        ok = mi.Bool(active) & (emitter != None)  # noqa: E711 (EmitterPtr comparison)
        idx = dr.gather(mi.UInt32, self._id_to_index, rid, ok)
        ok &= idx != 0xFFFFFFFF
        return dr.select(ok, idx, 0), ok

    def pdf(self, si: mi.Interaction3f, ds: mi.DirectionSample3f, active: mi.Bool,
            index: mi.UInt32 | None = None) -> mi.Float:
        """Solid-angle density, emitter choice included, with which
        :meth:`sample` produces the direction ``ds.d`` towards the point
        ``ds.p`` of ``ds.emitter`` (or of ``index``). ``ds.n`` must be the
        *geometric* normal at ``ds.p`` (as :meth:`sample` returns it, or
        :meth:`pdf_hit`); 0 for delta lights and emitters outside the subset."""
        active = mi.Bool(active)
        if index is None:
            index, ok_i = self.index_of(ds.emitter, active)
            active &= ok_i
        kind = dr.gather(mi.UInt32, self._e_kind, index, active)
        pmf = dr.gather(mi.Float, self._e_pmf, index, active)
        active &= pmf > 0.0
        present = set(self.kinds_present)
        out = dr.zeros(mi.Float, dr.width(active))
        d, dist = mi.Vector3f(ds.d), mi.Float(ds.dist)
        d2 = dr.square(dist)
        if present & {MESH, RECT}:
            flat = active & ((kind == MESH) | (kind == RECT))
            cos_y = -dr.dot(d, mi.Vector3f(ds.n))
            ok = flat & (cos_y > 0.0)
            ia = dr.gather(mi.Float, self._e_inv_area, index, ok)
            out = dr.select(ok, pmf * ia * d2 / dr.select(ok, cos_y, 1.0), out)
        if SPHERE in present:
            sph = active & (kind == SPHERE)
            c = dr.gather(mi.Point3f, self._e_c, index, sph)
            r = dr.gather(mi.Float, self._e_r, index, sph)
            dc2 = dr.squared_norm(c - si.p)
            outside = dc2 > dr.square(r * (1.0 - 1e-4))
            cos_max = dr.safe_sqrt(1.0 - dr.square(r) / dr.select(dc2 > 0.0, dc2, 1.0))
            cone_pdf = dr.rcp(dr.select(cos_max < 1.0, 2.0 * math.pi * (1.0 - cos_max), 0.0))
            cos_y = dr.abs(dr.dot(d, mi.Vector3f(ds.n)))
            ia = dr.gather(mi.Float, self._e_inv_area, index, sph)
            area_pdf = dr.select(cos_y > 0.0, ia * d2 / dr.select(cos_y > 0.0, cos_y, 1.0), 0.0)
            val = pmf * dr.select(outside, cone_pdf, area_pdf)
            out = dr.select(sph & dr.isfinite(val), val, out)
        if OTHER in present:
            oth = active & (kind == OTHER)
            ptr = dr.gather(mi.EmitterPtr, self._emitters_dr, index, oth)
            out = dr.select(oth & ~ds.delta, pmf * ptr.pdf_direction(si, ds, oth), out)
        return dr.select(active, out, 0.0)

    def pdf_hit(self, scene: mi.Scene, si: mi.Interaction3f, si2: mi.SurfaceInteraction3f,
                active: mi.Bool) -> mi.Float:
        """:meth:`pdf` of the emitter point hit by a ray from ``si`` (e.g. a
        BSDF sample); an escaped ray gives the environment's density."""
        ds = mi.DirectionSample3f(scene, si2, si)
        ds.n = dr.select(si2.is_valid(), mi.Normal3f(si2.n), ds.n)
        return self.pdf(si, ds, active)


def _scattered(arr, value, index):
    """Components of a 3D array with ``value`` written at ``index``."""
    out = []
    for c in range(3):
        a = mi.Float(arr[c])
        dr.scatter(a, value[c], index)
        out.append(a)
    return out


def _row(rows: mi.Float, index: mi.UInt32, active: mi.Bool) -> mi.ArrayXf:
    """The packed table row ``index`` (ROW floats), one packet gather."""
    return dr.gather(mi.ArrayXf, rows, index, active, shape=(ROW, dr.width(index)))


def _alias_lookup(u, n_f, n_1, q_arr, alias_arr, active, offset=None):
    """Index in [0, n) drawn by ``u`` from an alias table (at ``offset`` in
    the arrays), and the fraction of ``u`` left by the lookup, reused."""
    x = u * n_f
    j = dr.minimum(mi.UInt32(x), n_1)
    frac = x - mi.Float(j)
    at = j if offset is None else offset + j
    q = dr.gather(mi.Float, q_arr, at, active)
    keep = frac < q
    idx = dr.select(keep, j, dr.gather(mi.UInt32, alias_arr, at, active & ~keep))
    r = dr.select(keep, frac / dr.select(q > 0.0, q, 1.0), (frac - q) / dr.select(q < 1.0, 1.0 - q, 1.0))
    return idx, dr.clip(r, 0.0, 0.99999994)


# ---------------------------------------------------------------------- per-scene cache

_CACHE: dict[tuple, tuple] = {}


def for_scene(scene: mi.Scene, choice: str | None = None, subset=None) -> EmitterSampler:
    """The sampler of ``scene`` (built on first use, then cached and
    refreshed when an emissive mesh moved; both must happen outside
    symbolic loops: :class:`slc.scene.scenes.Scene` calls this at load and after
    every pose change). The cache key is the scene's
    address plus its first emitter, held alive by the entry, so a new scene
    at a recycled address is never mistaken for an old one."""
    choice = DEFAULT_CHOICE if choice is None else choice
    ems = scene.emitters()
    key = (id(scene), choice, None if subset is None else tuple(sorted(int(i) for i in subset)))
    hit = _CACHE.get(key)
    if hit is not None and len(ems) == len(hit[0].emitters) and (not ems or ems[0] is hit[0].emitters[0]):
        hit[0].refresh()
        return hit[0]
    outside_symbolic("build the emitter table")
    s = EmitterSampler(scene, choice=choice, subset=subset)
    _CACHE[key] = (s,)
    return s


def clear_cache() -> None:
    _CACHE.clear()


def forget(scene_id: int) -> None:
    """Drop the tables of the scene at address ``scene_id`` (called when its
    :class:`slc.scene.scenes.Scene` is freed): an entry holds the scene's emitters and
    emissive shapes, which would otherwise stay alive, and stay in Mitsuba's
    object registry, which every frozen function traverses."""
    for k in [k for k in _CACHE if k[0] == scene_id]:
        del _CACHE[k]
