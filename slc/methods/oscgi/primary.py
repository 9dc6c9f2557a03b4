"""The update of osc-gi's primary caches, stage by stage (:class:`PrimaryUpdate`, a part of
:class:`slc.methods.oscgi.method.OSCGI`): the per-frame budget's choice of entries, the texels each
entry traces, their new samples from the secondary cells, and the temporal blend written back."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.backend import aligned
from slc.scene.lights import light_inputs
from slc.core.freeze import FrozenFunction
from slc.core.keys import INVALID, stream_key
from slc.osc.blocks import extend_array
from slc.osc.protocol import EntryStart, entry_start
from slc.methods.oscgi.kernels import (STREAM_GLOSSY, STREAM_PRIMARY, STREAM_PRIMARY_DIRECT, primary_direct_kernel,
                                       primary_ray_kernel)
from slc.methods.oscgi.origins import backface_share


@dataclass
class TexelLanes:
    """An update's lanes: one per (entry e, texel k) of its N entries (N x D lanes), and which
    of them are traced this update (:meth:`PrimaryUpdate._texel_lanes`)."""
    e: mi.UInt32                  # the lane's entry (index into the update's entries)
    k: mi.UInt32                  # the lane's texel
    slot: mi.UInt32               # the entry's slot
    start: EntryStart             # where the entry's previous value comes from (reset / LOD seed)
    fine: mi.Bool                 # the entry starts from the mean of its finer entries instead
    fine_old: list | None         # that mean (3 channels)
    c_old: mi.Float               # the entry's update count before this update (1: a seeded new entry)
    c: mi.UInt32                  # this update's number
    full: mi.Bool                 # every texel traced (a new entry)
    traced: mi.Bool               # the texel is traced this update
    tl: mi.UInt32                 # the traced lanes (indices into the N x D lanes)
    S: int                        # a settled entry traces each texel once every S updates


@dataclass
class TexelSamples:
    """The new samples of an update's N x D texel lanes (:meth:`PrimaryUpdate._texel_samples`)."""
    value: list                   # radiance sample (3 channels; 0 where not traced)
    empty: mi.Bool                # the sample's cell holds no value yet (the texel keeps its own)
    inv_t: mi.Float               # 1 / hit distance of the texel's ray (0: a miss or not traced)
    n_t: mi.Float                 # 1 where a ray was traced


