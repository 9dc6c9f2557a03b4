"""The base class of cache methods: a payload in a surface cache.

:meth:`slc.methods.base.Method.render` runs the frame; this base class writes
a cache method's shared stage (:meth:`PayloadMethod.update_frame`) and a
subclass writes only the part that differs::

    class MyCache(PayloadMethod):
        name = "mine"
        params = PayloadMethod.cache_params + (Param(...), ...)
        words = 4                                     # 32-bit words per entry
        def update(self, ctx, fr, policy):            # write self.storage, return motion
        def shade(self, ctx, fr, v, gb):              # one viewer's pixels from the entries
        def shade_all(self, ctx, fr, gbuffers):       # optional: all viewers at once
        def make_cache(self):                         # optional: another surface cache

:meth:`PayloadMethod.update_frame` does, per frame: the cache's requests
(:class:`slc.osc.protocol.FrameRequests`), storage growth to the cache's
capacity, the ray policy of every active entry (from the payload's own
per-entry state: new, moving or settled; one :class:`EntryPolicy`), the
payload's ``update`` (stage "update"), the policy state's advance with the
motion the update reports; then :meth:`~slc.methods.base.Method.render` calls
``shade_all`` (stage "shade"): by default ``shade`` for every viewer; a
subclass may shade all viewers' pixels in one launch instead. A frame
without active entries shades nothing (its light is 0). Memory is the cache's own structures plus the allocated
entries times :meth:`payload_bytes`.

An entry's words are read and written through :meth:`PayloadMethod.read` /
:meth:`PayloadMethod.write` (word ``k`` of slot ``s`` is ``storage[s * words + k]``),
and where a new entry's previous value comes from (nothing, or its coarser LOD
seed) is :func:`entry_start`'s rule, the same for every payload.
"""
from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.methods.base import Method, MethodError, Param
from slc.osc.batch import PixelBatch, pixel_batch
from slc.osc.blocks import build_copy_kernels, extend_array
from slc.osc.cache import OnSurfaceCache
from slc.osc.protocol import EntryStart, FrameRequests, SurfaceCache, entry_start  # noqa: F401 (re-exported)

_UPD_MASK = 0xFFFF


