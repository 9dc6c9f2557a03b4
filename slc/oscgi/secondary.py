r"""Secondary radiance caches: a hashed world grid of coarse cells on the surfaces that the
primary caches' rays hit (the slides' "secondary caches ... span ~30 cm x 30 cm, quantized to
allow for more reuse").

A cell is keyed by the hit's quantised position ``floor(p / h)`` (``h`` = the cell size), the
dominant axis and sign of its front-facing geometric normal (6 bins: the two sides of a wall never
share a cell) and, by default, the hit's shape (``shape_key``: two rooms whose floors are separate
shapes never share a cell even where a 30 cm cell straddles the wall between them; the journal's
secondary caches are on-surface texels of islands, which never straddle two islands either).
The key is a 32-bit TEA hash of these; its home slot a second hash word. The table is open
addressing with linear probing over ``slots`` entries, filled without races in ``probes`` rounds
of gather / ``scatter_reduce(min)`` / gather (the smallest key wins a contested empty slot, the
others probe on): the same requests give the same table on every run. A request that finds no
slot within ``probes`` gets no cell and counts as overflow.

*Eviction*: a cell not touched (hit by any cache ray) in ``evict_after`` whole frames is freed at
the start of the next one (touched last in frame u: freed at the start of frame u + K + 1).
Freeing slots of a linear-probing table would cut the probe chains of the cells behind them, so the table is rebuilt instead: the surviving keys are inserted into an empty
table (deterministic, as above) and their data move with them; a freed slot is thus reused from
a reset state (count 0, layers 0). With eviction on, the table is also brought down to
``max_load`` (1/4) of its slots at the start of a frame by freeing the least recently touched
cells, so that the frame's new cells find slots within ``probes`` rounds.

*Budget*: at most ``budget`` cells are updated per frame (0: all requested). The requested cells
are ranked by ring (the cells primary rays read this frame first), then least-sampled (update
count), then oldest update, then slot; the others keep
their value (their EMA is simply not advanced this frame) and their ring requests lapse.

Each cell stores the *outgoing diffuse* radiance of its surface, :math:`L_o = \rho E / \pi`, in
``bounces`` layers: layer 1 holds direct light only, layer b adds light that arrived after b-1
further bounces,

.. math:: L^{(1)} = \frac{\rho}{\pi} E_{dir}, \qquad
          L^{(b)} = \rho\Big(\frac{E_{dir}}{\pi} + \frac{1}{n}\sum_{j=1}^{n} L^{(b-1)}(c_j)\Big),

with :math:`E_{dir}` from ``light_samples`` samples of the project's light sampling
(:func:`slc.lights.sample_light`, shadow rays) and n = ``rays`` cosine-distributed rays whose hits
fall in cells :math:`c_j` (their layer b-1 of the previous update; an emitter or the environment
hit by such a ray adds nothing, since next-event estimation already counts that light). A primary
cache reads layer ``bounces``, so that the primary point receives light after exactly
1..``bounces`` reflections, the paths of :func:`slc.references.indirect_light`. Bounces accumulate
over frames: layer b of a cell is at most b-1 updates behind.

Glossy hits (``glossy_hits``): a cell holds diffuse radiance only (0 for a metal); a secondary ray
whose hit has a glossy or delta BSDF reads instead one light sample with that BSDF towards the
ray's origin (:func:`_glossy_kernel`), the hit's layer 1 exactly (a lower bound for layers >= 2).

Points: a cell is updated from a representative point, the hit (lowest lane) that touched it last;
as hits move over the cell from frame to frame, the temporal average spans the cell.
Update set: every cell hit by a primary ray this frame (ring 1) and every cell hit by a ring-r
cell's rays in the previous frame (ring r+1 <= ``bounces``); ring ``bounces`` needs direct light only
and traces no rays. Temporal filter: exponential moving average with blend factor
1 / min(n, ``n_max``), n the cell's update count.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..backend import aligned
from ..cones.update import light_inputs
from ..freeze import FrozenFunction
from ..keys import INVALID, mixed_rng, stream_key
from ..lights import sample_light, visible
from .laps import Laps

EMPTY = INVALID
NO_RING = 0xFFFF
STREAM_SECONDARY = 0x05EC0001
_REP = 9          # representative point (3), front normal (3), diffuse albedo (3)


def front_normal(si: mi.SurfaceInteraction3f, d: mi.Vector3f) -> mi.Vector3f:
    """Geometric normal of a hit, on the side the ray ``d`` came from."""
    return dr.select(dr.dot(si.n, d) > 0.0, -si.n, si.n)


def _take(v, idx):
    """Components of the 3-vector ``v`` at ``idx`` (same type)."""
    return type(v)(*[dr.gather(mi.Float, v[c], idx) for c in range(3)])


@dataclass
class CacheHits:
    """The hits of cache rays (:meth:`SecondaryCache.trace`), one lane per ray."""
    p: mi.Point3f                 # hit position
    n: mi.Vector3f                # geometric normal
    t: mi.Float                   # hit distance (inf: a miss)
    shape: mi.UInt32              # shape index (into scene.shapes())
    pi: mi.PreliminaryIntersection3f
    valid: mi.Bool
    key: mi.UInt32                # the hit's cell key and home slot (:func:`cell_key`)
    home: mi.UInt32
    front_n: mi.Vector3f          # geometric normal on the ray's side
    glossy: mi.Bool               # the hit's BSDF has a glossy or delta lobe


@dataclass
class GlossyHits:
    """At the non-diffuse hits ``lanes`` of cache rays (:func:`_glossy_kernel`): the NEE term
    ``Ld``, one BSDF-sampled ray ``ray`` (mask ``ok``, weight ``bw``) and, when traced, the
    cells that ray hit (``slots``, ``hit``)."""
    lanes: mi.UInt32
    Ld: mi.Color3f
    bw: mi.Color3f
    ray: mi.Ray3f
    ok: mi.Bool
    slots: mi.UInt32 | None = None
    hit: mi.Bool | None = None


@dataclass
class CellHits:
    """Cache rays traced to the cells they hit (:meth:`SecondaryCache.sample`)."""
    hits: CacheHits
    slots: mi.UInt32              # the hit cell of each ray (INVALID: none)
    ok: mi.Bool                   # the ray has a cell
    glossy: GlossyHits | None     # the non-diffuse hits' own estimate (None: none this frame)


def _trace_kernel(sc, ray, active, h: float, slots: int, shape_key: bool):
    """Cache rays to their hits (``RayFlags.Minimal``) and the hits' cell keys: the fields of
    :class:`CacheHits` in order, evaluated. Frozen by :class:`SecondaryCache` (the rays of
    primary and secondary caches: two recordings)."""
    pi = sc.ray_intersect_preliminary(ray, coherent=False, active=active)
    si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
    sidx = mi.UInt32(pi.shape_index)
    ok = mi.Bool(active) & si.is_valid()
    key, home, nf = cell_key(si, ray.d, sidx, h, slots, shape_key)
    flags = pi.shape.bsdf().flags()
    glossy = ok & (mi.has_flag(flags, mi.BSDFFlags.Glossy) | mi.has_flag(flags, mi.BSDFFlags.Delta))
    out = (mi.Point3f(si.p), mi.Vector3f(si.n), mi.Float(si.t), sidx, pi, ok, key, home, nf, glossy)
    dr.eval(*out)
    return out


def cell_key(si, d, shape_index, h: float, slots: int, shape_key: bool):
    """(key, home slot, front normal) of hits ``si`` reached along ``d`` (see
    :meth:`SecondaryCache.key_of`)."""
    nf = front_normal(si, d)
    level = mi.UInt32(0)           # key bits 28-31: 0 (one cell size)
    hl = h * mi.Float(mi.UInt32(1) << level)
    c = mi.Vector3i(dr.floor(si.p / hl))
    a = dr.abs(nf)
    axis = dr.select((a.x >= a.y) & (a.x >= a.z), 0, dr.select(a.y >= a.z, 1, 2))
    neg = dr.select(axis == 0, nf.x < 0.0, dr.select(axis == 1, nf.y < 0.0, nf.z < 0.0))
    bin_ = mi.UInt32(axis * 2) + dr.select(neg, 1, 0)
    shape = mi.UInt32(shape_index) if shape_key else mi.UInt32(0)
    ux, uy, uz = (dr.reinterpret_array(mi.UInt32, v) for v in (c.x, c.y, c.z))
    k0, _ = mi.sample_tea_32(ux, uy, 4)
    key, home = mi.sample_tea_32(k0 ^ (uz * 0x9E3779B9), bin_ | (shape << 3) | (level << 28), 4)
    key = dr.minimum(key, EMPTY - 1)
    return key, home & (slots - 1), nf


def _rep_kernel(sc, pi, ray, idx, slots, p, nf):
    """The representative points of the winning lanes ``idx``: (slots, the 9 words: position,
    front normal and the diffuse albedo: the full interaction from the preliminary one, a BSDF
    call), evaluated. The caller writes them (a frozen function copies an input it writes to).
    ``sc`` (the scene, unused) declares the scene's arrays as inputs (the free width of
    ``lanes``, :mod:`slc.freeze`)."""
    pw = dr.gather(type(pi), pi, idx)
    rw = dr.gather(mi.Ray3f, ray, idx)
    sw = pw.compute_surface_interaction(rw, mi.RayFlags.All, True)
    albedo = mi.Color3f(sw.bsdf().eval_diffuse_reflectance(sw, sw.is_valid()))
    pp, nw = _take(p, idx), _take(nf, idx)
    sl = dr.gather(mi.UInt32, slots, idx)
    words = [pp.x, pp.y, pp.z, nw.x, nw.y, nw.z, albedo.x, albedo.y, albedo.z]
    dr.eval(sl, *words)
    return sl, words


def _direct_kernel(sc, lights, rep, keys_tab, cells, mix, ns, n_samples: float):
    r"""Direct light at the representative points of ``cells``: ``ns`` (opaque) light samples
    x_i (the project's light sampling, shadow rays), each weighted :math:`L_e \cos / p`;
    ``lights`` declares the emitter table as an input. Returns (E_dir/pi, the outgoing direct
    radiance before the albedo; point, normal, albedo, key and lit mask of each cell)."""
    rp = [dr.gather(mi.Float, rep, cells * _REP + j) for j in range(_REP)]
    p, nrm, rho = mi.Point3f(*rp[0:3]), mi.Vector3f(*rp[3:6]), mi.Color3f(*rp[6:9])
    keys = dr.gather(mi.UInt32, keys_tab, cells)
    si = dr.zeros(mi.SurfaceInteraction3f)     # width 1: a literal of the inputs' width would be baked
    si.p, si.n, si.sh_frame, si.wi = p, nrm, mi.Frame3f(nrm), mi.Vector3f(0, 0, 1)
    lit = dr.max(rho) > 0.0
    sampler = mixed_rng(keys, mix)

    def cond(i, E, sampler):
        return i < ns

    def body(i, E, sampler):
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        ds, w, ok = sample_light(sc, si, u, lit)
        cos = dr.dot(ds.d, nrm)
        ok &= (cos > 0.0) & dr.all(dr.isfinite(w))
        ok = visible(sc, si, ds, ok)
        return i + 1, E + dr.select(ok, w * cos, 0.0), sampler

    _, E_dir, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), sampler), cond=cond, body=body,
                                labels=("i", "E", "sampler"))
    L_dir = (E_dir / n_samples) * (1.0 / math.pi)
    dr.eval(L_dir, p, nrm, rho, keys, lit)
    return L_dir, p, nrm, rho, keys, lit


def _ray_kernel(p, nrm, keys, tl, mix, R: int):
    """The cosine rays of the tracing lanes ``tl`` (cell c = tl // R of the update's cells, ray
    j = tl % R) from the cells' representative points ``p`` (normals ``nrm``, keys ``keys``)."""
    c_of, j = tl // R, tl % R
    s2 = mixed_rng(dr.gather(mi.UInt32, keys, c_of) * R + j, mix)
    u = mi.Point2f(s2.next_float32(), s2.next_float32())
    sil = dr.zeros(mi.SurfaceInteraction3f)    # width 1: a literal of the inputs' width would be baked
    sil.p, sil.n = _take(p, c_of), _take(nrm, c_of)
    sil.sh_frame = mi.Frame3f(sil.n)
    d = sil.sh_frame.to_world(mi.warp.square_to_cosine_hemisphere(u))
    ray = sil.spawn_ray(d)
    dr.eval(ray)
    return ray


def _glossy_kernel(sc, lights, pi, ray, gi, lane_key, mix):
    """At the hits ``gi`` of cache rays on non-diffuse surfaces (glossy, metal), the
    outgoing radiance towards the entry is view-dependent, which a cell's diffuse radiance cannot
    hold: one light sample with the hit's BSDF (next-event estimation: the light after one
    reflection) and one BSDF-sampled ray, whose hit cell's radiance (layer ``bounces`` - 1) the
    caller adds with the weight. Returns (NEE term, BSDF weight, BSDF ray, its mask)."""
    ctx = mi.BSDFContext()
    pw = dr.gather(type(pi), pi, gi)
    rw = dr.gather(mi.Ray3f, ray, gi)
    si = pw.compute_surface_interaction(rw, mi.RayFlags.All, True)
    bsdf = si.bsdf()
    rng = mixed_rng(dr.gather(mi.UInt32, lane_key, gi), mix)
    # ------------------ next-event estimation at the hit ------------------
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    ds, w, okd = sample_light(sc, si, u, si.is_valid())
    okd = visible(sc, si, ds, okd)
    f = mi.Color3f(bsdf.eval(ctx, si, si.to_local(ds.d), okd))
    Ld = dr.select(okd, f * w, 0.0)
    # ------------------ one BSDF-sampled bounce ------------------
    bs, bw = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                         si.is_valid())
    ok2 = si.is_valid() & (bs.pdf > 0.0) & (dr.max(mi.Color3f(bw)) > 0.0)
    ray2 = si.spawn_ray(si.to_world(bs.wo))
    bw = dr.select(ok2, mi.Color3f(bw), 0.0)
    dr.eval(Ld, bw, ray2, ok2)
    return Ld, bw, ray2, ok2