class PrimaryUpdate:
    """The ``update`` of :class:`~slc.methods.oscgi.method.OSCGI` (see its docstring for the estimator),
    a part the method holds and calls: it reads the method ``gi``'s settings, storage and secondary
    cache, writes the entries' storage and the figures the method reports (``entries_updated``,
    ``origin_probe``), and keeps the state of its own stages (``upd_frame``, ``finer_seeded``)."""

    def __init__(self, gi):
        self.gi = gi
        # traced once and replayed (FrozenFunction): a new width of the inputs needs no recording;
        # a call narrower than 2 lanes is traced (narrow: the argument whose width decides)
        self.k_ray = FrozenFunction(primary_ray_kernel, bool(gi.freeze), max_recordings=6, narrow=(2,))
        self.k_direct = FrozenFunction(primary_direct_kernel, bool(gi.freeze), max_recordings=6, narrow=(3,))
        # direct light in the entries only with output=full, direct=cache; else per pixel (OSCGI.finish)
        self.cache_direct = gi.output == "full" and gi.direct == "cache"
        self.reset()

    def reset(self) -> None:
        """Forget the state kept across frames."""
        self.upd_frame = None          # per slot: frame of the entry's last update (update_budget)
        self.finer_seeded = None       # per entry of the last update: seeded from its finer entries (tests)

    def update(self, ctx, fr, policy):
        """The stages of an update: the budget's choice of entries (:meth:`_budgeted`), the
        texels each traces (:meth:`_texel_lanes`), their new samples from the secondary cells
        (:meth:`_texel_samples`), the temporal blend written back (:meth:`_blend`)."""
        gi = self.gi
        n_requested = fr.n_active
        fr, policy = self._budgeted(ctx, fr, policy)
        gi.laps.start()
        # in a frame without new entries the cache's seed slots are a literal (all INVALID), which
        # would give the kernels reading them another IR (built in a timed frame): an array in memory
        dr.make_opaque(fr.seed_slot)
        lanes = self._texel_lanes(fr, policy)
        samples = self._texel_samples(ctx, fr, lanes)
        self._blend(fr, lanes, samples)
        return dr.zeros(mi.Bool, n_requested)

    def _texel_lanes(self, fr, policy) -> TexelLanes:
        """One lane per (entry, texel) of the updated entries, where each starts from, and which
        texels this update traces: texel k of an entry is traced in its first update and,
        afterwards, in update c when k = c (mod S), S = hemi^2 / texel_rays: every texel once per
        S updates."""
        gi = self.gi
        D, N = gi.grid.n, fr.n_active
        lane = dr.arange(mi.UInt32, N * D)
        e, k = lane // D, lane % D
        S = D // gi.texel_rays
        is_new = dr.gather(mi.Bool, fr.is_new, e)
        slot = dr.gather(mi.UInt32, fr.active, e)
        start = entry_start(is_new, dr.gather(mi.UInt32, fr.seed_slot, e), slot)
        # ------- new entries without a coarser seed: the mean of their finer entries, if any -------
        kids = self._finer_seeds(fr)
        # per entry (N lanes), then spread to the entry's texels
        n_kids_e = sum(dr.select(kd != INVALID, 1.0, 0.0) for kd in kids)
        fine_e = fr.is_new & (fr.seed_slot == INVALID) & (n_kids_e > 0.0)
        self.finer_seeded = fine_e                                      # per entry (tests)
        n_kids = dr.gather(mi.Float, n_kids_e, e) if kids else 0.0
        fine = dr.gather(mi.Bool, fine_e, e)
        fine_old = []
        for ch in range(3):
            acc = mi.Float(0.0)
            for kd in kids:
                ks = dr.gather(mi.UInt32, kd, e)
                acc += gi.read(ks, k * 3 + ch, fine & (ks != INVALID))
            fine_old.append(acc * dr.rcp(dr.maximum(n_kids, 1.0)))
        # fine_old is read (masked) in the blend's kernel: not evaluated here over every texel
        dr.eval(fine_e)
        gi.laps.lap("primary_seeds")
        c_old = dr.select(is_new, dr.select(start.seeded | fine, 1.0, 0.0), gi.read(slot, gi.count_word))
        c = mi.UInt32(c_old) + 1                                     # this update's number
        full = dr.gather(mi.UInt32, policy.rays, e) >= D
        traced = full | ((k % S) == (c % S))
        dr.eval(traced, c_old)
        return TexelLanes(e=e, k=k, slot=slot, start=start, fine=fine, fine_old=fine_old, c_old=c_old, c=c,
                          full=full, traced=traced, tl=dr.compress(traced), S=S)

    def _texel_samples(self, ctx, fr, lanes: TexelLanes) -> TexelSamples:
        """The traced texels' new samples: one jittered cosine ray per traced texel from the
        entry's own point; the outgoing radiance of the secondary cell it hits (the cells
        requested, then updated, shared by every entry), or at a glossy hit its own estimate
        (:meth:`SecondaryCache.sample`); with ``direct=cache`` the entry's light samples binned
        into the texels. Spread back to all N x D lanes (0 where not traced)."""
        gi = self.gi
        sc, sec, laps = gi.scene.mi_scene, gi.secondary, gi.laps
        D, N, tl = gi.grid.n, fr.n_active, lanes.tl
        et, kt = tl // D, tl % D
        ray, ok = self.k_ray((fr.si.p, fr.si.n, fr.si.sh_frame.n), fr.keys, tl,
                             stream_key(gi.seed, ctx.frame, STREAM_PRIMARY), D, gi.hemi)
        laps.lap("primary_raygen", ray, ok)

        # ------------- secondary caches: cells of the hits, requests, update (all shared) -------------
        req = sec.begin_frame(ctx.frame)              # eviction first: slots move in a rebuild
        laps.lap("secondary_evict", req)
        # non-diffuse hits: NEE + one BSDF ray into a cell (ring 2) per lane
        h = sec.sample(ray, ok, dr.gather(mi.UInt32, fr.keys, et) * D + kt,
                       stream_key(gi.seed, ctx.frame, STREAM_GLOSSY), "primary_rays", bounce=True)
        if gi.probe_origins:                      # (measurements, tests: back-face hits of the cache rays)
            b, v = backface_share(h.hits.n, ray.d, h.hits.valid)
            gi.origin_probe = (gi.origin_probe[0] + b, gi.origin_probe[1] + v)
        sec.request(req, h.slots, h.ok, 1)
        sec.record_reuse(h.slots, h.ok)
        g = h.glossy
        if g is not None and g.slots is not None:
            sec.request(req, g.slots, g.hit, 2)
        laps.lap("secondary_lookup", h.slots, h.ok, req)
        sec.update(ctx.frame, req)
        laps.lap("secondary_update")
        # a hit cell never updated yet (over the budget) holds no value: the texel is not blended
        # (it keeps its value) rather than pulled towards 0, unless it has no value yet either
        Lg = None
        if g is not None:
            Lg = g.Ld if g.slots is None else g.Ld + g.bw * sec.radiance(g.slots, g.hit, layer=gi.bounces - 1)
        Lc = sec.hit_radiance(h, Lg)                   # outgoing radiance of the hit's cell
        em = h.ok & ~sec.updated_once(h.slots, h.ok)
        if g is not None:
            dr.scatter(em, g.hit & ~sec.updated_once(g.slots, g.hit) if g.slots is not None else mi.Bool(False),
                       g.lanes)
        # mean inverse hit distance of the entry's rays this update (a miss: 0), for the filter
        t_hit = h.hits.t
        it_hit = dr.select(t_hit != dr.inf, dr.rcp(dr.maximum(t_hit, 1e-6)), 0.0)
        if dr.width(tl) == N * D:
            # every texel traced (texel_rays = hemi^2, the default, or all entries updated in full):
            # tl is the identity, the per-lane values are used as they are (no scatters)
            out = TexelSamples(value=Lc, empty=mi.Bool(em), inv_t=dr.select(ok, it_hit, 0.0),
                               n_t=dr.select(ok, 1.0, 0.0))
        else:
            out = TexelSamples(value=[dr.zeros(mi.Float, N * D) for _ in range(3)], empty=dr.zeros(mi.Bool, N * D),
                               inv_t=dr.zeros(mi.Float, N * D), n_t=dr.zeros(mi.Float, N * D))
            for ch in range(3):
                dr.scatter(out.value[ch], Lc[ch], tl)
            dr.scatter(out.empty, em, tl)
            dr.scatter(out.inv_t, it_hit, tl, ok)
            dr.scatter(out.n_t, 1.0, tl, ok)
        dr.eval(*out.value, out.empty, out.inv_t, out.n_t)
        laps.lap("primary_samples")

        # ----------------- direct light (output=full): light samples binned into texels -----------------
        if self.cache_direct:
            scratch = dr.zeros(mi.Float, N * D * 3)
            scratch = self.k_direct(sc, light_inputs(sc), fr.si, fr.keys, scratch,
                                    stream_key(gi.seed, ctx.frame, STREAM_PRIMARY_DIRECT),
                                    dr.opaque(mi.UInt32, gi.direct_rays),
                                    1.0 / (gi.direct_rays * gi.grid.texel_weight), gi.hemi)
            lane = dr.arange(mi.UInt32, N * D)
            out.value = [out.value[c] + dr.gather(mi.Float, scratch, lane * 3 + c) for c in range(3)]
            laps.lap("primary_direct")
        return out

    def _blend(self, fr, lanes: TexelLanes, samples: TexelSamples) -> None:
        r"""The temporal EMA of every traced texel, :math:`L_k \leftarrow L_k + (\hat L_k - L_k)
        / \min(c_k, N_{max})`, c_k the texel's own sample count (c for full updates, about
        1 + ceil((c - 1) / S) in rotation); a new entry starts from its seed. The irradiance and
        the mean inverse hit distance follow; everything is written back to the storage."""
        gi = self.gi
        D, N, G = gi.grid.n, fr.n_active, gi.grid
        st, traced, k = lanes.start, lanes.traced, lanes.k
        cnt = lanes.c_old + 1.0
        c_k = dr.select(lanes.full, cnt, 1.0 + mi.Float((lanes.c - 1 + lanes.S - 1) // lanes.S))
        a = dr.select(traced & ~(samples.empty & (c_k > 1.0)), dr.rcp(dr.minimum(c_k, float(gi.n_max))), 0.0)
        new = []
        for ch in range(3):
            old = dr.select(lanes.fine, lanes.fine_old[ch], gi.read(st.src, k * 3 + ch, st.keep))
            new.append(dr.fma(a, dr.select(traced, samples.value[ch], old) - old, old))
        E = [dr.block_sum(x, D) * G.texel_weight for x in new]      # per entry: (pi/R^2) sum_k L_k
        # the mean inverse hit distance, EMA over updates (the seed's value for a seeded entry)
        n_e, s_e = dr.block_sum(samples.n_t, D), dr.block_sum(samples.inv_t, D)
        c_e = dr.gather(mi.Float, lanes.c_old, dr.arange(mi.UInt32, N) * D) + 1.0
        st_e = entry_start(fr.is_new, fr.seed_slot, fr.active)
        d_old = gi.read(st_e.src, gi.inv_t_word, st_e.keep)
        a_e = dr.select(n_e > 0.0, dr.select(st_e.keep, dr.rcp(dr.minimum(c_e, float(gi.n_max))), 1.0), 0.0)
        d_new = dr.fma(a_e, s_e * dr.rcp(dr.maximum(n_e, 1.0)) - d_old, d_old)
        dr.eval(*new, *E, cnt, d_new)
        gi.laps.lap("primary_blend")
        # no live reader of the storage (unevaluated gathers) may survive the scatters below: Dr.Jit
        # would copy the whole storage (12.9 MB at 16k entries) before writing into it
        del old, d_old
        lanes.fine_old = None
        for ch in range(3):
            gi.write(new[ch], lanes.slot, k * 3 + ch)
        gi.write(E, fr.active, gi.irr_word)
        gi.write(cnt, lanes.slot, gi.count_word, k == 0)
        gi.write(d_new, fr.active, gi.inv_t_word)
        gi.laps.lap("primary_ema", gi.storage)

    def update_limit(self, fr) -> int:
        """The most entries one frame's update may take (``update_budget`` x the largest
        viewer's pixels / bias^2; 0 when off): about ``update_budget`` times the entries one
        viewer requests (one entry per bias x bias pixels at the footprint's level)."""
        gi = self.gi
        if gi.update_budget <= 0.0 or not fr.pixel_slot:
            return 0
        px = max(dr.width(ps) for ps in fr.pixel_slot)
        return max(1, int(math.ceil(gi.update_budget * px / max(float(gi.bias), 1e-3) ** 2)))

    def _budgeted(self, ctx, fr, policy):
        """(fr, policy) of the entries this frame's update takes. Under the limit
        (:meth:`update_limit`; always for one viewer at the default) every requested entry.
        Over it, the slides' fixed per-frame budget: every new entry (it has no value yet), then
        the settled ones most due, due = frame of the last update + min(updates, ``n_max``)
        (fewest samples first, then oldest; ties by slot), up to the limit. An entry not taken
        keeps its value (it holds one: every entry is updated in its first frame); once every
        entry has ``n_max`` updates the order is a round robin, so each of N entries is updated
        at least once every ceil(N / limit) frames while no new ones arrive (tested). The last
        update's frame per slot is kept beside the storage (``upd_frame``). With several
        viewers the update always reads the entries through the selection (all of them when
        under the limit), so that its kernels are the same whether or not the budget bites in
        a frame (a first frame under the limit after the warm-up would build kernels); one viewer
        under the limit reads the cache's arrays directly (the same kernels and images)."""
        gi = self.gi
        N, B = fr.n_active, self.update_limit(fr)
        cap = dr.width(gi.storage) // gi.words
        if B > 0 and (self.upd_frame is None or dr.width(self.upd_frame) < cap):
            self.upd_frame = (dr.zeros(mi.UInt32, cap) if self.upd_frame is None
                              else extend_array(self.upd_frame, 0, cap, mi.UInt32))
        gi.entries_updated = N
        if B <= 0:
            return fr, policy
        now = dr.opaque(mi.UInt32, ctx.frame)
        if N <= B and len(fr.pixel_slot) < 2:
            dr.scatter(self.upd_frame, now, fr.active)
            dr.eval(self.upd_frame)
            return fr, policy
        take = N
        if N > B:
            slot = np.array(fr.active, dtype=np.int64)
            cnt = np.array(gi.read(fr.active, gi.count_word))
            last = np.array(dr.gather(mi.UInt32, self.upd_frame, fr.active), dtype=np.int64)
            due = last + np.minimum(cnt, float(gi.n_max)).astype(np.int64)
            due[np.array(fr.is_new, dtype=bool)] = -1                  # new entries: always
            order = np.lexsort((slot, due))
            take = min(max(B, int(np.count_nonzero(due < 0))), N)
        # an aligned copy: a numpy buffer at an unaligned address is another kernel (slc.core.backend.aligned)
        sel = (mi.UInt32(aligned(np.sort(order[:take]), np.uint32)) if take < N
               else dr.arange(mi.UInt32, N))
        sub = dataclasses.replace(fr, active=dr.gather(mi.UInt32, fr.active, sel),
                                  si=dr.gather(mi.SurfaceInteraction3f, fr.si, sel),
                                  is_new=dr.gather(mi.Bool, fr.is_new, sel),
                                  seed_slot=dr.gather(mi.UInt32, fr.seed_slot, sel),
                                  keys=dr.gather(mi.UInt32, fr.keys, sel))
        policy = policy.take(sel)
        # arrays in memory: a gather from a literal (the cache's is_new / seed_slot in a frame without
        # new entries) stays a literal, and the update's kernels would get another IR (a kernel build)
        dr.make_opaque(sub.active, sub.si, sub.is_new, sub.seed_slot, sub.keys, policy.rays, policy.unsettled)
        dr.scatter(self.upd_frame, now, sub.active)
        dr.eval(self.upd_frame)      # now: a pending scatter would fuse into whichever kernel comes next
        gi.entries_updated = take
        return sub, policy

    def _finer_seeds(self, fr) -> list:
        """Per active entry, the slots of the 4 entries of the next finer level covering it
        (INVALID where absent, not mapped, new this frame, never updated, or where the entry is
        not new, has a coarser seed or is at level 0): the slides seed new entries from the
        adjacent levels, coarser and finer; the on-surface cache gives the coarser one. Asked of
        the cache's entry topology (:class:`slc.osc.protocol.EntryTopology`)."""
        gi = self.gi
        if not gi.seed_finer:
            return []
        topo = gi.cache
        new_now = dr.zeros(mi.Bool, dr.width(gi.storage) // gi.words)     # entries new this frame
        dr.scatter(new_now, True, fr.active, fr.is_new)
        isl, lvl, tx, ty = topo.entry_texels(fr.active)
        need = fr.is_new & (fr.seed_slot == INVALID) & (lvl > 0)
        finer = dr.maximum(lvl, 1) - 1
        kids = []
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            sl = topo.slot_at(isl, finer, tx * 2 + dx, ty * 2 + dy, need)
            m = need & (sl != INVALID)
            m &= ~dr.gather(mi.Bool, new_now, sl, m)
            m &= gi.read(sl, gi.count_word, m) > 0.0
            kids.append(dr.select(m, sl, INVALID))
        dr.eval(*kids)
        return kids
