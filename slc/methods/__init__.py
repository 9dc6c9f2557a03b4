"""The one small interface through which the pipeline knows methods.

A method receives, once per frame, the G-buffers of all viewers and returns
per viewer the light it computes (``output``: ``"direct"`` light without the
emitted radiance seen directly, which :func:`slc.scene.gbuffer.compose` adds;
``"indirect"``; or ``"full"``). Cache methods share work across the viewers
of a frame (see :mod:`slc.osc.payload` for the cache-method base class);
per-viewer methods loop over them.

A method declares its settings once, as a tuple of :class:`Param`; the base
class parses and validates them (one-line :class:`MethodError` for a bad
value), sets them as attributes, reports them in :meth:`Method.settings`,
and appends a parameter table to the class docstring and to
``slc methods``' help.

Methods are found, like scenes and experiments, without editing a core file:
every ``slc/methods/<package>/method.py``, every
``methods/*.py`` beside the repository's ``scenes/`` and ``experiments/``,
and every module or file named in the environment variable ``SLC_METHODS``
(``os.pathsep``-separated) registers its methods with :func:`register` when
imported. See ``docs/adding-a-method.md``.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from slc.core import backend
from slc.core.errors import MethodError
from slc.core.spec import parse_spec

backend.ensure()  # method modules build Mitsuba types on import

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


# -----------------------------------------------------------------------------
# The method interface
# -----------------------------------------------------------------------------

class Method(ABC):
    """Base class of a method.

    Subclasses set ``name`` (and ``output`` when they do not return direct
    light), declare ``params`` and implement :meth:`render`. ``seed`` makes
    runs deterministic: the same seed and settings give the same images.
    :meth:`validate` checks settings against each other after parsing."""

    name = "method"
    output = "direct"          # one of OUTPUTS: which reference a result is compared with
    params: tuple[Param, ...] = ()
    label = None               # display name when settings differ from the defaults

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.output not in OUTPUTS:
            raise TypeError(f"{cls.__name__}.output must be one of {OUTPUTS}")
        if "params" in cls.__dict__ and cls.__doc__ is not None:
            cls.__doc__ = cls.__doc__.rstrip() + "\n" + param_table(cls.params)

    def __init__(self, scene, seed: int = 0, **kw):
        self.scene = scene
        self.seed = int(seed)
        names = {p.name for p in self.params}
        unknown = sorted(set(kw) - names)
        if unknown:
            raise MethodError(f"{self.name}: unknown setting{'s' if len(unknown) > 1 else ''} "
                              f"{', '.join(unknown)} (known: {', '.join(sorted(names)) or 'none'})")
        for p in self.params:
            setattr(self, p.name, p.parse(self.name, kw.get(p.name, p.default)))
        self.validate()

    def validate(self) -> None:
        """Cross-checks of the parsed settings; raise :class:`MethodError`."""

    def seed_for(self, frame: int, viewer: int = 0) -> int:
        return (self.seed * 1_000_003 + frame * 7919 + viewer * 104729 + 1) & 0x7FFFFFFF

    def settings(self) -> dict:
        return {p.name: getattr(self, p.name) for p in self.params}

    @classmethod
    def describe(cls) -> list[str]:
        return [p.describe() for p in cls.params]

    def reset(self) -> None:
        """Forget all state carried across frames (caches, reservoirs)."""

    @abstractmethod
    def render(self, ctx: FrameContext, gbuffers: list, timer) -> list:
        """Light per viewer (list of mi.Color3f, one per G-buffer), as ``output`` says."""

    def memory_bytes(self) -> int:
        """Bytes of state the method keeps (caches, reservoirs, buffers)."""
        return 0

    def stats(self) -> dict:
        """Extra per-frame figures (e.g. cache fill ratio), merged into rows."""
        return {}


# -----------------------------------------------------------------------------
# Registry and discovery
# -----------------------------------------------------------------------------

@dataclass
class _Entry:
    factory: Callable
    pattern: re.Pattern
    help: str
    cls: type | None


_REGISTRY: dict[str, _Entry] = {}
_LOADED = False
PACKAGE_DIR = Path(__file__).resolve().parent
USER_METHODS_DIR = PACKAGE_DIR.parents[1] / "methods"


def register(name: str, factory: Callable, pattern: str | None = None, help: str = "",
             cls: type | None = None) -> None:
    """Register ``factory(scene, *groups, **settings) -> Method`` under ``name``.

    ``factory`` may be a :class:`Method` subclass itself. ``pattern`` (a
    regex) lets a family of names map to one factory, its groups passed as
    positional integers (``rt(\\d+)`` -> ``rt48``). ``cls`` (default: the
    factory when it is a class) gives ``slc methods`` the parameter list."""
    if cls is None and isinstance(factory, type):
        cls = factory
    _REGISTRY[name] = _Entry(factory, re.compile(pattern or re.escape(name)), help, cls)


def method_modules() -> list[str]:
    """Import names of the built-in method modules, found by convention."""
    return [f"slc.methods.{p.parent.name}.method" for p in sorted(PACKAGE_DIR.glob("*/method.py"))]


def _import_file(path: Path):
    spec = importlib.util.spec_from_file_location(f"slc_method_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _load_all():
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for m in method_modules():
        importlib.import_module(m)
    if USER_METHODS_DIR.is_dir():
        for p in sorted(USER_METHODS_DIR.glob("*.py")):
            if not p.stem.startswith("_"):
                _import_file(p)
    for item in filter(None, os.environ.get("SLC_METHODS", "").split(os.pathsep)):
        if item.endswith(".py"):
            if not Path(item).is_file():
                raise MethodError(f"SLC_METHODS: method file '{item}' not found")
            _import_file(Path(item))
        else:
            try:
                importlib.import_module(item)
            except ModuleNotFoundError as e:
                raise MethodError(f"SLC_METHODS: method module '{item}' not found ({e})") from None


def known(name: str) -> bool:
    """Whether ``name`` (without settings) names a registered method."""
    _load_all()
    return any(e.pattern.fullmatch(name) for e in _REGISTRY.values())


def available() -> dict[str, str]:
    """Name -> help, with the parameter list of methods that declare one."""
    _load_all()
    out = {}
    for k, e in _REGISTRY.items():
        text = e.help
        if e.cls is not None and e.cls.params:
            text += "\n" + "\n".join("    " + d for d in e.cls.describe())
        out[k] = text
    return out


def create(spec: str, scene, **settings) -> Method:
    """Instantiate a method by name (``rt16``, ``rt48``, ``slc``, ``restir``...),
    optionally with settings in the name: ``slc:max_cones=2``."""
    _load_all()
    name, extra = parse_spec(spec, "method setting", MethodError)
    settings = {**extra, **settings}
    for entry in _REGISTRY.values():
        m = entry.pattern.fullmatch(name)
        if m:
            args = [int(g) for g in m.groups()]
            try:
                method = entry.factory(scene, *args, **settings)
            except TypeError as e:
                raise MethodError(f"bad settings for method '{spec}': {e}") from None
            if extra:
                method.label = spec
            return method
    raise MethodError(f"unknown method '{name}' (available: {', '.join(sorted(_REGISTRY))}; rtN for any N)")
