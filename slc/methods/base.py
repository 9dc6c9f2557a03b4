"""The method contract: :class:`Method` runs the frame, a subclass writes what differs.

In the spirit of Mitsuba 3's ``ADIntegrator.render`` (the base class runs the
frame, a subclass writes ``sample()``), :meth:`Method.render` runs one frame
for every method:

1. ``fr = update_frame(ctx, gbuffers, timer)``: the stages shared by every viewer
   (a cache's update, VPLs and their maps, reservoir passes, cells...), each
   timed under its own stage name by the subclass; what shading reads of them
   is returned (``None`` for a method without shared stages);
2. the stage ``shade_stage`` (``"shade"`` unless a method names it otherwise):
   :meth:`Method.shade_all`, by default :meth:`Method.shade` for every viewer,
   or every viewer's light 0 when :meth:`Method.can_shade` says the frame has
   nothing to shade from;
3. ``finish(ctx, fr, gbuffers, outs, timer)``: stages after shading and the
   frame's bookkeeping (statistics, state kept for the next frame).

In check mode (:mod:`slc.core.check`) every stage's outputs are checked as
the stage ends, and :meth:`Method.render` checks the images it returns (raw
and composed as the method's ``output`` is compared: no NaN/Inf, no negative
value), naming the method and the frame; a render node that runs the stages
itself checks its images with :meth:`Method.check_images`.

A method declares its settings once, as a tuple of :class:`Param`; the base
class parses and validates them (one-line :class:`MethodError` for a bad
value), sets them as attributes, reports them in :meth:`Method.settings`,
and appends a parameter table to the class docstring and to
``slc methods``' help.
"""
from __future__ import annotations

from abc import ABC
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.core import check
from slc.core.errors import MethodError  # noqa: F401 (raised by Param.parse; re-exported)
from slc.reference.references import image_of

OUTPUTS = ("direct", "indirect", "full")


@dataclass
class FrameContext:
    """What a method knows of the frame besides the G-buffers."""
    frame: int          # frame index in the sequence; methods derive their random streams from it


# -----------------------------------------------------------------------------
# Settings
# -----------------------------------------------------------------------------

@dataclass(frozen=True)
class Param:
    """One setting of a method: its name, default and one-line help, and the
    values it allows (inclusive bounds ``lo``/``hi`` for numbers, or
    ``choices``). The type is the default's (``int``, ``float``, ``str``,
    ``bool``) unless ``kind`` says otherwise; ``None`` as default means
    "derived when not given" and needs ``kind``."""
    name: str
    default: object
    help: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple | None = None
    kind: type | None = None

    @property
    def type(self) -> type:
        return self.kind or type(self.default)

    def parse(self, method: str, value):
        """``value`` (from Python or from a ``key=value`` string) converted
        and checked; a :class:`MethodError` naming the method otherwise."""
        if value is None and self.default is None:
            return None
        t = self.type
        try:
            if t is bool:
                if isinstance(value, str):
                    if value.lower() not in ("0", "1", "true", "false", "yes", "no", "on", "off"):
                        raise ValueError
                    value = value.lower() in ("1", "true", "yes", "on")
                elif isinstance(value, (int, float)) and value not in (0, 1):
                    raise ValueError
                value = bool(value)
            elif t is int:
                if isinstance(value, float) and not value.is_integer():
                    raise ValueError
                if isinstance(value, str):
                    value = float(value)
                    if not value.is_integer():
                        raise ValueError
                value = int(value)
            elif t is float:
                value = float(value)
                if value != value:
                    raise ValueError
            else:
                value = t(value)
        except (TypeError, ValueError, OverflowError):
            raise MethodError(f"{method}: {self.name} must be {_type_word(t)} (got '{value}')") from None
        if self.choices is not None and value not in self.choices:
            raise MethodError(f"{method}: {self.name} must be one of {', '.join(map(str, self.choices))} "
                              f"(got '{value}')")
        if self.lo is not None and value < self.lo or self.hi is not None and value > self.hi:
            raise MethodError(f"{method}: {self.name} must be in {self.range_text()} (got {value})")
        return value

    def range_text(self) -> str:
        if self.choices is not None:
            return "/".join(map(str, self.choices))
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        return f"[{lo}, {hi}]" if self.lo is not None or self.hi is not None else ""

    def describe(self) -> str:
        allowed = self.range_text()
        return f"{self.name}={self.default}" + (f" ({allowed})" if allowed else "") + f": {self.help}"


