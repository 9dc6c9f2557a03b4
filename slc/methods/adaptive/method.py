"""The registered ``adaptive`` method: a per-entry representation chosen from
the light each surface point receives (visibility of delta lights, cones or
SH/YCoCg), on the on-surface cache. See docs/adaptive.md."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.methods.cones.packing import words_per_entry
from slc.methods.cones.shading import shade_key, shader_for
from slc.methods.cones.update import ConeParams
from slc.core.keys import INVALID
from slc.methods import register
from slc.osc.payload import PayloadMethod, RayPolicy
from slc.methods.sh.ycocg import encoding as get_encoding
from slc.methods.adaptive import choice as ch
from slc.methods.adaptive import cones_rep, records, sh_rep, vis_frozen, visibility
from slc.methods.adaptive.choice import CONES, NONE, SH, VIS, ChoiceParams, Header
from slc.methods.adaptive.pool import Pool
from slc.methods.adaptive.env_lights import EnvLights
from slc.methods.adaptive.lanes import count_hist, means, opaque_header, subset, tally
from slc.methods.adaptive.params import PARAMS
from slc.methods.adaptive.sphere_lights import SphereLights

REPS = (VIS, CONES, SH)
RESTART_COUNT = 4
WARM_FRAMES = 2            # frames that run every kernel (see reset)


class AdaptiveCache(PayloadMethod):
    r"""A per-entry representation of the incoming direct light, chosen and
    changed over time from the entry's own samples (``adaptive``).

    Every on-surface cache entry carries a 3-word header (representation tag,
    light statistics, the slot of its record) and one record in the pool of
    its representation:

    - VISIBILITY (delta lights, sphere lights small at the entry, and the
      environment map's bright small regions, ``env_lights``): per-light
      visibility of the ``vis_lights`` lights that matter most at the entry plus
      a residual irradiance; the lights' unoccluded contribution is evaluated
      exactly at shading (a sphere light: pi L r^2/d^2 at its current centre);
    - CONES: the Surface Light Cones record (``max_cones`` cones, 286 bits for 3);
    - SH: incident radiance in SH with YCoCg chrominance compression.

    Statistics (running means over the entry's samples): the delta-light
    share of the visible energy :math:`s_\delta` and the mean resultant
    length :math:`R` of the other light's directions. Choice: VISIBILITY
    when :math:`s_\delta > 0.5`, else SH when :math:`R < 0.75`, else CONES,
    with hysteresis bands and ``switch_after`` updates in a row before a
    switch; a switch converts the old record into the new one through lobes
    (direction, half-angle, integrated radiance), keeping the energy.
    New entries start in the scene's prior (VISIBILITY when every emitter
    is a delta light or the environment's regions hold most of its power, SH
    when every emitter is at infinity, else CONES). A representation fewer
    than ``min_share`` of the entries ask for is not used.
    Ray policy as ``slc``. See docs/adaptive.md.
    """

    name = "adaptive"
    params = PARAMS + PayloadMethod.cache_params
    words, storage_type, reads_seeds = ch.HEADER_WORDS, mi.UInt32, False    # new entries start in the prior

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.cone_params = ConeParams(max_cones=self.max_cones)
        self.enc = get_encoding(self.encoding)
        self.choice = ChoiceParams(window=self.window, theta_delta=self.theta_delta, theta_r=self.theta_r,
                                   switch_after=self.switch_after,
                                   allow_sh=self.sh_when == "always" or self._has_environment(scene))
        poly, spheres = self.polygon_lights == "on", self.sphere_lights != "off"
        sph = SphereLights(scene, self.sphere_sin, spheres, poly) if spheres or poly else None
        if sph is not None and self.sphere_lights == "auto" and not sph.listable_only:   # spheres among other lights:
            sph = SphereLights(scene, self.sphere_sin, False, True) if poly else None   # not listed (see docs)
        self.sph = sph if sph is not None and sph.any else None
        env = EnvLights(scene, self.env_ratio, self.env_max_sr) if self.env_lights == "auto" else None
        self.env = env if env is not None and env.any else None
        self.prior = self._prior(scene, self.sph, self.env, self.theta_delta)
        ems = list(scene.mi_scene.emitters())
        n_list = sum(1 for i, e in enumerate(ems) if bool(int(e.flags()) & int(mi.EmitterFlags.Delta))
                     or (self.sph is not None and bool(self.sph.flag[i])))
        n_list += self.env.n if self.env is not None else 0
        self.vis_k = max(1, min(self.vis_lights, n_list))       # no more slots than listable lights
        self._vis_share = self.vis_rays if n_list <= self.vis_k else 1.0    # vis_rays: every light fits a record

    @staticmethod
    def _has_environment(scene) -> bool:
        """Whether an emitter is infinite and not a delta (an environment map or constant sky)."""
        return any(bool(int(e.flags()) & int(mi.EmitterFlags.Infinite))
                   and not bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) for e in scene.mi_scene.emitters())

    @staticmethod
    def _prior(scene, sph=None, env=None, theta_delta=0.5) -> int:
        ems = list(scene.mi_scene.emitters())
        if not ems:
            return CONES
        if env is not None and len(ems) == 1 and env.share > theta_delta:
            return VIS          # the environment alone, most of its power in listable regions
        # sphere lights count as delta lights (listed where small at the entry)
        delta = [bool(int(e.flags()) & int(mi.EmitterFlags.Delta)) or (sph is not None and bool(sph.flag[i]))
                 for i, e in enumerate(ems)]
        inf = [bool(int(e.flags()) & int(mi.EmitterFlags.Infinite)) for e in ems]
        if all(d and not i for d, i in zip(delta, inf)) or all(delta):
            return VIS
        if all(i and not d for d, i in zip(delta, inf)):
            return SH
        return CONES

    def reset(self):
        super().reset()
        self.pools = None
        # First WARM_FRAMES frames: every kernel (each representation's update and shading,
        # each conversion) runs, on masked lanes where nothing needs it, so that none is
        # first built in a later frame; from then on unused ones are skipped. Two frames:
        # the cache's first frame hands over some inputs (of the entries' interactions) in
        # another form than later frames, so a kernel run only in frame 0 is built again
        # when first needed (frame 5 on the atrium: the first SH update).
        self._warm = False
        self._frames_seen = 0
        self._counts = {}
        self._count_hist = None
        self._switches = 0
        self._tags = None

    def _make_pools(self):
        self.pools = {VIS: Pool("visibility", visibility.words(self.vis_k, self.env is not None)),
                      CONES: Pool("cones", words_per_entry(self.max_cones)),
                      SH: Pool("sh", sh_rep.words(self.enc))}

    def ray_policy(self) -> RayPolicy:
        return self.settings_ray_policy()

    # ------------------------------------------------------------------ update
    def update(self, ctx, fr, policy):
        """One function because its stages (slot hand-over, the representations' updates, the
        choice) share the frame's header fields, lane masks and pool slots; its stages are marked
        by banner comments.

        One update of the active entries ``fr.active``: reused slots give back their records and
        new ones get one, every representation updates its own entries, then the statistics
        choose each entry's representation. Returns the entries' motion mask."""
        if self.pools is None:
            self._make_pools()
        if self.sph is not None:
            self.sph.refresh()          # sphere lights' centres at the scene's current time
        # ------------------------------- the entries' headers and ray policy (opaque values)
        sc, W = self.scene.mi_scene, self.words
        N = fr.n_active
        base = fr.active * W
        hw = [dr.gather(mi.UInt32, self.storage, base + k) for k in range(W)]
        h = ch.unpack_header(hw)
        # In frame 0 every entry is new: is_new, the rays and everything computed from them
        # (tags, counts, the switch mask) would be literals that Dr.Jit folds into the kernels,
        # so the frame-0 warm-up would trace other kernels than a frame with real switches.
        # Opaque values keep the IR independent of the data (docs/adaptive.md, Cost).
        is_new, rays, unsettled = mi.Bool(fr.is_new), mi.UInt32(policy.rays), mi.Bool(policy.unsettled)
        # the entries' ray-policy state before this update (as slc: moving entries cap C and
        # leave the stratified sequence; the others continue it after the samples they drew)
        moving, first_sample = policy.moving, policy.first_sample
        dr.make_opaque(is_new, rays, unsettled, moving, first_sample)
        forced = {"visibility": VIS, "cones": CONES, "sh": SH}.get(self.force)
        start = {"visibility": VIS, "cones": CONES, "sh": SH}.get(self.start, self.prior)
        prior = forced if forced is not None else start

        # ------------------------------- reused slots give back their old records; new ones get a record
        # (all lane counts read back at once; a pool with no lane is skipped once warm)
        fresh = is_new | (h.tag == NONE)
        tag = dr.select(fresh, mi.UInt32(prior), h.tag)
        slot = dr.select(fresh, mi.UInt32(INVALID), h.slot)
        dr.eval(fresh, tag, slot)     # and after the hand-over: the same kernels in a frame without one
        rel = [is_new & (h.tag == r) for r in REPS]
        acq = [fresh & (tag == r) for r in REPS]
        n_rel_acq = tally([m & (h.slot != INVALID) for m in rel] + acq)
        for r, m, n in zip(REPS, rel, n_rel_acq[:3]):
            if n or not self._warm:
                self.pools[r].release(h.slot, m, n)
        for r, m, n in zip(REPS, acq, n_rel_acq[3:]):
            if n or not self._warm:
                slot = dr.select(m, self.pools[r].acquire(m, n), slot)
        dr.eval(slot)
        z = dr.zeros(mi.Float, N)
        h = Header(tag=tag, streak=dr.select(fresh, 0, h.streak), count=dr.select(fresh, 0, h.count),
                   e=dr.select(fresh, 0.0, h.e), slot=slot, s_delta=dr.select(fresh, 0.0, h.s_delta),
                   m=dr.select(fresh, mi.Vector3f(z, z, z), h.m))
        opaque_header(h)

        # ------------------------------- every representation updates its own entries
        ed, en, mv = dr.zeros(mi.Float, N), dr.zeros(mi.Float, N), dr.zeros(mi.Vector3f, N)
        motion, vis_motion = dr.zeros(mi.Bool, N), dr.zeros(mi.Bool, N)
        # evaluated before the loop (else fused into the first representation's kernel: one per set)
        traced = mi.UInt32(rays)        # the rays each entry traces (VISIBILITY: its share of them)
        dr.make_opaque(ed, en, mv, motion, vis_motion, traced)
        # every representation's lanes before the first update kernel: a compression waits for
        # the kernels queued before it, and the host traces the next update while one runs
        subsets = {r: subset(tag == r) for r in REPS}
        for r in REPS:
            idx, on, n_r = subsets[r]
            if n_r == 0 and self._warm:
                continue        # no lane: no kernel traced (tracing costs as much as a small frame)
            # entries with many rays side by side (as slc's update): a SIMD packet's loop runs as many
            # iterations as its largest ray count
            order = dr.argsort(dr.gather(mi.UInt32, rays, idx), descending=True)
            idx, on = dr.gather(mi.UInt32, idx, order), dr.gather(mi.Bool, on, order)
            pool = self.pools[r]
            ps = dr.gather(mi.UInt32, slot, idx)
            rec = pool.gather(ps, on)
            si = dr.gather(mi.SurfaceInteraction3f, fr.si, idx)
            key = dr.gather(mi.UInt32, fr.keys, idx)
            ry = dr.gather(mi.UInt32, rays, idx)
            fr_r = dr.gather(mi.Bool, fresh, idx)
            if r == VIS:
                ry = visibility.traced_rays(ry, dr.gather(mi.Float, h.s_delta, idx), fr_r, self.prior == VIS,
                                            self._vis_share)
                dr.scatter(traced, ry, idx, on)
                # the residual's memory is cut for moving entries only (a new entry's light did not move)
                out, mo, st = self._vis_update()(sc, rec, si, key, ry, dr.gather(mi.Bool, moving, idx), fr_r, on,
                                                 ctx.frame)
                dr.scatter(motion, mo, idx, on)
                dr.scatter(vis_motion, mo, idx, on)
            elif r == CONES:
                out, mo, st = self._cones_update()(sc, rec, si, key, ry, dr.gather(mi.Bool, unsettled, idx),
                                                   dr.gather(mi.Bool, moving, idx),
                                                   dr.gather(mi.UInt32, first_sample, idx), fr_r, on, ctx.frame)
                dr.scatter(motion, mo, idx, on)
            else:
                out, st = self._sh_update()(sc, rec, si, key, ry, fr_r, on, ctx.frame)
            dr.eval(out, st)
            del rec
            pool.scatter(out, ps, on)
            dr.scatter(ed, st[0], idx, on)
            dr.scatter(en, st[1], idx, on)
            dr.scatter(mv, st[2], idx, on)
            dr.eval(pool.data, ed, en, mv, motion, vis_motion)
        # a listed delta light went dark: the statistics restart from a short window
        h.count = dr.select(vis_motion, dr.minimum(h.count, RESTART_COUNT), h.count)

        # ------------------------------- statistics and the choice
        e_d, e_n, m_hat = means(ed, en, mv, traced)
        h = ch.update_stats(h, e_d, e_n, m_hat, self.choice)
        allowed = ctx.frame % self.switch_period == 0
        h, switch, target = ch.decide(h, self.choice, allowed=allowed)
        if forced is not None:
            switch = dr.zeros(mi.Bool, N)
        opaque_header(h)
        if allowed or not self._warm:
            if forced is None and self.min_share > 0.0:
                switch, target = self._sparse(h, switch, target, start, allowed, N)
            dr.make_opaque(switch, target)
            h = self._switch(fr, h, switch, target)
        else:
            self._switches = 0          # between switch frames: nothing to count or convert
        for k, w in enumerate(ch.pack_header(h)):
            dr.scatter(self.storage, w, base + k)
        self._tags = h.tag
        # the tags' counts are read back only in shade (a read-back here waited for this
        # update's kernels before the host could trace the policy update that follows)
        self._counts = None
        self._count_hist = count_hist([h.tag == r for r in REPS])
        dr.eval(self.storage, self._tags, self._count_hist)
        return motion

    def _sparse(self, h: Header, switch: mi.Bool, target: mi.UInt32, fallback: int, allowed: bool, N: int):
        """A representation that fewer than ``min_share`` of the active entries
        ask for (their target) is not used: those entries, and the entries in
        it, take ``fallback`` (the scene's prior) instead. Tracing a
        representation's update, shading and conversions costs as much host
        time as a small frame (skylit:env=spots: 0.4% of the entries in cones
        cost 40 ms a frame). One read-back of the demand per switch frame; the
        blocked set enters the kernels as an opaque table (same IR whatever
        is blocked)."""
        demand = tally([target == r for r in REPS])
        blocked = [False] * 4
        for r, d in zip(REPS, demand):
            blocked[r] = bool(r != fallback and d < self.min_share * N)
        self._blocked = [ch.NAMES[r] for r in REPS if blocked[r]]
        tbl = mi.Bool(blocked)
        dr.make_opaque(tbl)
        bt = dr.gather(mi.Bool, tbl, target)
        bh = dr.gather(mi.Bool, tbl, h.tag)
        target = dr.select(bt, mi.UInt32(fallback), target)
        sw = (switch | bh) & (target != h.tag) & (h.tag != NONE)
        dr.eval(sw, target)
        if not allowed:
            sw = dr.zeros(mi.Bool, N)
        return sw, target

    def _switch(self, fr, h: Header, switch: mi.Bool, target: mi.UInt32) -> Header:
        """Convert the records of switching entries (old representation ->
        lobes -> new representation), then move them between pools. One small
        kernel per (old, new) pair that occurs: the conversion of all pairs in
        one kernel was traced in every frame with a switch and cost more than
        the update itself (skylit: 400 ms a frame)."""
        sc, K, Kv = self.scene.mi_scene, self.max_cones, self.vis_k
        tag, slot = mi.UInt32(h.tag), mi.UInt32(h.slot)
        self._switches = int(dr.count(switch)[0]) if dr.width(switch) else 0
        if self._switches == 0 and self._warm:
            return h
        for src in REPS:
            for dst in REPS:
                if dst == src:
                    continue
                idx, on, n = subset(switch & (h.tag == src) & (target == dst))
                if n == 0 and self._warm:
                    continue
                old = dr.gather(mi.UInt32, h.slot, idx)
                si = dr.gather(mi.SurfaceInteraction3f, fr.si, idx)
                n_l = dr.width(idx)
                rec = self.pools[src].gather(old, on)
                # ------------------------------- old record -> lobes
                if src == VIS:
                    lobes = visibility.lobes(sc, rec, si, on, Kv, self.sph, self.env)
                elif src == CONES:
                    lobes = cones_rep.lobes(rec, on, K)
                else:
                    lobes = sh_rep.lobes(rec, on, self.enc)
                # ------------------------------- lobes -> new record
                if dst == VIS:
                    E = sh_rep.irradiance_at_normal(rec, self.enc) if src == SH else \
                        cones_rep.irradiance_at_normal(lobes)
                    new = visibility.from_irradiance(E, n_l, Kv, self.env is not None)
                elif dst == CONES:
                    new = cones_rep.from_lobes(lobes, n_l, self.cone_params)
                else:
                    new = sh_rep.from_lobes(lobes, n_l, self.enc)
                dr.eval(new)
                del rec
                s_new = self.pools[dst].acquire(on)
                self.pools[dst].scatter(new, s_new, on)
                self.pools[src].release(old, on)
                dr.scatter(tag, mi.UInt32(dst), idx, on)
                dr.scatter(slot, s_new, idx, on)
                dr.eval(tag, slot, self.pools[dst].data)
        return Header(tag=tag, streak=h.streak, count=h.count, e=h.e, slot=slot, s_delta=h.s_delta, m=h.m)

    def render(self, ctx, gbuffers, timer):
        out = super().render(ctx, gbuffers, timer)
        if self.pools is not None:
            self._frames_seen += 1
            self._warm = self._frames_seen >= WARM_FRAMES
        return out

    # ------------------------------------------------------------------ records (slc.methods.adaptive.records)
    entry_state, set_entry_state, record_bytes = records.entry_state, records.set_entry_state, records.record_bytes
    pack_records, unpack_records = records.pack_records, records.unpack_records

    # ------------------------------------------------------------------ shade
    def shade(self, ctx, fr, v, gb):
        sc, W = self.scene.mi_scene, self.words
        if self.sph is not None:
            self.sph.refresh()
        slot = mi.UInt32(fr.pixel_slot[v])
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        tag = dr.gather(mi.UInt32, self.storage, slot * W, ok) & 3
        ps = dr.gather(mi.UInt32, self.storage, slot * W + 1, ok)
        tf = dr.gather(mi.Frame3f, fr.si.sh_frame, fr.pixel_index[v], ok)
        si = gb.si
        bsdf = si.bsdf()
        m_v, m_c, m_s = ok & (tag == VIS), ok & (tag == CONES), ok & (tag == SH)
        # a representation no active entry uses is not traced (no pixel can need it)
        if self._counts is None and getattr(self, "_count_hist", None) is not None:
            self._counts = dict(zip(REPS, tally(REPS, self._count_hist)))
        used = (self._counts or {}) if self._warm else {}
        # each representation's shading is its own kernel, added into an evaluated sum (the same
        # kernels whichever representations are present)
        L = dr.zeros(mi.Color3f, gb.size)
        dr.eval(L)
        parts = []
        if used.get(VIS, 1):
            parts.append(lambda: self._vis_shading()(self.pools[VIS].gather(ps, m_v), m_v, si, sc, ctx.frame, v))
        if used.get(CONES, 1):
            parts.append(lambda: shader_for(self, self.max_cones)(
                self.pools[CONES].data, dr.select(m_c, ps, 0), m_c, si, tf, self.shade_samples,
                shade_key(ctx.frame, self.seed)))
        if used.get(SH, 1):
            parts.append(lambda: self._sh_shading()(self.pools[SH].gather(ps, m_s), m_s, si, tf))
        for part in parts:
            Lr = part()
            dr.eval(Lr)
            L = L + Lr
            dr.eval(L)
        return L

    def _frozen(self, attr: str, make):
        """The frozen function kept in ``attr``, made on first use by
        ``make(freeze)``; unfrozen in an animated scene, where every frame
        would record it again."""
        f = getattr(self, attr, None)
        if f is None:
            f = make(not bool(getattr(self.scene, "dynamic", False)))
            setattr(self, attr, f)
        return f

    def _vis_update(self) -> vis_frozen.VisUpdate:
        """The VISIBILITY update."""
        return self._frozen("_vis_up", lambda fz: vis_frozen.VisUpdate(self.vis_k, self.seed, self.sph, self.env, fz))

    def _cones_update(self) -> cones_rep.ConesUpdate:
        """The CONES update."""
        return self._frozen("_cones_up", lambda fz: cones_rep.ConesUpdate(
            self.cone_params, self.seed, self.sph, self.env, freeze=fz))

    def _sh_update(self) -> sh_rep.SHUpdate:
        """The SH update."""
        return self._frozen("_sh_up", lambda fz: sh_rep.SHUpdate(
            self.encoding, self.seed, self.sh_count, self.sph, self.env, freeze=fz))

    def _vis_shading(self) -> vis_frozen.VisShading:
        """The VISIBILITY pool's shading (glossy pixels may sample their polygon lights)."""
        make = lambda fz: vis_frozen.VisShading(self.vis_k, self.sph, self.env, fz, self.polygon_glossy,  # noqa: E731
                                                self.polygon_samples, self.seed)
        return self._frozen("_vis_shade", make)

    def _sh_shading(self) -> sh_rep.SHShading:
        """The SH pool's shading."""
        return self._frozen("_sh_shade", lambda fz: sh_rep.SHShading(
            self.encoding, self.seed, self.glossy_samples, freeze=fz))

    # ------------------------------------------------------------------ reports
    def pixel_tags(self, fr, v, gb) -> mi.UInt32:
        """Representation tag of each pixel's entry (NONE where there is none)."""
        slot = mi.UInt32(fr.pixel_slot[v])
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        return dr.select(ok, dr.gather(mi.UInt32, self.storage, slot * self.words, ok) & 3, NONE)

    def memory_bytes(self) -> int:
        if self.cache is None:
            return 0
        pools = sum(p.bytes_allocated() for p in self.pools.values()) if self.pools else 0
        return int(self.cache.memory_bytes()) + int(self.cache.entries_allocated()) * self.payload_bytes() + pools

    def stats(self) -> dict:
        out = super().stats()
        if self.pools is None:
            return out
        tags = self._tags
        n = max(dr.width(tags), 1) if tags is not None else 1
        for r in REPS:
            name = ch.NAMES[r]
            cnt = int(dr.count(tags == r)[0]) if tags is not None and dr.width(tags) else 0
            out[f"share_{name}"] = cnt / n
            out[f"bytes_{name}"] = float(self.pools[r].bytes_allocated())
            out[f"records_{name}"] = float(self.pools[r].used)
        out["switches"] = float(self._switches)
        out["payload_bytes"] = out.get("payload_bytes", 0.0) + sum(float(p.bytes_allocated())
                                                                   for p in self.pools.values())
        return out


register("adaptive", AdaptiveCache,
         help="per-entry representation chosen from the entry's light: delta-light visibility, cones or SH/YCoCg")
