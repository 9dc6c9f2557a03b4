"""A per-scene emitter sampler in one kernel, without a virtual call over
emitters: table lookups for the emitter and (on meshes) the triangle, then
closed-form sampling of the chosen entry.

Why one long module: the table's set-up (per emitter kind) and its sampling and pdf kernels
must agree exactly (tested by chi-square); they are kept side by side.

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

See ``docs/emitter-sampling.md`` for the densities.
"""
from __future__ import annotations

import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np

# Entry kinds. MESH: one triangle of an area light on a mesh (area sampling);
# RECT: a rectangle (area sampling); SPHERE: a sphere (solid angle, as Mitsuba);
# POINT: a point light; OTHER: sampled by Mitsuba's own ``sample_direction``.
MESH, RECT, SPHERE, POINT, OTHER = 0, 1, 2, 3, 4
KIND_NAMES = {MESH: "mesh", RECT: "rectangle", SPHERE: "sphere", POINT: "point", OTHER: "mitsuba"}

# One packed row of ROW = 16 float32 per alias entry, read by one packet gather (Dr.Jit bundles a
# power-of-two run of contiguous elements into vector loads): the entry's alias cell (keep
# probability q, alias as a local index stored as a float), its geometry (p0 and two edges e0, e1;
# sphere: centre and (r, 0, 0); point light: position), radiance or intensity L, the area density
# with the emitter choice folded in (pa = P(e)/A_e; P(e) for spheres, points and others) and the
# emitter's index into scene.emitters() (stored as a float: exact below 2^24).
ROW = 16
SEG_SELECT_MAX = 8   # up to this many emitters, their table segments are selected, not gathered
ROW_Q, ROW_ALIAS, ROW_P0, ROW_E0, ROW_E1, ROW_L, ROW_PA, ROW_EM = 0, 1, 2, 5, 8, 11, 14, 15

CHOICES = ("power", "uniform")
# Emitter choice of the per-scene samplers (for_scene). 'uniform' (Mitsuba's) by default: the power-
# proportional choice raised RT-16's relMSE on atrium, sponza, garden, street and (28x) village, where a
# bright distant moon takes the samples of nearby torches (docs/emitter-sampling.md).
DEFAULT_CHOICE = os.environ.get("SLC_EMITTER_CHOICE", "uniform")