def _type_word(t) -> str:
    return {int: "an integer", float: "a number", bool: "0 or 1", str: "a string"}.get(t, t.__name__)


def param_table(params) -> str:
    """The Markdown/reST-friendly table appended to a method's docstring."""
    if not params:
        return ""
    lines = ["", "Parameters (``name=default``, allowed values: meaning)::", ""]
    lines += [f"    {p.describe()}" for p in params]
    return "\n".join(lines) + "\n"


class _SettingsView:
    """A method's parsed settings as its instance shows them (class attributes behind them), for
    its cross-checks without an instance (:meth:`Method.check_settings`)."""

    def __init__(self, cls: type, values: dict):
        self.__dict__.update(values)
        self._cls = cls

    def __getattr__(self, name: str):
        return getattr(self._cls, name)


# -----------------------------------------------------------------------------
# The method interface
# -----------------------------------------------------------------------------

class Method(ABC):
    """Base class of a method.

    Subclasses set ``name`` (and ``output`` when they do not return direct
    light), declare ``params`` and write :meth:`shade` (one viewer's light),
    and where they share work across viewers :meth:`update_frame` (the shared
    stages before shading), :meth:`finish` (after it) or a batched
    :meth:`shade_all`; :meth:`render` runs the frame. ``seed`` makes runs
    deterministic: the same seed and settings give the same images.
    :meth:`validate` checks settings against each other after parsing."""

    name = "method"
    output = "direct"          # one of OUTPUTS: which reference a result is compared with
    params: tuple[Param, ...] = ()
    label = None               # display name when settings differ from the defaults
    shade_stage = "shade"      # the name under which the shading stage is timed

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.output not in OUTPUTS:
            raise TypeError(f"{cls.__name__}.output must be one of {OUTPUTS}")
        if "params" in cls.__dict__ and cls.__doc__ is not None:
            cls.__doc__ = cls.__doc__.rstrip() + "\n" + param_table(cls.params)

    def __init__(self, scene, seed: int = 0, **kw):
        self.scene = scene
        self.seed = int(seed)
        for k, v in self.parse_settings(kw).items():
            setattr(self, k, v)
        self.validate()

    @classmethod
    def parse_settings(cls, kw: dict) -> dict:
        """Every setting's value (``kw``'s, else its default) converted and checked by its
        :class:`Param`; a one-line :class:`MethodError` for an unknown setting or a bad value."""
        names = {p.name for p in cls.params}
        unknown = sorted(set(kw) - names)
        if unknown:
            raise MethodError(f"{cls.name}: unknown setting{'s' if len(unknown) > 1 else ''} "
                              f"{', '.join(unknown)} (known: {', '.join(sorted(names)) or 'none'})")
        return {p.name: p.parse(cls.name, kw.get(p.name, p.default)) for p in cls.params}

    @classmethod
    def check_settings(cls, kw: dict) -> dict:
        """:meth:`parse_settings` and the cross-checks of :meth:`validate`, without a scene and
        without making the method (``validate`` reads the settings and class attributes only);
        returns the parsed settings."""
        values = cls.parse_settings(kw)
        cls.validate(_SettingsView(cls, values))
        return values

    def validate(self) -> None:
        """Cross-checks of the parsed settings (the settings and class attributes only: it also
        runs without an instance, :meth:`check_settings`); raise :class:`MethodError`."""

    def seed_for(self, frame: int, viewer: int = 0) -> int:
        return (self.seed * 1_000_003 + frame * 7919 + viewer * 104729 + 1) & 0x7FFFFFFF

    def settings(self) -> dict:
        return {p.name: getattr(self, p.name) for p in self.params}

    @classmethod
    def describe(cls) -> list[str]:
        return [p.describe() for p in cls.params]

    def reset(self) -> None:
        """Forget all state carried across frames (caches, reservoirs)."""

    # ------------------------------------------------------------------ frame
    def render(self, ctx: FrameContext, gbuffers: list, timer) -> list:
        """Light per viewer (list of mi.Color3f, one per G-buffer), as ``output`` says:
        :meth:`render_stages` under the method's and the frame's name, its images checked in
        check mode (:meth:`check_images`). Every stage's outputs are checked in check mode as
        the stage ends (:meth:`slc.core.timing.StageTimer.stage`)."""
        with check.scope(self.label or self.name, ctx.frame, gbuffers):
            outs = self.render_stages(ctx, gbuffers, timer)
        self.check_images(ctx, outs, gbuffers)
        return outs

    def render_stages(self, ctx: FrameContext, gbuffers: list, timer) -> list:
        """The frame's stages: :meth:`update_frame`, the shading stage, :meth:`finish` (module
        docstring); a method that runs another one inside its frame calls this (its images are
        checked as part of the frame's)."""
        # ------------------------------- the stages shared by every viewer
        fr = self.update_frame(ctx, gbuffers, timer)

        # ------------------------------- shade every viewer
        with timer.stage(self.shade_stage) as st:
            if self.can_shade(fr):
                outs = list(self.shade_all(ctx, fr, gbuffers))
            else:
                outs = [dr.zeros(mi.Color3f, gb.size) for gb in gbuffers]
            st.outputs(*outs)

        # ------------------------------- after shading: further stages, statistics, state
        return self.finish(ctx, fr, gbuffers, outs, timer)

    def check_images(self, ctx: FrameContext, outs: list, gbuffers: list) -> None:
        """Check mode (:mod:`slc.core.check`): every viewer's light ``outs`` of frame
        ``ctx.frame``, raw (stage "image") and composed as its ``output`` is compared (stage
        "compose"), has no NaN/Inf and no negative value (else a :class:`~slc.core.check.CheckError`
        naming the method, the frame and the pixel); nothing outside check mode."""
        if not check.enabled():
            return
        with check.scope(self.label or self.name, ctx.frame, gbuffers):
            check.images(outs, gbuffers)
            check.images([image_of(self.output, gb, d) for gb, d in zip(gbuffers, outs)], gbuffers,
                         stage="compose")

    def update_frame(self, ctx: FrameContext, gbuffers: list, timer):
        """The stages shared by every viewer before shading, each timed by ``timer.stage``;
        returns what :meth:`shade` reads of them (``fr``). Default: none (``None``)."""
        return None

    def can_shade(self, fr) -> bool:
        """Whether the frame has anything to shade from; when not, every viewer's light is 0
        and :meth:`shade_all` is not called. Default: always."""
        return True

    def shade_all(self, ctx: FrameContext, fr, gbuffers: list) -> list:
        """Every viewer's light (a list of ``mi.Color3f``, one per G-buffer). Default:
        :meth:`shade` per viewer. A subclass may batch the viewers into one launch; its images
        must be those of :meth:`shade` (random numbers keyed per viewer as there)."""
        return [self.shade(ctx, fr, v, gb) for v, gb in enumerate(gbuffers)]

    def shade(self, ctx: FrameContext, fr, v: int, gb) -> mi.Color3f:
        """Viewer ``v``'s light at the points of its G-buffer ``gb``; ``fr``: what
        :meth:`update_frame` returned this frame."""
        raise NotImplementedError(f"{type(self).__name__} writes neither shade nor shade_all")

    def finish(self, ctx: FrameContext, fr, gbuffers: list, outs: list, timer) -> list:
        """Stages after shading and the frame's bookkeeping; returns the light per viewer
        (default: ``outs``)."""
        return outs

    def memory_bytes(self) -> int:
        """Bytes of state the method keeps (caches, reservoirs, buffers)."""
        return 0

    def stats(self) -> dict:
        """Extra per-frame figures (e.g. cache fill ratio), merged into rows."""
        return {}
