"""The registered ``adaptive`` method: a per-entry representation chosen from
the light each surface point receives (visibility of delta lights, cones or
SH/YCoCg), on the on-surface cache. See docs/adaptive.md."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from slc.lib.cones.update import ConeParams
from slc.core.keys import INVALID
from slc.methods import register
from slc.methods.cache_method import PayloadMethod, RayPolicy
from slc.lib.sh.ycocg import encoding as get_encoding
from slc.methods.adaptive import choice as ch
from slc.methods.adaptive.choice import CONES, NONE, SH, TAG_OF, VIS, ChoiceParams, Header, glossy_entries
from slc.methods.adaptive.cones_rep import ConesRep
from slc.lib.lights.env_lights import EnvLights
from slc.methods.adaptive.lanes import count_hist, means, opaque_header, subset, tally
from slc.methods.adaptive.params import PARAMS
from slc.methods.adaptive.representation import Entries, Pixels
from slc.methods.adaptive.sh_rep import SHRep
from slc.lib.lights.sphere_lights import SphereLights
from slc.methods.adaptive.visibility import VisibilityRep
from slc.scene.bsdf_table import front_side_only

REPRESENTATIONS = (VisibilityRep, ConesRep, SHRep)     # in the order of their tags (slc.methods.adaptive.choice)
REPS = tuple(r.tag for r in REPRESENTATIONS)
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
    switch, carried out in every ``switch_period``-th frame (in every frame of
    the cache's first ``switch_early``); a switch converts the old record into
    the new one through lobes (direction, half-angle, integrated radiance),
    keeping the energy. New entries start in the representation that held the
    most active entries at the last update (``start=majority``), in the
    scene's prior before (VISIBILITY when every emitter is a delta light or
    the environment's regions hold most of its power, SH when every emitter
    is at infinity, else CONES). A representation fewer than ``min_share`` of
    the entries ask for is not used.
    Ray policy as ``slc``. See docs/adaptive.md.
    """

    name = "adaptive"
    params = PARAMS + PayloadMethod.cache_params
    words, storage_type, reads_seeds = ch.HEADER_WORDS, mi.UInt32, False    # new entries start in the prior

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        # the CONES pool is slc's record with slc's update (samples below the horizon dropped and
        # cosine-weighted where every BSDF reflects on its front side only)
        self._back = not front_side_only(scene)     # two-sided BSDFs: VISIBILITY keeps a residual behind
        self.cone_params = ConeParams(max_cones=self.max_cones, front_only=not self._back)
        self.enc = get_encoding(self.encoding)
        self.choice = ChoiceParams(window=self.window, theta_delta=self.theta_delta, theta_glossy=self.theta_glossy,
                                   theta_r=self.theta_r,
                                   switch_after=self.switch_after,
                                   allow_sh=self.sh_when == "always" or (self.sh_when == "environment"
                                                                         and self._has_environment(scene)))
        poly, spheres = self.polygon_lights == "on", self.sphere_lights != "off"
        sph = SphereLights(scene, self.sphere_sin, spheres, poly) if spheres or poly else None
        if sph is not None and self.sphere_lights == "auto" and not sph.listable_only:   # spheres among other lights:
            sph = SphereLights(scene, self.sphere_sin, False, True) if poly else None   # not listed (see docs)
        self.sph = sph if sph is not None and sph.any else None
        env = EnvLights(scene, self.env_ratio, self.env_max_sr, sky_light=self.env_sky == "auto") \
            if self.env_lights == "auto" else None
        self.env = env if env is not None and env.any else None
        self.prior = self._prior(scene, self.sph, self.env, self.theta_delta)
        if self.prior == SH and not self.choice.allow_sh:
            self.prior = CONES
        ems = list(scene.mi_scene.emitters())
        n_list = sum(1 for i, e in enumerate(ems) if bool(int(e.flags()) & int(mi.EmitterFlags.Delta))
                     or (self.sph is not None and bool(self.sph.flag[i])))
        n_list += self.env.n if self.env is not None else 0
        self.vis_k = max(1, min(self.vis_lights, n_list))       # no more slots than listable lights
        # vis_rays where every light fits a record, but not under a sky: a wide light's visible
        # fraction needs every ray (with half of them the sky-lit entries of skylit had 1.35x the
        # per-pixel error of slc's cones)
        sky = self.env is not None and self.env.has_sky
        self._vis_share = self.vis_rays if n_list <= self.vis_k and not sky else 1.0

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
        if env is not None and len(ems) == 1 and env.share + env.sky_share > theta_delta:
            return VIS          # the environment alone, most of its power in listable regions and the sky
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
        self.reps = None        # the representations (and their pools), made at the first update
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

    @property
    def pools(self) -> dict | None:
        """{tag: pool} of the representations (None before the first update)."""
        return None if self.reps is None else {r.tag: r.pool for r in self.reps}

    def rep(self, tag: int):
        """The representation of ``tag`` (the representations and their pools are made on first use)."""
        if self.reps is None:
            self.reps = [R(self) for R in REPRESENTATIONS]
        return self.reps[REPS.index(tag)]

    def ray_policy(self) -> RayPolicy:
        return self.settings_ray_policy()

    # ------------------------------------------------------------------ update
    def update(self, ctx, fr, policy):
        """One update of the active entries ``fr.active``: reused slots give back their records
        and new ones get one (:meth:`_hand_over`), every representation updates its own entries
        (:meth:`_update_representations`), then the statistics choose each entry's
        representation and the entries that switch are converted (:meth:`_choose`). Returns
        the entries' motion mask."""
        self.rep(VIS)                   # the representations, on first use
        if self.sph is not None:
            self.sph.refresh()          # sphere lights' centres at the scene's current time
        # ------------------------------- the entries' headers and ray policy (opaque values)
        W = self.words
        base = fr.active * W
        h = ch.unpack_header([dr.gather(mi.UInt32, self.storage, base + k) for k in range(W)])
        # In frame 0 every entry is new: is_new, the rays and everything computed from them
        # (tags, counts, the switch mask) would be literals that Dr.Jit folds into the kernels,
        # so the frame-0 warm-up would trace other kernels than a frame with real switches.
        # Opaque values keep the IR independent of the data (docs/adaptive.md, Cost).
        is_new, rays, unsettled = mi.Bool(fr.is_new), mi.UInt32(policy.rays), mi.Bool(policy.unsettled)
        # the entries' ray-policy state before this update (as slc: moving entries cap C and
        # leave the stratified sequence; the others continue it after the samples they drew)
        moving, first_sample = policy.moving, policy.first_sample
        dr.make_opaque(is_new, rays, unsettled, moving, first_sample)
        glossy = glossy_entries(self.scene, fr.si, self.env)    # their own start and threshold
        h, fresh = self._hand_over(h, is_new, fr.n_active, glossy)
        motion, vis_motion, stats = self._update_representations(ctx, fr, h, fresh, rays, unsettled, moving,
                                                                 first_sample)
        # a listed delta light went dark: the statistics restart from a short window
        h.count = dr.select(vis_motion, dr.minimum(h.count, RESTART_COUNT), h.count)
        tag_before = h.tag
        h = self._choose(ctx, fr, h, stats, glossy)
        # an entry that switched learns its new record with the rays of a moving entry (its record
        # converted from another representation holds a rough estimate, which the residual's
        # count would otherwise keep for hundreds of samples)
        motion = motion | (h.tag != tag_before)
        for k, w in enumerate(ch.pack_header(h)):
            dr.scatter(self.storage, w, base + k)
        self._tags = h.tag
        # the tags' counts are read back only in shade (here the read-back waited for this update)
        self._counts = None
        self._count_hist = count_hist([h.tag == r for r in REPS])
        dr.eval(self.storage, self._tags, self._count_hist)
        return motion

    def _representation_of_new(self) -> int:
        """``force``, else ``start``: a fixed representation, the scene's prior, or (``majority``)
        the representation that held the most active entries at the last update (the prior in
        the first frame and on a tie)."""
        forced = TAG_OF.get(self.force)
        if forced is not None or self.start != "majority":
            return forced or TAG_OF.get(self.start, self.prior)
        counts = self._last_counts()
        best = max(counts.values(), default=0)
        if best == 0 or counts.get(self.prior, 0) == best:
            return self.prior
        return max(counts, key=counts.get)

    def _last_counts(self) -> dict:
        """{tag: active entries} of the last update ({} before the first), read back once."""
        if self._counts is None and self._count_hist is not None:
            self._counts = dict(zip(REPS, tally(REPS, self._count_hist)))
        return self._counts or {}

    def _hand_over(self, h: Header, is_new: mi.Bool, N: int, glossy):
        """Reused slots give back their old records; new ones get a record of the representation
        new entries start in (lane counts read back at once; a pool with no lane is skipped once
        warm); with ``start=majority`` a ``glossy`` one (:func:`glossy_entries`) starts in cones
        where the majority is VISIBILITY but the prior is not. Returns (header, fresh: a new record)."""
        fresh = is_new | (h.tag == NONE)
        # opaque: the representation of new entries may change between frames (start=majority)
        start = dr.opaque(mi.UInt32, self._representation_of_new())
        if self.start == "majority" and self.force == "auto" and self.prior != VIS and glossy is not None:
            start = dr.select((start == VIS) & glossy, mi.UInt32(CONES), start)
        tag = dr.select(fresh, start, h.tag)
        slot = dr.select(fresh, mi.UInt32(INVALID), h.slot)
        dr.eval(fresh, tag, slot)     # and after the hand-over: the same kernels in a frame without one
        rel = [is_new & (h.tag == r.tag) for r in self.reps]
        acq = [fresh & (tag == r.tag) for r in self.reps]
        n_rel_acq = tally([m & (h.slot != INVALID) for m in rel] + acq)
        n_reps = len(self.reps)
        for r, m, n in zip(self.reps, rel, n_rel_acq[:n_reps]):
            if n or not self._warm:
                r.pool.release(h.slot, m, n)
        for r, m, n in zip(self.reps, acq, n_rel_acq[n_reps:]):
            if n or not self._warm:
                slot = dr.select(m, r.pool.acquire(m, n), slot)
        dr.eval(slot)
        z = dr.zeros(mi.Float, N)
        h = Header(tag=tag, streak=dr.select(fresh, 0, h.streak), count=dr.select(fresh, 0, h.count),
                   e=dr.select(fresh, 0.0, h.e), slot=slot, s_delta=dr.select(fresh, 0.0, h.s_delta),
                   m=dr.select(fresh, mi.Vector3f(z, z, z), h.m))
        opaque_header(h)
        return h, fresh

    def _update_representations(self, ctx, fr, h: Header, fresh, rays, unsettled, moving, first_sample):
        """Every representation updates its own entries (:class:`~.representation.Entries`);
        returns (motion, the motion that restarts the statistics, (e_delta, e_nd, m) means)."""
        N = fr.n_active
        ed, en, mv = dr.zeros(mi.Float, N), dr.zeros(mi.Float, N), dr.zeros(mi.Vector3f, N)
        motion, vis_motion = dr.zeros(mi.Bool, N), dr.zeros(mi.Bool, N)
        # evaluated before the loop (else fused into the first representation's kernel: one per set)
        traced = mi.UInt32(rays)        # the rays each entry traces (VISIBILITY: its share of them)
        dr.make_opaque(ed, en, mv, motion, vis_motion, traced)
        # every representation's lanes before the first update kernel: a compression waits for
        # the kernels queued before it, and the host traces the next update while one runs
        subsets = {r.tag: subset(h.tag == r.tag) for r in self.reps}
        for rep in self.reps:
            idx, on, n_r = subsets[rep.tag]
            if n_r == 0 and self._warm:
                continue        # no lane: no kernel traced (tracing costs as much as a small frame)
            # entries with many rays side by side (a SIMD packet's loop runs its largest ray count)
            order = dr.argsort(dr.gather(mi.UInt32, rays, idx), descending=True)
            idx, on = dr.gather(mi.UInt32, idx, order), dr.gather(mi.Bool, on, order)
            ps = dr.gather(mi.UInt32, h.slot, idx)
            e = Entries(rec=rep.pool.gather(ps, on), si=dr.gather(mi.SurfaceInteraction3f, fr.si, idx),
                        key=dr.gather(mi.UInt32, fr.keys, idx), rays=dr.gather(mi.UInt32, rays, idx),
                        moving=dr.gather(mi.Bool, moving, idx), unsettled=dr.gather(mi.Bool, unsettled, idx),
                        first_sample=dr.gather(mi.UInt32, first_sample, idx), fresh=dr.gather(mi.Bool, fresh, idx),
                        s_delta=dr.gather(mi.Float, h.s_delta, idx),
                        texel=dr.gather(mi.Float, fr.texel_size, idx) if fr.texel_size is not None else None,
                        on=on, frame=ctx.frame)
            up = rep.update(e)
            if up.rays is not None:
                dr.scatter(traced, up.rays, idx, on)
            if up.motion is not None:
                dr.scatter(motion, up.motion, idx, on)
                if rep.restarts_stats:
                    dr.scatter(vis_motion, up.motion, idx, on)
            dr.eval(up.words, up.stats)
            del e
            rep.pool.scatter(up.words, ps, on)
            for total, x in ((ed, up.stats.ed), (en, up.stats.en), (mv, up.stats.m)):
                dr.scatter(total, x, idx, on)
            dr.eval(rep.pool.data, ed, en, mv, motion, vis_motion)
        return motion, vis_motion, means(ed, en, mv, traced)

    # ------------------------------------------------------------------ the choice
    def _choose(self, ctx, fr, h: Header, stats, glossy=None) -> Header:
        """The statistics' running means, the choice rule (``glossy``: the glossy entries, their
        own threshold), and the switches it asks for (in every frame of the cache's first
        ``switch_early``, then in every ``switch_period``-th)."""
        N = fr.n_active
        forced = self.force != "auto"
        h = ch.update_stats(h, *stats, self.choice)
        allowed = self._frames_seen < self.switch_early or ctx.frame % self.switch_period == 0
        h, switch, target = ch.decide(h, self.choice, allowed=allowed, glossy=glossy)
        if forced:
            switch = dr.zeros(mi.Bool, N)
        opaque_header(h)
        if allowed or not self._warm:
            if not forced and self.min_share > 0.0:
                start = TAG_OF.get(self.start, self.prior)
                switch, target = self._sparse(h, switch, target, start, allowed, N)
            dr.make_opaque(switch, target)
            h = self._switch(fr, h, switch, target)
        else:
            self._switches = 0          # between switch frames: nothing to count or convert
        return h

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
        lobes -> new representation, :class:`~.representation.Representation`), then move them
        between pools. One small kernel per (old, new) pair that occurs: the conversion of all
        pairs in one kernel was traced in every frame with a switch and cost more than the
        update itself (skylit: 400 ms a frame)."""
        tag, slot = mi.UInt32(h.tag), mi.UInt32(h.slot)
        self._switches = int(dr.count(switch)[0]) if dr.width(switch) else 0
        if self._switches == 0 and self._warm:
            return h
        for src in self.reps:
            for dst in self.reps:
                if dst is src:
                    continue
                idx, on, n = subset(switch & (h.tag == src.tag) & (target == dst.tag))
                if n == 0 and self._warm:
                    continue
                old = dr.gather(mi.UInt32, h.slot, idx)
                si = dr.gather(mi.SurfaceInteraction3f, fr.si, idx)
                rec = src.pool.gather(old, on)
                new = dst.convert(src, rec, src.lobes(rec, si, on), dr.width(idx))
                dr.eval(new)
                del rec
                s_new = dst.pool.acquire(on)
                dst.pool.scatter(new, s_new, on)
                src.pool.release(old, on)
                dr.scatter(tag, mi.UInt32(dst.tag), idx, on)
                dr.scatter(slot, s_new, idx, on)
                dr.eval(tag, slot, dst.pool.data)
        return Header(tag=tag, streak=h.streak, count=h.count, e=h.e, slot=slot, s_delta=h.s_delta, m=h.m)

    def finish(self, ctx, fr, gbuffers, out, timer):
        if self.reps is not None:
            self._frames_seen += 1
            self._warm = self._frames_seen >= WARM_FRAMES
        return out

    # ------------------------------------------------------------------ shade
    def shade(self, ctx, fr, v, gb):
        slot = mi.UInt32(fr.pixel_slot[v])
        return self._shade_pixels(ctx, fr, slot, mi.Bool(gb.valid) & (slot != INVALID), gb.si,
                                  mi.UInt32(fr.pixel_index[v]), v)

    def shade_all(self, ctx, fr, gbuffers):
        """All viewers' pixels: one launch per representation over every viewer's pixels one
        after another (:meth:`~slc.methods.cache_method.PayloadMethod.pixel_batch`), split per viewer;
        each pixel keeps the random numbers it has per viewer (its index within its viewer, its
        viewer's streams), so the images are the per-viewer ones bit for bit. One viewer:
        :meth:`shade`."""
        if len(gbuffers) < 2:
            return super().shade_all(ctx, fr, gbuffers)
        px = self.pixel_batch(fr, gbuffers)
        return px.split(self._shade_pixels(ctx, fr, px.slot, px.active, px.si, px.index, px.viewer, px.pid,
                                           len(gbuffers)))

    def _shade_pixels(self, ctx, fr, slot, ok, si, index, viewer, pid=None, n_viewers: int = 1):
        """L_o at the pixels ``si`` (entries ``slot``, ``ok`` those with one; ``index`` their
        entries' indices into the frame's active entries), from every representation in use;
        ``viewer``, ``pid`` and ``n_viewers`` as :class:`~.representation.Pixels`."""
        W = self.words
        if self.sph is not None:
            self.sph.refresh()
        tag = dr.gather(mi.UInt32, self.storage, slot * W, ok) & 3
        ps = dr.gather(mi.UInt32, self.storage, slot * W + 1, ok)
        tf = dr.gather(mi.Frame3f, fr.si.sh_frame, index, ok)
        # a representation no active entry uses is not traced (no pixel can need it)
        used = self._last_counts() if self._warm else {}
        # each representation's shading is its own kernel, added into an evaluated sum (the same
        # kernels whichever representations are present)
        L = dr.zeros(mi.Color3f, dr.width(slot))
        dr.eval(L)
        for rep in self.reps:
            if used.get(rep.tag, 1):
                Lr = rep.shade(Pixels(slot=ps, active=ok & (tag == rep.tag), si=si, tf=tf, frame=ctx.frame,
                                      viewer=viewer, pid=pid, n_viewers=n_viewers))
                dr.eval(Lr)
                L = L + Lr
                dr.eval(L)
        return L

    # ------------------------------------------------------------------ reports
    def pixel_tags(self, fr, v, gb) -> mi.UInt32:
        """Representation tag of each pixel's entry (NONE where there is none)."""
        slot = mi.UInt32(fr.pixel_slot[v])
        ok = mi.Bool(gb.valid) & (slot != INVALID)
        return dr.select(ok, dr.gather(mi.UInt32, self.storage, slot * self.words, ok) & 3, NONE)

    def memory_bytes(self) -> int:
        if self.cache is None:
            return 0
        pools = sum(r.pool.bytes_allocated() for r in self.reps) if self.reps else 0
        return int(self.cache.memory_bytes()) + int(self.cache.entries_allocated()) * self.payload_bytes() + pools

    def stats(self) -> dict:
        out = super().stats()
        if self.reps is None:
            return out
        tags = self._tags
        n = max(dr.width(tags), 1) if tags is not None else 1
        for r in self.reps:
            cnt = int(dr.count(tags == r.tag)[0]) if tags is not None and dr.width(tags) else 0
            out[f"share_{r.name}"] = cnt / n
            out[f"bytes_{r.name}"] = float(r.pool.bytes_allocated())
            out[f"records_{r.name}"] = float(r.pool.used)
        out["switches"] = float(self._switches)
        out["payload_bytes"] = out.get("payload_bytes", 0.0) + sum(float(r.pool.bytes_allocated()) for r in self.reps)
        return out


register("adaptive", AdaptiveCache,
         help="per-entry representation chosen from the entry's light: delta-light visibility, cones or SH/YCoCg")
