"""The per-scene emitter table: its layout and its set-up from a ``mi.Scene``.

:class:`EmitterTable` reads a scene's emitters once (kind, radiance, geometry
and power of each), builds the two-level alias tables (the emitter, then the
triangle of a mesh emitter) and packs one row of ``ROW`` floats per entry (the
``ROW_*`` columns); it follows moving emissive meshes (:meth:`EmitterTable.refresh`).
The sampling and density kernels that read the table are
:class:`slc.scene.emitter_sampling.EmitterSampler`, which extends it; the
densities are in ``docs/emitter-sampling.md``.
"""
from __future__ import annotations

import math

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


class EmitterTable:
    """The set-up of :class:`slc.scene.emitter_sampling.EmitterSampler`: the
    scene's emitters read into alias tables and packed rows (parameters as
    there: ``scene``, ``choice``, ``subset``)."""

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
        self.builds = 0
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

    def _choice_pmf(self, rows) -> np.ndarray:
        """The emitter choice P(e) over the table's emitters ``rows`` (as :meth:`_classify` gives
        them, after the emitter's index): uniform, or by power (emitters of unknown power and
        infinite ones keep the uniform share)."""
        N = len(rows)
        pmf = np.full(N, 1.0 / max(N, 1))
        if self.choice == "power" and N:
            inf = int(mi.EmitterFlags.Infinite)
            known = [k for k, r in enumerate(rows)
                     if r[4] is not None and not (int(self.emitters[r[0]].flags()) & inf)]
            power = np.array([max(rows[k][4], 0.0) for k in known], np.float64)
            if known and power.sum() > 0.0:
                share = len(known) / N
                pmf[known] = share * power / power.sum()
        return pmf

    def _build(self):
        # ``builds`` counts the reads of the emitters (construction and :meth:`rebuild`): a
        # reader of the scene's emitters on the host (e.g. slc's constant-emitter flag) keyed on
        # it follows a change of their radiance
        self.builds += 1
        rows = [(i, *self._classify(i)) for i in self.subset]
        N = len(rows)
        self.kinds_present = sorted({r[1] for r in rows})
        # ---------------- emitter choice P(e) ----------------
        pmf = self._choice_pmf(rows)
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
        counts, offsets, q, alias = _segment_alias(ent_p, self.size)
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
            outside_symbolic("re-read a moved emissive mesh")
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
        outside_symbolic("rebuild the emitter table")
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


def _segment_alias(ent_p: list, size: int):
    """(counts, offsets, q, alias) of the emitters' segments of the table: each segment
    (one emitter's entries, probabilities ``ent_p[e]``) holds the alias table of its entries,
    normalised within it (local indices)."""
    counts = np.array([len(x) for x in ent_p], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    q = np.ones(size)
    alias = np.zeros(size, np.int64)
    for o, c, x in zip(offsets, counts, ent_p):
        tot = x.sum()
        q[o:o + c], alias[o:o + c] = alias_table(x / tot if tot > 0 else np.full(c, 1.0 / c))
    return counts, offsets, q, alias


def _ptr(emitter) -> int:
    """Registry id of an emitter (a stable identity for one process)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(emitter))[0])


def outside_symbolic(what: str) -> None:
    """The table is read from the scene on the host, which a symbolic loop
    or call cannot do (its literals cannot be evaluated there)."""
    if dr.flag(dr.JitFlag.SymbolicScope):
        raise RuntimeError(f"cannot {what} inside a symbolic loop: call slc.scene.emitter_sampling.for_scene(scene) "
                           "before tracing (slc.scene.scenes.Scene does it at load and in set_time)")