def alias_table(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Walker/Vose alias table of a probability vector ``p`` (sums to 1):
    entry j is kept with probability ``q[j]``, else replaced by ``alias[j]``."""
    n = len(p)
    q = np.asarray(p, np.float64) * n
    alias = np.arange(n, dtype=np.int64)
    small = [int(i) for i in np.nonzero(q < 1.0)[0]]
    large = [int(i) for i in np.nonzero(q >= 1.0)[0]]
    while small and large:
        s, l = small.pop(), large.pop()
        alias[s] = l
        q[l] -= 1.0 - q[s]
        (small if q[l] < 1.0 else large).append(l)
    for i in small + large:   # leftovers are 1 up to rounding
        q[i] = 1.0
    return np.clip(q, 0.0, 1.0), alias


def constant_rgb(value) -> np.ndarray | None:
    """A constant texture value (Float or Color3f parameter) as RGB, or None."""
    try:
        a = np.array(value, np.float64).ravel()
    except Exception:
        return None
    if a.size == 1:
        return np.repeat(a, 3)
    if a.size == 3:
        return a
    return None


def _luminance(c: np.ndarray) -> float:
    return float(0.212671 * c[0] + 0.715160 * c[1] + 0.072169 * c[2])


class EmitterSampler:
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

    def __init__(self, scene: mi.Scene, choice: str = "uniform", subset=None):
        if choice not in CHOICES:
            raise ValueError(f"emitter choice must be one of {', '.join(CHOICES)}, not '{choice}'")
        self.choice = choice
        self.emitters = list(scene.emitters())
        n_all = len(self.emitters)
        self.subset = list(range(n_all)) if subset is None else sorted(int(i) for i in subset)
        self._emitters_dr = scene.emitters_dr()
        ids = np.array(dr.reinterpret_array(mi.UInt32, self._emitters_dr), dtype=np.int64)
        table = np.full(int(ids.max()) + 1 if len(ids) else 1, 0xFFFFFFFF, dtype=np.uint32)
        table[ids] = np.arange(len(ids), dtype=np.uint32)
        self._id_to_index = mi.UInt32(table)
        # get_shape() may return the base class: take the scene's own (typed) object, found by
        # its emitter (shape ids are not unique: unnamed XML shapes can share one)
        by_emitter = {_ptr(sh.emitter()): sh for sh in scene.shapes() if sh.is_emitter()}
        self._shapes = {i: by_emitter.get(_ptr(e), e.get_shape()) for i, e in enumerate(self.emitters)
                        if e.get_shape() is not None}
        self._build()

    # ------------------------------------------------------------------ set-up

    def _classify(self, i: int):
        """(kind, radiance or intensity RGB, geometry dict, power or None) of emitter i."""
        e = self.emitters[i]
        cls = e.class_name()
        params = mi.traverse(e)
        if cls == "AreaLight" and "radiance.value" in params.keys():
            L = constant_rgb(params["radiance.value"])
            sh = e.get_shape()
            sh = self._shapes.get(i, sh) if sh is not None else None
            if L is not None and sh is not None:
                name = sh.class_name()
                if name == "Rectangle":
                    def at(u, v):
                        ps = sh.sample_position(0.0, mi.Point2f(u, v))
                        return (np.array(ps.p, np.float64).ravel(), np.array(ps.n, np.float64).ravel())
                    p0, n = at(0.0, 0.0)
                    e0 = at(1.0, 0.0)[0] - p0
                    e1 = at(0.0, 1.0)[0] - p0
                    if np.dot(np.cross(e0, e1), n) < 0.0:   # the kernel takes n = cross(e0, e1)
                        e0, e1 = e1, e0
                    A = float(np.linalg.norm(np.cross(e0, e1)))
                    return RECT, L, dict(p0=p0[None], e0=e0[None], e1=e1[None], n=n[None], A=A), \
                        math.pi * _luminance(L) * A
                if name == "Sphere":
                    b = sh.bbox()
                    lo, hi = np.array(b.min, np.float64).ravel(), np.array(b.max, np.float64).ravel()
                    c, r = 0.5 * (lo + hi), 0.5 * float(np.min(hi - lo))
                    ps = sh.sample_position(0.0, mi.Point2f(0.3, 0.6))
                    outward = float(np.dot(np.array(ps.n, np.float64).ravel(),
                                           np.array(ps.p, np.float64).ravel() - c)) > 0.0
                    if outward and r > 0.0:
                        A = 4.0 * math.pi * r * r
                        return SPHERE, L, dict(p0=c[None], e0=np.array([[r, 0.0, 0.0]]), A=A), \
                            math.pi * _luminance(L) * A
                if sh.is_mesh():
                    V = np.array(sh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
                    F = np.array(sh.faces_buffer(), np.int64).reshape(-1, 3)
                    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
                    e0, e1 = p1 - p0, p2 - p0
                    c = np.cross(e0, e1)
                    a2 = np.linalg.norm(c, axis=1)
                    n = c / np.maximum(a2, 1e-30)[:, None]
                    area = 0.5 * a2
                    A = float(area.sum())
                    return MESH, L, dict(p0=p0, e0=e0, e1=e1, n=n, area=area, A=A), math.pi * _luminance(L) * A
        if cls == "PointLight" and "intensity.value" in params.keys():
            I = constant_rgb(params["intensity.value"])
            if I is not None:
                pos = np.array(params["position"], np.float64).ravel()
                return POINT, I, dict(p0=pos[None]), 4.0 * math.pi * _luminance(I)
        return OTHER, np.zeros(3), {}, None

    def _build(self):
        rows = [(i, *self._classify(i)) for i in self.subset]
        N = len(rows)
        self.kinds_present = sorted({r[1] for r in rows})
        # ---------------- emitter choice P(e) ----------------
        pmf = np.full(N, 1.0 / max(N, 1))
        if self.choice == "power" and N:
            inf = int(mi.EmitterFlags.Infinite)
            known = [k for k, r in enumerate(rows)
                     if r[4] is not None and not (int(self.emitters[r[0]].flags()) & inf)]
            power = np.array([max(rows[k][4], 0.0) for k in known], np.float64)
            if known and power.sum() > 0.0:
                share = len(known) / N
                pmf[known] = share * power / power.sum()
        # ---------------- alias entries ----------------
        ent_p, ent_em, ent_kind, ent_pa, ent_L = [], [], [], [], []
        P0, E0, E1 = [], [], []
        n_all = len(self.emitters)
        e_kind = np.full(n_all, OTHER, np.uint32)
        e_pmf = np.zeros(n_all, np.float64)
        e_inv_area = np.zeros(n_all, np.float64)
        e_c = np.zeros((n_all, 3), np.float64)
        e_r = np.zeros(n_all, np.float64)
        self._mesh_buffers = []
        for k, (i, kind, L, g, _) in enumerate(rows):
            e_kind[i], e_pmf[i] = kind, pmf[k]
            if kind in (MESH, RECT, SPHERE):
                e_inv_area[i] = 1.0 / g["A"] if g["A"] > 0.0 else 0.0
            if kind == MESH:
                m = len(g["area"])
                ent_p.append(pmf[k] * g["area"] / g["A"] if g["A"] > 0.0 else np.zeros(m))
                sh = self._shapes[i]
                self._mesh_buffers.append([sh, sh.vertex_positions_buffer(), sum(len(x) for x in ent_p) - m, m])
            else:
                m = 1
                ent_p.append(np.array([pmf[k]]))
            z = np.zeros((m, 3))
            P0.append(g.get("p0", z)); E0.append(g.get("e0", z)); E1.append(g.get("e1", z))
            ent_em.append(np.full(m, i)); ent_kind.append(np.full(m, kind)); ent_L.append(np.tile(L, (m, 1)))
            ent_pa.append(np.full(m, pmf[k] * e_inv_area[i] if kind in (MESH, RECT) else pmf[k]))
            if kind in (SPHERE, POINT):
                e_c[i] = g["p0"][0]
                e_r[i] = g["e0"][0, 0] if kind == SPHERE else 0.0
        # two levels: the emitter (by u.x: uniform as Mitsuba, or an alias table over P(e)),
        # then the entry within it (by u.y: an alias table over its triangles' areas)
        self.size = sum(len(x) for x in ent_p)
        counts = np.array([len(x) for x in ent_p], np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        q = np.ones(self.size)
        alias = np.zeros(self.size, np.int64)
        for o, c, x in zip(offsets, counts, ent_p):
            tot = x.sum()
            q[o:o + c], alias[o:o + c] = alias_table(x / tot if tot > 0 else np.full(c, 1.0 / c))
        eq, ealias = alias_table(pmf / pmf.sum() if pmf.sum() > 0 else np.full(N, 1.0 / N))
        self._uniform = self.choice == "uniform" or bool(np.allclose(pmf, 1.0 / N, rtol=0, atol=0))
        self._seg = mi.Float(np.stack([offsets, counts], axis=1).astype(np.float32).ravel())
        # few emitters: their segments as kernel parameters (opaque: no recompilation when they
        # change), picked by a chain of selects instead of a gather
        self._seg_params = [(dr.opaque(mi.UInt32, int(o)), dr.opaque(mi.Float, float(c)))
                            for o, c in zip(offsets, counts)] if N <= SEG_SELECT_MAX else None
        self._eq = mi.Float(eq.astype(np.float32))
        self._ealias = mi.UInt32(ealias.astype(np.uint32))
        self._N = dr.opaque(mi.Float, float(N))
        self._N1 = dr.opaque(mi.UInt32, N - 1)
        self.n_emitters = N

        # per alias entry: one packed row of ROW floats (see ROW_* and docs/emitter-sampling.md)
        if self.size >= 1 << 24:
            raise ValueError(f"emitter table too large ({self.size} entries; indices are stored as float32)")
        self._cells = mi.Float(np.stack([q, alias], axis=1).astype(np.float32).ravel())
        rows_np = np.zeros((self.size, ROW), np.float32)
        rows_np[:, ROW_P0:ROW_P0 + 3] = np.concatenate(P0)
        rows_np[:, ROW_E0:ROW_E0 + 3] = np.concatenate(E0)
        rows_np[:, ROW_E1:ROW_E1 + 3] = np.concatenate(E1)
        rows_np[:, ROW_L:ROW_L + 3] = np.concatenate(ent_L)
        rows_np[:, ROW_PA] = np.concatenate(ent_pa)
        rows_np[:, ROW_EM] = np.concatenate(ent_em)
        self._rows = mi.Float(rows_np.ravel())
        # per emitter (index into scene.emitters())
        self._e_kind = mi.UInt32(e_kind)
        self._e_pmf = mi.Float(e_pmf.astype(np.float32))
        self._e_inv_area = mi.Float(e_inv_area.astype(np.float32))
        self._e_c = mi.Point3f(*[e_c[:, c].astype(np.float32) for c in range(3)])
        self._e_r = mi.Float(e_r.astype(np.float32))
        self.pmf = {i: float(e_pmf[i]) for i in self.subset}

    def refresh(self) -> bool:
        """Follow emissive meshes whose vertex buffer was replaced (animated
        lights): their triangles' corners and edges are gathered from the new
        buffer on the device and scattered into the table (no host copy).
        Holding the old buffers keeps their JIT indices from being reused, so
        an index change is a reliable signal. The motion must preserve
        triangle areas (rigid, as :class:`slc.scene.scenes.Animated`); otherwise
        call :meth:`rebuild`."""
        moved = False
        for rec in self._mesh_buffers:
            sh, buf, off, m = rec
            V = sh.vertex_positions_buffer()
            if V.index == buf.index:
                continue
            _outside_symbolic("re-read a moved emissive mesh")
            F = sh.faces_buffer()
            t = dr.arange(mi.UInt32, m)
            corner = [dr.gather(mi.UInt32, F, 3 * t + c) for c in range(3)]
            P = [mi.Point3f(*[dr.gather(mi.Float, V, 3 * f + a) for a in range(3)]) for f in corner]
            at = (off + t) * ROW
            for col, val in ((ROW_P0, P[0]), (ROW_E0, P[1] - P[0]), (ROW_E1, P[2] - P[0])):
                for a in range(3):
                    dr.scatter(self._rows, val[a], at + (col + a))
            rec[1] = V
            moved = True
        if moved:
            dr.eval(self._rows)
        return moved

    def rebuild(self) -> None:
        """Re-read every emitter (e.g. after a non-rigid change)."""
        _outside_symbolic("rebuild the emitter table")
        self._build()

    @property
    def tabled(self) -> bool:
        """True when at least one emitter is sampled by the table itself."""
        return any(k != OTHER for k in self.kinds_present)

    def describe(self) -> dict:
        counts = {}
        for i in self.subset:
            k = KIND_NAMES[self._kind_of(i)]
            counts[k] = counts.get(k, 0) + 1
        return {"entries": self.size, "emitters": counts, "choice": self.choice}

    def _kind_of(self, i: int) -> int:
        return int(np.array(dr.gather(mi.UInt32, self._e_kind, mi.UInt32(i)))[0])

    # ------------------------------------------------------------------ sampling

    def sample(self, si: mi.SurfaceInteraction3f, u: mi.Point2f, active: mi.Bool):
        """One light sample from ``si``: (DirectionSample3f, L_e/pdf as
        Color3f, mask, emitter index). ``ds.pdf`` is the solid-angle density
        with the emitter choice in it (the choice probability alone for
        point lights, ``ds.delta``); the mask is false where no sample exists
        (pdf 0, back side of a one-sided emitter, zero radiance)."""
        active = mi.Bool(active)

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
        u2 = mi.Point2f(ux, dr.clip(uy, 0.0, 0.99999994))

        em = mi.UInt32(row[ROW_EM])
        pa = row[ROW_PA]
        p0 = mi.Point3f(row[ROW_P0], row[ROW_P0 + 1], row[ROW_P0 + 2])
        Le = mi.Color3f(row[ROW_L], row[ROW_L + 1], row[ROW_L + 2])
        present = set(self.kinds_present)
        if len(present) == 1:   # one kind (e.g. emissive meshes only): no per-lane kind
            kind = mi.UInt32(self.kinds_present[0])
        else:
            kind = dr.gather(mi.UInt32, self._e_kind, em, active)

        p = mi.Point3f(p0)
        n = dr.zeros(mi.Vector3f, dr.width(active))
        pdf = dr.zeros(mi.Float, dr.width(active))
        delta = dr.zeros(mi.Bool, dr.width(active))

        # ------------------ triangles and rectangles: uniform in area ------------------
        if present & {MESH, RECT}:
            flat = active & ((kind == MESH) | (kind == RECT))
            e0 = mi.Vector3f(row[ROW_E0], row[ROW_E0 + 1], row[ROW_E0 + 2])
            e1 = mi.Vector3f(row[ROW_E1], row[ROW_E1 + 1], row[ROW_E1 + 2])
            nf = dr.normalize(dr.cross(e0, e1))   # the geometric normal (rectangles: oriented at set-up)
            b = mi.warp.square_to_uniform_triangle(u2)
            b = dr.select(kind == MESH, mi.Vector2f(b), mi.Vector2f(u2))
            pf = p0 + e0 * b.x + e1 * b.y
            to = pf - si.p
            d2 = dr.squared_norm(to)
            cos_y = -dr.dot(to, nf) * dr.rsqrt(dr.select(d2 > 0.0, d2, 1.0))
            ok_f = flat & (cos_y > 0.0) & (d2 > 0.0)
            p = dr.select(flat, pf, p)
            n = dr.select(flat, nf, n)
            pdf = dr.select(ok_f, pa * d2 / dr.select(ok_f, cos_y, 1.0), pdf)

        # ------------------ spheres: uniform in the subtended cone ------------------
        if SPHERE in present:
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
            p = dr.select(sph, ps, p)
            n = dr.select(sph, v, n)
            pdf = dr.select(ok_s, pdf_s, pdf)

        # ------------------ point lights: a delta in position ------------------
        if POINT in present:
            pt = active & (kind == POINT)
            d2 = dr.squared_norm(p0 - si.p)
            pdf = dr.select(pt, pa, pdf)
            delta |= pt
            Le = dr.select(pt, Le / dr.select(d2 > 0.0, d2, 1.0), Le)

        # ------------------ everything else: Mitsuba, for those lanes only ------------------
        ds_o = None
        if OTHER in present:
            oth = active & (kind == OTHER)
            ptr = dr.gather(mi.EmitterPtr, self._emitters_dr, em, oth)
            ds_o, w_o = ptr.sample_direction(si, u2, oth)
            pdf_o = ds_o.pdf * pa
            oth &= ds_o.pdf > 0.0
            p = dr.select(oth, ds_o.p, p)
            n = dr.select(oth, mi.Vector3f(ds_o.n), n)
            pdf = dr.select(oth, pdf_o, pdf)
            delta = dr.select(oth, ds_o.delta, delta)
            # w_o = L_e / p_e: turn it into L_e so that the common division applies
            Le = dr.select(oth, mi.Color3f(w_o) * ds_o.pdf, Le)

        # ------------------ direction sample and weight ------------------
        ds = dr.zeros(mi.DirectionSample3f, dr.width(active))
        to = p - si.p
        dist = dr.norm(to)
        d = to / dr.select(dist > 0.0, dist, 1.0)
        if ds_o is not None:
            far = active & (kind == OTHER)
            d = dr.select(far, ds_o.d, d)
            dist = dr.select(far, ds_o.dist, dist)
        ds.p, ds.n, ds.d, ds.dist = p, mi.Normal3f(n), d, dist
        ds.pdf, ds.delta, ds.time = pdf, delta, si.time
        ds.emitter = dr.gather(mi.EmitterPtr, self._emitters_dr, em, active)
        ok = active & (pdf > 0.0)
        w = dr.select(ok, Le / dr.select(ok, pdf, 1.0), 0.0)
        ok &= dr.max(w) > 0.0
        return ds, w, ok, em

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


def _ptr(emitter) -> int:
    """Registry id of an emitter (a stable identity for one process)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(emitter))[0])


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
    _outside_symbolic("build the emitter table")
    s = EmitterSampler(scene, choice=choice, subset=subset)
    _CACHE[key] = (s,)
    return s


def _outside_symbolic(what: str) -> None:
    """The table is read from the scene on the host, which a symbolic loop
    or call cannot do (its literals cannot be evaluated there)."""
    if dr.flag(dr.JitFlag.SymbolicScope):
        raise RuntimeError(f"cannot {what} inside a symbolic loop: call slc.scene.emitter_sampling.for_scene(scene) "
                           "before tracing (slc.scene.scenes.Scene does it at load and in set_time)")


def clear_cache() -> None:
    _CACHE.clear()


def forget(scene_id: int) -> None:
    """Drop the tables of the scene at address ``scene_id`` (called when its
    :class:`slc.scene.scenes.Scene` is freed): an entry holds the scene's emitters and
    emissive shapes, which would otherwise stay alive, and stay in Mitsuba's
    object registry, which every frozen function traverses."""
    for k in [k for k in _CACHE if k[0] == scene_id]:
        del _CACHE[k]