class SecondaryCache:
    """Hashed grid of secondary radiance cells (see the module).

    Parameters: ``cell`` (edge in scene units), ``bounces`` (layers), ``n_max`` (EMA cap),
    ``rays`` (cosine rays per cell update, 32), ``light_samples`` (per cell update, 4),
    ``slots`` (table size, a power of two), ``probes`` (linear-probing rounds), ``shape_key``,
    ``budget`` (cell updates per frame, 0: unlimited), ``evict_after`` (frames unused, 0: never),
    ``max_load`` (with eviction on: cells kept at the start of a frame, as a fraction of ``slots``),
    ``glossy_hits`` (True: :class:`GlossyHits` at non-diffuse hits), ``freeze`` (True: the kernels
    with shape, BSDF and emitter calls, the ray tracing with the cell keys, the representative
    albedo, the direct light, the secondary rays and the glossy hits, are traced once and replayed
    by :class:`slc.freeze.FrozenFunction`; same results as traced)."""

    def __init__(self, mi_scene: mi.Scene, cell: float, bounces: int = 2, n_max: int = 8, rays: int = 32,
                 light_samples: int = 4, slots: int = 1 << 16, probes: int = 32, shape_key: bool = True,
                 seed: int = 0, budget: int = 0, evict_after: int = 0, max_load: float = 0.25,
                 freeze: bool = True, glossy_hits: bool = True):
        if slots & (slots - 1):
            raise ValueError("slots must be a power of two")
        self.sc, self.h, self.B = mi_scene, float(cell), int(bounces)
        self.n_max, self.rays, self.light_samples = int(n_max), int(rays), int(light_samples)
        self.slots, self.probes, self.shape_key, self.seed = int(slots), int(probes), bool(shape_key), int(seed)
        self.budget, self.evict_after, self.max_load = int(budget), int(evict_after), float(max_load)
        self.laps = Laps(False)
        # the kernels with BSDF, shape and emitter calls, traced once and replayed (dr.freeze); calls
        # narrower than 2 lanes traced (``narrow``: the arguments whose width decides)
        self.freeze, self.glossy_hits = bool(freeze), bool(glossy_hits)
        self._k_trace = FrozenFunction(_trace_kernel, self.freeze, max_recordings=6)
        # lanes: the winning lanes idx (a pure kernel), run on a free width when their number equals the
        # size of some scene array (the atrium: 2,880, recorded again in a timed frame; slc.freeze)
        self._k_rep = FrozenFunction(_rep_kernel, self.freeze, max_recordings=6, lanes=(3,), narrow=(3,))
        self._k_direct = FrozenFunction(_direct_kernel, self.freeze, max_recordings=6, narrow=(4,))
        self._k_ray = FrozenFunction(_ray_kernel, self.freeze, max_recordings=6, narrow=(0, 3))
        self._k_glossy = FrozenFunction(_glossy_kernel, self.freeze, max_recordings=6, narrow=(4,))
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._alloc()
        if self.evict_after > 0 and not getattr(self, "_warm", False):
            self._warm = True           # once per table (reset() is also the eviction's "nothing survives")
            self._warm_rebuild()
            self._alloc()

    def _alloc(self) -> None:
        cap = self.slots
        self.keys = dr.full(mi.UInt32, EMPTY, cap)
        self.home = dr.zeros(mi.UInt32, cap)                # home slot of the key (for rebuilds)
        self.used = dr.zeros(mi.UInt32, cap)                # last frame touched
        self.stamp = dr.zeros(mi.UInt32, cap)               # last frame updated
        self.count = dr.zeros(mi.UInt32, cap)
        self.pending = dr.full(mi.UInt32, NO_RING, cap)     # ring requested for the next update
        self.rep = dr.zeros(mi.Float, cap * _REP)
        self.layers = dr.zeros(mi.Float, cap * 3 * self.B)
        self._reuse_count = dr.zeros(mi.UInt32, self.slots)   # primary hits per cell, last frame
        self._overflow = mi.UInt32(0)                         # kept lazy: no sync inside a timed stage
        self.updated, self.requested, self.evicted, self.frame = 0, 0, 0, 0
        dr.eval(self.keys, self.home, self.used, self.stamp, self.count, self.pending, self.rep, self.layers)

    def words_per_slot(self) -> int:
        return 6 + _REP + 3 * self.B       # key, home, used, stamp, count, ring + rep. point + layers

    def memory_bytes(self) -> int:
        """The whole table (allocated up front)."""
        return 4 * self.words_per_slot() * self.slots

    def used_cells(self) -> int:
        return int(dr.count(self.keys != EMPTY)[0])

    def used_bytes(self) -> int:
        return 4 * self.words_per_slot() * self.used_cells()

    # ------------------------------------------------------------------ keys
    def key_of(self, si: mi.SurfaceInteraction3f, d: mi.Vector3f, shape_index: mi.UInt32):
        """(key, home slot, front normal) of hits ``si`` reached along ``d`` on the shapes
        ``shape_index`` (indices into ``scene.shapes()``: the same in every process, unlike the
        shape pointers)."""
        return cell_key(si, d, shape_index, self.h, self.slots, self.shape_key)

    def find_or_insert(self, key: mi.UInt32, home: mi.UInt32, active: mi.Bool) -> mi.UInt32:
        """Slot of each key (inserted when absent); INVALID where inactive or the table is full."""
        mask = self.slots - 1
        slot, act = mi.UInt32(home), mi.Bool(active)
        found = dr.full(mi.UInt32, INVALID, dr.width(key))
        dr.eval(slot, act, found)
        for r in range(self.probes):
            # ------------- claim the probed slot where it is empty (smallest key wins) -------------
            cur = dr.gather(mi.UInt32, self.keys, slot, act)
            dr.eval(cur)                  # read before the claim (and no copy of the table on write)
            dr.scatter_reduce(dr.ReduceOp.Min, self.keys, key, slot, act & (cur == EMPTY))
            dr.eval(self.keys)
            # --------------------- ours now (or already)? else probe the next slot ---------------------
            cur = dr.gather(mi.UInt32, self.keys, slot, act)
            mine = act & (cur == key)
            found = dr.select(mine, slot, found)
            act &= ~mine
            slot = dr.select(act, (slot + 1) & mask, slot)
            dr.eval(found, act, slot)
            if r % 2 == 1 and not dr.any(act):       # most requests settle in one or two rounds
                break
        self._overflow = self._overflow + mi.UInt32(dr.count(act))
        got = found != INVALID
        dr.scatter(self.home, home, found, got)
        dr.scatter(self.used, dr.opaque(mi.UInt32, self.frame), found, got)
        dr.eval(self.home, self.used)
        return found

    def find(self, key: mi.UInt32, home: mi.UInt32, active: mi.Bool) -> tuple:
        """(slot, found) of each key, looked up without insertion: linear probing from its home
        slot (a symbolic loop, at most ``probes`` rounds) until the key or an empty slot."""
        mask = self.slots - 1
        k0 = dr.gather(mi.UInt32, self.keys, home, active)

        def cond(j, s, k):
            return active & (j < self.probes) & (k != key) & (k != EMPTY)

        def body(j, s, k):
            s = (s + 1) & mask
            return j + 1, s, dr.gather(mi.UInt32, self.keys, s, active)

        _, slot, k = dr.while_loop(state=(mi.UInt32(0), mi.UInt32(home), k0), cond=cond, body=body,
                                   labels=("j", "s", "k"))
        return slot, active & (k == key)

    def trace(self, ray: mi.Ray3f, active=True) -> CacheHits:
        """Hits of cache rays and their cells' keys (:func:`_trace_kernel`, frozen): position,
        geometric normal and shape only (``RayFlags.Minimal``): the cell key needs no more, and
        the full interaction (for the albedo) is computed again for the one representative lane
        per cell."""
        active = dr.zeros(mi.Bool, dr.width(ray.d)) | mi.Bool(active)      # an array of the rays' width
        return CacheHits(*self._k_trace(self.sc, ray, active, self.h, self.slots, self.shape_key))

    def _set_rep(self, slots: mi.UInt32, ok: mi.Bool, hits: CacheHits, ray: mi.Ray3f) -> None:
        """Each touched cell's representative point: the lowest lane that touched it. The albedo
        (a BSDF call on the full interaction, computed from the lane's preliminary intersection)
        is evaluated on the winning lanes only (one per touched cell)."""
        lane = dr.arange(mi.UInt32, dr.width(slots))
        win = dr.full(mi.UInt32, INVALID, self.slots)
        dr.scatter_reduce(dr.ReduceOp.Min, win, lane, slots, ok)
        dr.eval(win)
        w = ok & (dr.gather(mi.UInt32, win, slots, ok) == lane)
        idx = dr.compress(w)
        if dr.width(idx) == 0:
            return
        sl, words = self._k_rep(self.sc, hits.pi, ray, idx, slots, hits.p, hits.front_n)
        for j, v in enumerate(words):
            dr.scatter(self.rep, v, sl * _REP + j)
        dr.eval(self.rep)

    def touch(self, hits: CacheHits, ray: mi.Ray3f, active: mi.Bool):
        """Cells of the hits (from :meth:`trace`) of ``ray`` (inserted when new, representative
        point refreshed). Returns (slots, valid mask)."""
        ok = mi.Bool(active) & hits.valid
        self.laps.lap("touch_key", ok)
        slots = self.find_or_insert(hits.key, hits.home, ok)
        self.laps.lap("touch_find")
        ok &= slots != INVALID
        dr.eval(ok)
        self._set_rep(slots, ok, hits, ray)
        self.laps.lap("touch_rep")
        return slots, ok

    def sample(self, ray: mi.Ray3f, active, lane_key: mi.UInt32, mix, lap: str, grazing: bool = True,
               bounce: bool = False) -> CellHits:
        """Cache rays to the cells they hit: :meth:`trace`, :meth:`touch` and, with
        ``glossy_hits``, the non-diffuse hits' own estimate (:func:`_glossy_kernel`, random
        numbers keyed by ``lane_key`` per ray and the stream ``mix``); with ``bounce`` (and
        ``bounces`` > 1) the glossy hits' BSDF rays traced and touched too (their cells, ring 2,
        are the caller's to request). ``grazing`` False drops the hits with n . d = 0.
        ``lap``: the sub-stage clock's name for the tracing."""
        hits = self.trace(ray, active)
        self.laps.lap(lap, hits.p, hits.n, hits.t, hits.valid, hits.key, hits.home, hits.glossy)
        slots, ok = self.touch(hits, ray, active)
        if not grazing:
            ok &= dr.dot(hits.n, ray.d) != 0.0
        glossy = None
        if self.glossy_hits:
            gi = dr.compress(hits.glossy)
            if dr.width(gi) > 0:
                glossy = GlossyHits(gi, *self._k_glossy(self.sc, light_inputs(self.sc), hits.pi, ray, gi,
                                                        lane_key, mix))
                if bounce and self.B > 1:
                    h2 = self.trace(glossy.ray, glossy.ok)
                    glossy.slots, glossy.hit = self.touch(h2, glossy.ray, glossy.ok)
                    glossy.hit &= dr.dot(h2.n, glossy.ray.d) != 0.0
        return CellHits(hits, slots, ok, glossy)

    def hit_radiance(self, h: CellHits, glossy_L=None, layer: int | None = None) -> list:
        """Per ray (3 channels): the outgoing radiance (layer ``layer``, default ``bounces``) of
        the cell it hit, or ``glossy_L`` at the glossy hits ``h.glossy.lanes``."""
        L = self.radiance(h.slots, h.ok, layer)
        L = [mi.Float(L[c]) for c in range(3)]
        if h.glossy is not None and glossy_L is not None:
            for c in range(3):
                dr.scatter(L[c], glossy_L[c], h.glossy.lanes)
        return L

    def updated_once(self, slots: mi.UInt32, ok: mi.Bool) -> mi.Bool:
        """Whether cells hold a value (updated at least once)."""
        return ok & (dr.gather(mi.UInt32, self.count, slots, ok) > 0)

    def radiance(self, slots: mi.UInt32, ok: mi.Bool, layer: int | None = None) -> mi.Color3f:
        """Outgoing radiance of cells (layer ``bounces`` by default)."""
        b = (self.B if layer is None else layer) - 1
        base = (slots * self.B + b) * 3
        return mi.Color3f(*[dr.gather(mi.Float, self.layers, base + c, ok) for c in range(3)])

    # ------------------------------------------------------------------ update
    def begin_frame(self, frame: int | None = None) -> mi.UInt32:
        """Start a frame: evict cells unused for ``evict_after`` frames, then return the requests
        carried from the previous update (ring per slot); the caller adds ring 1."""
        if frame is not None:
            self.frame = int(frame)
        self.evicted = 0
        if self.evict_after > 0:
            self.evict()
        req, self.pending = self.pending, dr.full(mi.UInt32, NO_RING, self.slots)
        return req

    def evict(self) -> int:
        """Free the cells not touched in the last ``evict_after`` frames by rebuilding the table
        with the others (see the module); returns the number freed."""
        live = self.keys != EMPTY
        old = self._old(live)
        n_live, n_old = int(dr.count(live)[0]), int(dr.count(old)[0])
        cap = int(self.slots * self.max_load)
        if n_live - n_old > cap:
            n_old += self._drop_least_recent(live, old, n_live - n_old - cap)
        if n_old == 0:
            return 0
        keep = dr.compress(live & ~old)
        if dr.width(keep) == 0:                # nothing survives: a fresh table
            ov, frame = self._overflow, self.frame
            self.reset()
            self._overflow, self.evicted, self.frame = ov, n_old, frame
            return n_old
        self._rebuild(keep)
        self.evicted = n_old
        return n_old

    def _old(self, live: mi.Bool) -> mi.Bool:
        """Live cells not touched in the last ``evict_after`` whole frames."""
        f = dr.opaque(mi.UInt32, self.frame)
        return live & (f - self.used > self.evict_after) & (self.used < f)

    def _drop_least_recent(self, live: mi.Bool, old: mi.Bool, n: int) -> int:
        """Over the load cap: mark (in ``old``) the ``n`` least recently touched live cells that
        are not old yet (then lowest slot); returns how many were marked."""
        idx = np.asarray(dr.compress(live & ~old), dtype=np.int64)
        u = np.asarray(dr.gather(mi.UInt32, self.used, mi.UInt32(aligned(idx, np.uint32))), dtype=np.int64)
        drop = idx[np.lexsort((idx, u))[:n]]
        dr.scatter(old, True, mi.UInt32(aligned(np.sort(drop), np.uint32)))
        return int(drop.size)

    def _rebuild(self, keep: mi.UInt32) -> None:
        """An empty table with the cells at slots ``keep`` (evaluated, ascending) re-inserted and
        their data moved; every other slot in its reset state."""
        # every array in memory (a literal one, e.g. ``pending`` with one bounce, would fold into the
        # gathers below and give another kernel than the one built by _warm_rebuild)
        dr.make_opaque(self.home, self.used, self.stamp, self.count, self.pending, self._reuse_count, self.rep,
                       self.layers)
        per_slot = [(self.home, 1), (self.used, 1), (self.stamp, 1), (self.count, 1), (self.pending, 1),
                    (self._reuse_count, 1), (self.rep, _REP), (self.layers, 3 * self.B)]
        data = [(type(a), [dr.gather(type(a), a, keep * w + j) for j in range(w)], w) for a, w in per_slot]
        kk, kh = dr.gather(mi.UInt32, self.keys, keep), dr.gather(mi.UInt32, self.home, keep)
        dr.eval(kk, kh, *[v for _, vs, _ in data for v in vs])
        # ------------- an empty table, the surviving keys re-inserted, their data moved -------------
        self.keys = dr.full(mi.UInt32, EMPTY, self.slots)
        ov = self._overflow
        new = self.find_or_insert(kk, kh, mi.Bool(True))
        self._overflow = ov            # the table only shrinks: every survivor finds a slot
        ok = new != INVALID
        fresh = [dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.UInt32, self.slots),
                 dr.zeros(mi.UInt32, self.slots), dr.full(mi.UInt32, NO_RING, self.slots),
                 dr.zeros(mi.UInt32, self.slots), dr.zeros(mi.Float, self.slots * _REP),
                 dr.zeros(mi.Float, self.slots * 3 * self.B)]
        for arr, (_, vs, w) in zip(fresh, data):
            for j, v in enumerate(vs):
                dr.scatter(arr, v, new * w + j, ok)
        dr.eval(*fresh)
        (self.home, self.used, self.stamp, self.count, self.pending, self._reuse_count, self.rep,
         self.layers) = fresh

    def _warm_rebuild(self) -> None:
        """Build the kernels of an eviction (the selection of old cells, the over-cap selection
        and the rebuild) on a stand-in table of three cells, so that the first real eviction,
        often after an experiment's warm-up frames, builds none. The caller then allocates the
        table afresh. The stand-in must look like a running table to the JIT: distinct arrays in
        memory (equal literal arrays are one variable, and gathers from literals are folded) and
        at least two survivors (a width-1 array is read as a scalar)."""
        U, F, n = mi.UInt32, mi.Float, self.slots
        i = dr.arange(U, n)
        self.keys = dr.select(i < 3, i + 1, EMPTY)
        self.home, self.used, self.stamp, self.count = (dr.full(U, 1 + j, n) for j in range(4))
        self.pending, self._reuse_count = dr.full(U, 5, n), dr.full(U, 6, n)
        self.rep, self.layers = dr.full(F, 7.0, n * _REP), dr.full(F, 8.0, n * 3 * self.B)
        dr.make_opaque(self.keys, self.home, self.used, self.stamp, self.count, self.pending, self.rep,
                       self.layers, self._reuse_count)
        ov, frame = self._overflow, self.frame
        self.frame = 0
        live = self.keys != EMPTY
        old = self._old(live)                             # none (used = 2 > frame 0)
        dr.count(live), dr.count(old)
        dr.eval(dr.compress(live & ~old))                 # evict()'s selection without the cap
        self._drop_least_recent(live, old, 1)             # the cap: one of the three dropped
        self._rebuild(dr.compress(live & ~old))           # two survivors
        self._overflow, self.frame = ov, frame

    def request(self, req: mi.UInt32, slots: mi.UInt32, ok: mi.Bool, ring: int = 1) -> None:
        dr.scatter_reduce(dr.ReduceOp.Min, req, mi.UInt32(ring), slots, ok)

    def record_reuse(self, slots: mi.UInt32, ok: mi.Bool) -> None:
        """Primary hits per touched cell this frame (the reuse histogram)."""
        cnt = dr.zeros(mi.UInt32, self.slots)
        dr.scatter_reduce(dr.ReduceOp.Add, cnt, mi.UInt32(1), slots, ok)
        self._reuse_count = cnt

    @property
    def overflow(self) -> int:
        """Requests that found no slot, since the last reset."""
        return int(self._overflow[0])

    @property
    def reuse(self) -> mi.UInt32:
        """Primary hits of each cell touched in the last frame."""
        cnt = self._reuse_count
        return dr.gather(mi.UInt32, cnt, dr.compress(cnt > 0))

    def update(self, frame: int, req: mi.UInt32) -> mi.UInt32:
        """Update every requested cell once (see the module); returns the updated slots."""
        sc, B = self.sc, self.B
        cells = dr.compress(req <= B)
        self.requested = dr.width(cells)
        if 0 < self.budget < dr.width(cells):
            # ----------- budget: least-sampled first, then oldest update, then slot -----------
            c_np = np.asarray(cells, dtype=np.int64)
            rg = np.asarray(dr.gather(mi.UInt32, req, cells), dtype=np.int64)
            cnt = np.asarray(dr.gather(mi.UInt32, self.count, cells), dtype=np.int64)
            age = self.frame - np.asarray(dr.gather(mi.UInt32, self.stamp, cells), dtype=np.int64)
            order = np.lexsort((c_np, -age, cnt, rg))[: self.budget]
            cells = mi.UInt32(aligned(np.sort(c_np[order]), np.uint32))   # aligned: else another kernel
        n = dr.width(cells)
        self.updated = n
        if n == 0:
            return cells
        ring = dr.gather(mi.UInt32, req, cells)

        # ------------------- direct light at the representative point (NEE) -------------------
        L_dir, p, nrm, rho, keys, lit = self._k_direct(
            sc, light_inputs(sc), self.rep, self.keys, cells, stream_key(self.seed, frame, STREAM_SECONDARY),
            dr.opaque(mi.UInt32, self.light_samples), float(max(self.light_samples, 1)))
        self.laps.lap("sec_direct")

        # ------------- cosine rays to other cells: layers b-1 of their previous update -------------
        mean = [mi.Color3f(0.0) for _ in range(B - 1)]
        tl = mi.UInt32()
        if B > 1:
            R = self.rays
            lane = dr.arange(mi.UInt32, n * R)
            c_of = lane // R
            tracing = dr.gather(mi.UInt32, ring, c_of) < B
            tracing &= dr.gather(mi.Bool, lit, c_of)
            # ---- only the tracing lanes (cells of ring < B with albedo) from here on ----
            tl = dr.compress(tracing)
        if dr.width(tl) > 0:      # (none: no cell of ring < B has albedo and light, e.g. a black scene)
            c_of = tl // R
            ray = self._k_ray(p, nrm, keys, tl, stream_key(self.seed, frame, STREAM_SECONDARY + 1), R)
            # ---- rays hitting glossy/metal surfaces: NEE with the hit's BSDF towards the cell
            # (the light after one reflection there, layer 1 exactly; a lower bound for layers >= 2) ----
            h = self.sample(ray, True, dr.gather(mi.UInt32, keys, c_of) * R + tl % R,
                            stream_key(self.seed, frame, STREAM_SECONDARY + 2), "sec_rays", grazing=False)
            next_ring = dr.gather(mi.UInt32, ring, c_of) + 1
            dr.scatter_reduce(dr.ReduceOp.Min, self.pending, next_ring, h.slots, h.ok & (next_ring <= B))
            for b in range(1, B):
                Lh = self.hit_radiance(h, h.glossy.Ld if h.glossy is not None else None, layer=b)
                full = [dr.zeros(mi.Float, n * R) for _ in range(3)]
                for c in range(3):
                    dr.scatter(full[c], Lh[c], tl)
                mean[b - 1] = mi.Color3f(*[dr.block_sum(full[c], R) for c in range(3)]) * (1.0 / R)
            dr.eval(self.pending, *mean)
            Lh = None                     # an unevaluated reader of the layers (written below)
            self.laps.lap("sec_touch")
            traced = ring < B
        else:
            traced = dr.zeros(mi.Bool, n)

        # ----------------------------- new layers, EMA, write back -----------------------------
        new = [rho * L_dir]
        for b in range(1, B):
            new.append(dr.select(traced, rho * (L_dir + mean[b - 1]), new[0]))
        cnt = dr.minimum(dr.gather(mi.UInt32, self.count, cells) + 1, 0xFFFF)
        a = dr.rcp(mi.Float(dr.minimum(cnt, self.n_max)))
        vals = []
        for b in range(B):
            for c in range(3):
                idx = (cells * B + b) * 3 + c
                old = dr.gather(mi.Float, self.layers, idx)
                vals.append((idx, dr.fma(a, new[b][c] - old, old)))
        dr.eval(cnt, *[v for _, v in vals])
        # no unevaluated reader of the written arrays may survive (Dr.Jit would copy them whole)
        old = None
        for idx, v in vals:
            dr.scatter(self.layers, v, idx)
        dr.scatter(self.count, cnt, cells)
        dr.scatter(self.stamp, dr.opaque(mi.UInt32, frame), cells)
        dr.eval(self.layers, self.count, self.stamp)
        return cells

    # ------------------------------------------------------------------ reports
    def reuse_histogram(self, bins=(1, 2, 4, 8, 16, 32, 64, 128, 256, 1 << 30)) -> dict:
        """Touched cells by primary hits per cell, in bins [bins[i], bins[i+1])."""
        r = np.asarray(self.reuse, dtype=np.int64)
        h, _ = np.histogram(r, bins=list(bins))
        return {"bins": list(bins), "counts": h.tolist(), "cells": int(r.size),
                "mean": float(r.mean()) if r.size else 0.0, "max": int(r.max()) if r.size else 0}
