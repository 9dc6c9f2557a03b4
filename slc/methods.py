"""The one small interface through which the pipeline knows methods.

A method receives, once per frame, the G-buffers of all viewers and returns
their direct illumination (without the emitted radiance seen directly, which
:func:`slc.gbuffer.compose` adds). Cache methods share work across the
viewers of a frame; per-viewer methods loop over them.

To add a method: subclass :class:`Method`, implement :meth:`Method.render`
and :meth:`Method.memory_bytes`, and :func:`register` a factory under a name
(see ``docs/adding-a-method.md``).
"""
from __future__ import annotations

import importlib
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable


class MethodError(ValueError):
    """Unknown method name or bad method settings (one-line message)."""


@dataclass
class FrameContext:
    frame: int          # frame index in the sequence
    time: float         # scene time in seconds
    seed: int = 0       # run seed; methods derive per-frame/per-viewer streams from it


class Method(ABC):
    """Base class of a direct-illumination method.

    Subclasses set ``name`` and implement :meth:`render`. ``seed`` makes runs
    deterministic: the same seed and settings give the same images."""

    name = "method"
    label = None    # display name when settings differ from the defaults
    shared = False
    output = "direct"  # what render() returns; "indirect" methods cannot join direct-light experiments  # True when one state serves all viewers (caches)

    def __init__(self, scene, seed: int = 0, **kw):
        if kw:
            raise MethodError(f"{type(self).__name__}: unknown settings {', '.join(sorted(kw))}")
        self.scene = scene
        self.seed = int(seed)

    def seed_for(self, frame: int, viewer: int = 0) -> int:
        return (self.seed * 1_000_003 + frame * 7919 + viewer * 104729 + 1) & 0x7FFFFFFF

    def settings(self) -> dict:
        return {}

    def reset(self) -> None:
        """Forget all state carried across frames (caches, reservoirs)."""

    @abstractmethod
    def render(self, ctx: FrameContext, gbuffers: list, timer) -> list:
        """Direct illumination per viewer (list of mi.Color3f, one per G-buffer)."""

    def memory_bytes(self) -> int:
        """Bytes of state the method keeps (caches, reservoirs, buffers)."""
        return 0

    def stats(self) -> dict:
        """Extra per-frame figures (e.g. cache fill ratio), merged into rows."""
        return {}


@dataclass
class _Entry:
    factory: Callable
    pattern: re.Pattern
    help: str


_REGISTRY: dict[str, _Entry] = {}
# Modules that register methods when imported (kept lazy: importing slc stays fast).
METHOD_MODULES = ["slc.baselines.rt", "slc.baselines.restir", "slc.cones.method", "slc.sh.method",
                  "slc.megaviews"]


def register(name: str, factory: Callable, pattern: str | None = None, help: str = "") -> None:
    """Register ``factory(scene, **settings) -> Method`` under ``name``.
    ``pattern`` (a regex) lets a family of names map to one factory, its
    groups passed as positional integers (``rt(\\d+)`` -> ``rt48``)."""
    _REGISTRY[name] = _Entry(factory, re.compile(pattern or re.escape(name)), help)


def _load_all():
    for m in METHOD_MODULES:
        try:
            importlib.import_module(m)
        except ModuleNotFoundError as e:
            if e.name is None or not m.startswith(e.name):
                raise


def known(name: str) -> bool:
    """Whether ``name`` (without settings) names a registered method."""
    _load_all()
    return any(e.pattern.fullmatch(name) for e in _REGISTRY.values())


def available() -> dict[str, str]:
    _load_all()
    return {k: e.help for k, e in _REGISTRY.items()}


def parse_spec(spec: str) -> tuple[str, dict]:
    """``"slc:max_cones=2,bias=0.5"`` -> ``("slc", {"max_cones": 2, "bias": 0.5})``."""
    name, _, rest = spec.partition(":")
    settings = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq:
            raise MethodError(f"bad method setting '{item}' in '{spec}' (expected key=value)")
        for conv in (int, float):
            try:
                v = conv(v)
                break
            except ValueError:
                pass
        settings[k.strip()] = v
    return name.strip(), settings


def create(spec: str, scene, **settings) -> Method:
    """Instantiate a method by name (``rt16``, ``rt48``, ``slc``, ``restir``...),
    optionally with settings in the name: ``slc:max_cones=2``."""
    _load_all()
    name, extra = parse_spec(spec)
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