@dataclass(frozen=True)
class RayPolicy:
    r"""Update rays per entry and frame, from the entry's own state.

    An entry is *new* for its first ``new_updates`` updates; after the
    payload reports motion it is *moving* for the next ``motion_updates``
    updates and gets ``moving`` rays; otherwise it is *settled* and gets
    ``settled`` rays. New and moving entries are "unsettled" (payloads may
    treat them differently, e.g. shorter memory); a new entry that moves gets
    the larger of its new and moving rays.

    A new entry at age ``a`` (updates so far) gets ``new`` rays when
    ``halve_every`` is 0 (a step: ``new`` rays, then ``settled``), else the
    age ramp ``max(settled, new >> (a // halve_every))``: rays go where the
    entry's sample count, and so the variance of its estimate, is smallest.

    ``budget`` (> 0) caps the rays of a frame at ``budget`` per active
    entry: when the entries ask for more, every entry keeps its ``settled``
    rays and the rays above them are scaled down by one common factor
    (rounded down, so the cap holds).  0: no cap."""
    new: int = 8
    new_updates: int = 8
    settled: int = 1
    moving: int = 8
    motion_updates: int = 8
    halve_every: int = 0
    budget: float = 0.0

    def new_rays(self, age: int) -> int:
        """Rays of a new entry at ``age`` (Python ints; the schedule)."""
        if age >= self.new_updates:
            return self.settled
        if self.halve_every <= 0:
            return self.new
        return max(self.settled, self.new >> (age // self.halve_every))

    def rays(self, state: mi.UInt32):
        """(rays, unsettled) per entry from its policy state word
        ``updates | motion_left << 16``."""
        upd, mot = state & _UPD_MASK, state >> 16
        young, moving = upd < self.new_updates, mot > 0
        r_new = mi.UInt32(self.new)
        if self.halve_every > 0:
            r_new = dr.maximum(mi.UInt32(self.settled), r_new >> (upd // self.halve_every))
        # a new entry that reported motion gets at least the moving rays (the ramp's
        # tail would give it 2 while its memory is cut short)
        r_new = dr.select(moving, dr.maximum(r_new, mi.UInt32(self.moving)), r_new)
        rays = dr.select(young, r_new, dr.select(moving, mi.UInt32(self.moving), mi.UInt32(self.settled)))
        if self.budget > 0 and dr.width(state) > 0:
            rays = self._capped(rays)
        return rays, young | moving

    def _capped(self, rays: mi.UInt32) -> mi.UInt32:
        """The per-frame cap (see the class docstring); no Python read-back:
        the totals stay width-1 arrays inside the kernel."""
        base = dr.minimum(rays, self.settled)
        extra = mi.Float(rays - base)
        n = dr.width(rays)
        room = dr.maximum(dr.opaque(mi.Float, self.budget * n) - mi.Float(dr.sum(base)), 0.0)
        want = dr.sum(extra)
        scale = dr.select(want > room, room / dr.maximum(want, 1.0), 1.0)
        return base + mi.UInt32(dr.floor(extra * scale))

    def samples_before(self, state: mi.UInt32) -> mi.UInt32:
        """Samples an entry has drawn before this update if it never moved
        (the sum of the schedule over its age): the index of its first sample
        in a per-entry low-discrepancy sequence (the update's stratification).
        Motion phases and the budget make it approximate, never invalid."""
        upd = state & _UPD_MASK
        total = mi.UInt32(0)
        for a in range(self.new_updates):
            total += dr.select(upd > a, mi.UInt32(self.new_rays(a)), 0)
        return total + mi.UInt32(dr.maximum(mi.Int32(upd) - self.new_updates, 0)) * self.settled

    def advance(self, state: mi.UInt32, motion: mi.Bool) -> mi.UInt32:
        """The state after one update; ``motion`` restarts the moving phase."""
        upd, mot = state & _UPD_MASK, state >> 16
        upd = dr.minimum(upd + 1, _UPD_MASK)
        mot = dr.select(motion, mi.UInt32(self.motion_updates), dr.select(mot > 0, mot - 1, 0))
        return upd | (mot << 16)


@dataclass(frozen=True)
class EntryPolicy:
    """The ray policy of this frame's active entries, built once by
    :meth:`PayloadMethod.update_frame` and handed to :meth:`PayloadMethod.update`.

    ``state``: each entry's policy state word before this update
    (``updates | motion_left << 16``; 0 for a new entry); ``rays`` and
    ``unsettled``: :meth:`RayPolicy.rays` of it; ``moving``: the entry is in a
    motion phase; ``first_sample``: :meth:`RayPolicy.samples_before` (the
    index of its first sample in a per-entry low-discrepancy sequence)."""
    policy: RayPolicy
    state: mi.UInt32
    rays: mi.UInt32
    unsettled: mi.Bool

    @classmethod
    def of(cls, policy: RayPolicy, state: mi.UInt32) -> "EntryPolicy":
        rays, unsettled = policy.rays(state)
        return cls(policy, state, rays, unsettled)

    @property
    def moving(self) -> mi.Bool:
        return (self.state >> 16) > 0

    @property
    def first_sample(self) -> mi.UInt32:
        return self.policy.samples_before(self.state)

    def take(self, idx: mi.UInt32) -> "EntryPolicy":
        """The policy of the entries ``idx`` (indices into this frame's active entries)."""
        return EntryPolicy(self.policy, dr.gather(mi.UInt32, self.state, idx),
                           dr.gather(mi.UInt32, self.rays, idx), dr.gather(mi.Bool, self.unsettled, idx))


class PayloadMethod(Method):
    """Base class of methods that keep a payload per surface-cache entry.

    Subclasses set ``words`` (32-bit words per entry; ``storage_type`` is
    ``mi.UInt32`` or ``mi.Float``), ``needs`` (cache capabilities they
    require), and implement :meth:`update` and :meth:`shade`; they may
    override :meth:`ray_policy` and :meth:`make_cache`. ``cache``
    (constructor keyword, not a setting) replaces the cache :meth:`make_cache`
    builds by any :class:`~slc.osc.protocol.SurfaceCache` (tests pass
    stand-ins); either way the cache must declare every capability in
    ``needs`` (a one-line :class:`MethodError` otherwise)."""

    cache_params = (
        Param("bias", 1.0, "cache mip bias (1: about one entry per pixel; larger: coarser)", lo=1e-3, hi=1e3),
        Param("block", 8, "cache block edge in texels", choices=(1, 2, 4, 8, 16, 32)),
        Param("evict_after", 60, "frames a block may stay unused before it is freed", lo=1),
    )
    # the settings of an entry's update rays by age and motion (:class:`RayPolicy`), for
    # payloads that follow it: :meth:`settings_ray_policy` reads them
    ray_policy_params = (
        Param("rays_new", 32, "update rays of a new entry (its first update; see halve_every)", lo=1, hi=1024),
        Param("new_updates", 20, "updates for which an entry counts as new", lo=1, hi=4096),
        Param("halve_every", 4, "a new entry's rays halve every this many updates (0: rays_new throughout)",
              lo=0, hi=4096),
        Param("rays_moving", 8, "update rays of entries after detected motion", lo=1, hi=1024),
        Param("rays_settled", 1, "update rays of settled entries", lo=1, hi=1024),
    )
    words = 1
    storage_type = mi.UInt32
    needs: frozenset = frozenset()
    reads_seeds = True       # the update starts a new entry from its LOD seed (FrameRequests.seed_slot)

    def __init__(self, scene, cache: SurfaceCache | None = None, **kw):
        super().__init__(scene, **kw)
        self._cache_arg = cache
        self.reset()

    # ------------------------------------------------------------------ hooks
    def ray_policy(self) -> RayPolicy:
        return RayPolicy()

    def settings_ray_policy(self, budget: float = 0.0) -> RayPolicy:
        """The :class:`RayPolicy` of the ``ray_policy_params`` settings, capped at ``budget``."""
        return RayPolicy(new=self.rays_new, new_updates=self.new_updates, halve_every=self.halve_every,
                         settled=self.rays_settled, moving=self.rays_moving, budget=budget)

    def make_cache(self) -> SurfaceCache:
        """The surface cache this method's entries live in, built at the first
        frame. Default: an :class:`~slc.osc.OnSurfaceCache` with the settings
        ``block``, ``bias`` and ``evict_after`` (and ``freeze`` where the method has it)."""
        return OnSurfaceCache(self.scene, block_size=self.block, bias=self.bias, evict_after=self.evict_after,
                              freeze=bool(getattr(self, "freeze", True)))

    @abstractmethod
    def update(self, ctx, fr: FrameRequests, policy: EntryPolicy) -> mi.Bool:
        """Update every active entry (``policy.rays`` samples each) in ``self.storage``;
        return the entries whose light moved (a mask over ``fr.active``)."""

    @abstractmethod
    def shade(self, ctx, fr: FrameRequests, v: int, gb) -> mi.Color3f:
        """Viewer ``v``'s pixels from the entries ``fr.pixel_slot[v]`` (no rays)."""

    def pixel_batch(self, fr: FrameRequests, gbuffers) -> PixelBatch:
        """Every viewer's pixels laid out one after another for one shading launch
        (:func:`slc.osc.batch.pixel_batch`; the layout kept on this instance while the viewers'
        sizes hold)."""
        return pixel_batch(self, fr, gbuffers)

    # ------------------------------------------------------------------ state
    def reset(self):
        self.cache = None
        self.storage = None
        self.policy_state = None
        self.requests = None      # the last frame's FrameRequests (for notebooks and tests)
        self.update_rays = None   # the rays of the last update per active entry (update_requested)
        self._last = {}

    # ------------------------------------------------------------------ entries
    def read(self, slots, word: int, active=True, n: int = 1, storage=None):
        """Word ``word`` of the entries ``slots`` (``n`` > 1: the ``n`` consecutive words from
        there, a list); 0 where not ``active``. ``storage``: another array of the same layout
        (a filtered copy) instead of ``self.storage``."""
        st = self.storage if storage is None else storage
        out = [dr.gather(self.storage_type, st, slots * self.words + (word + j), active) for j in range(n)]
        return out[0] if n == 1 else out

    def write(self, value, slots, word: int, active=True, storage=None) -> None:
        """Word ``word`` of the entries ``slots`` set to ``value`` (a list: consecutive words);
        ``storage``: another array of the same layout instead of ``self.storage``."""
        st = self.storage if storage is None else storage
        values = value if isinstance(value, (list, tuple)) else [value]
        for j, v in enumerate(values):
            dr.scatter(st, v, slots * self.words + (word + j), active)

    def use_cache(self, cache: SurfaceCache) -> None:
        """Keep this method's entries in ``cache`` (as the constructor keyword ``cache`` does);
        before the first frame only."""
        if self.cache is not None:
            raise MethodError(f"{self.name}: the cache is set before the first frame")
        self._cache_arg = cache

    def _set_up_cache(self):
        cache = self._cache_arg if self._cache_arg is not None else self.make_cache()
        missing = set(self.needs) - set(cache.capabilities)
        if missing:
            raise MethodError(f"{self.name}: the cache {type(cache).__name__} lacks {', '.join(sorted(missing))}")
        self.cache = cache
        build_copy_kernels()     # the storage may grow in any frame: its copy kernels are built here

    def _grow(self):
        """Storage and policy state sized to the cache's capacity (old contents kept)."""
        cap = max(int(self.cache.capacity), 1)
        if self.storage is not None and dr.width(self.policy_state) >= cap:
            return
        if self.storage is None:
            self.storage = dr.zeros(self.storage_type, cap * self.words)
            self.policy_state = dr.zeros(mi.UInt32, cap)
            dr.eval(self.storage, self.policy_state)
            return
        self.storage = extend_array(self.storage, 0, cap * self.words, self.storage_type)
        self.policy_state = extend_array(self.policy_state, 0, cap, mi.UInt32)

    # ------------------------------------------------------------------ frame
    def update_frame(self, ctx, gbuffers, timer) -> FrameRequests:
        """The cache's requests (:meth:`begin`), then every requested entry updated once
        (stage "update"); the requests are what shading reads."""
        fr = self.begin(ctx, gbuffers, timer)
        n_active = fr.n_active
        motion = mi.Bool()

        # ------------------------------- update every requested entry once
        with timer.stage("update") as st:
            if n_active > 0:
                motion = self.update_requested(ctx, fr)
                st.outputs(self.storage, self.policy_state)
        self._last = {"active_entries": n_active, "motion_entries": motion}
        return fr

    def can_shade(self, fr: FrameRequests) -> bool:
        """A frame without active entries has nothing to shade from (its light is 0)."""
        return fr.n_active > 0

    def begin(self, ctx, gbuffers, timer, extra=None) -> FrameRequests:
        """The cache's requests of this frame, storage grown to its capacity (the first part
        of :meth:`update_frame`); ``extra``: entries requested besides the pixels (by address,
        :meth:`slc.osc.cache.OnSurfaceCache.begin_frame`)."""
        if self.cache is None:
            self._set_up_cache()
        fr = self.requests = (self.cache.begin_frame(ctx.frame, gbuffers, timer) if extra is None else
                              self.cache.begin_frame(ctx.frame, gbuffers, timer, extra=extra))
        self._grow()
        return fr

    def update_requested(self, ctx, fr: FrameRequests) -> mi.Bool:
        """Update every active entry of ``fr`` once under the ray policy and advance the
        entries' policy state (the update stage of :meth:`update_frame`); the rays each entry took
        are kept in ``self.update_rays`` (a ``mi.UInt32`` over ``fr.active``). Returns the
        motion mask the payload's :meth:`update` reports."""
        state = dr.select(fr.is_new, 0, dr.gather(mi.UInt32, self.policy_state, fr.active))
        # evaluated: no reader of ``policy_state`` is left when the scatter below writes it
        # (an unevaluated gather would make the scatter copy the whole array first)
        dr.eval(state)
        policy = EntryPolicy.of(self.ray_policy(), state)
        motion = self.update(ctx, fr, policy)
        dr.scatter(self.policy_state, policy.policy.advance(state, motion), fr.active)
        self.update_rays = policy.rays
        return motion

    # ------------------------------------------------------------------ reports
    def payload_bytes(self) -> int:
        """Bytes per entry: the payload's words and its 4-byte policy state."""
        return 4 * self.words + 4

    def memory_bytes(self) -> int:
        if self.cache is None:
            return 0
        return int(self.cache.memory_bytes()) + int(self.cache.entries_allocated()) * self.payload_bytes()

    def stats(self) -> dict:
        out = dict(self.cache.stats()) if self.cache is not None else {}
        if self.cache is not None:
            out["payload_bytes"] = float(int(self.cache.entries_allocated()) * self.payload_bytes())
        for k, v in self._last.items():
            if isinstance(v, mi.Bool):
                v = int(dr.count(v)[0]) if dr.width(v) > 0 else 0
            out[k] = float(v or 0)
        return out

