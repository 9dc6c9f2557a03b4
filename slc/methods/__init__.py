"""The methods: their registry and discovery, and the contract through which the pipeline knows them.

The contract (:class:`Method`, :class:`Param`, :class:`FrameContext`,
:class:`MethodError`) lives in :mod:`slc.methods.base` and is re-exported
here: a method receives, once per frame, the G-buffers of all viewers and
returns per viewer the light it computes (``output``: ``"direct"`` light
without the emitted radiance seen directly, which
:func:`slc.scene.gbuffer.compose` adds; ``"indirect"``; or ``"full"``);
:meth:`Method.render` runs the frame and a subclass writes its shading and
the stages it shares across the viewers (see :mod:`slc.methods.cache_method` for
the cache-method base class).

Methods are found, like scenes and experiments, without editing a core file:
every ``slc/methods/<package>/method.py``, every
``methods/*.py`` beside the repository's ``scenes/`` and ``experiments/``,
and every module or file named in the environment variable ``SLC_METHODS``
(``os.pathsep``-separated) registers its methods with :func:`register` when
imported. See ``docs/adding-a-method.md``.

:func:`parse` checks a spec without a scene or making the method and returns it as data
(:class:`MethodSpec`), which another process (a render node) makes the method from.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from slc.core import backend
from slc.core.spec import parse_spec

backend.ensure()  # method modules build Mitsuba types on import

from slc.methods.base import OUTPUTS, FrameContext, Method, MethodError, Param, param_table  # noqa: E402,F401 (the contract)

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


def _entry(name: str) -> tuple[_Entry, list[int]]:
    """The registry entry whose pattern ``name`` (no settings) matches, and the pattern's groups."""
    _load_all()
    for entry in _REGISTRY.values():
        m = entry.pattern.fullmatch(name)
        if m:
            return entry, [int(g) for g in m.groups()]
    raise MethodError(f"unknown method '{name}' (available: {', '.join(sorted(_REGISTRY))}; rtN for any N)")


def create(spec: str, scene, **settings) -> Method:
    """Instantiate a method by name (``rt16``, ``rt48``, ``slc``, ``restir``...),
    optionally with settings in the name: ``slc:max_cones=2``."""
    _load_all()
    name, extra = parse_spec(spec, "method setting", MethodError)
    settings = {**extra, **settings}
    entry, args = _entry(name)
    try:
        method = entry.factory(scene, *args, **settings)
    except TypeError as e:
        raise MethodError(f"bad settings for method '{spec}': {e}") from None
    if extra:
        method.label = spec
    return method


# -----------------------------------------------------------------------------
# A method as data
# -----------------------------------------------------------------------------

@dataclass(frozen=True)
class MethodSpec:
    """A method spec checked without a scene (:func:`parse`), as data one process ships to
    another: ``spec`` as written, its ``name`` (``rt48``, ``slc``...), the ``settings`` it gives
    (converted and checked by the method's :class:`Param`, or as written for a method registered
    without a class), the method's ``output``. :meth:`create` makes the method, as
    :func:`create` makes it from ``spec``."""
    spec: str
    name: str
    settings: dict = field(default_factory=dict)
    output: str = "direct"

    @property
    def cls(self) -> type | None:
        """The method's class (the registry's; ``None`` for a factory registered without one)."""
        return _entry(self.name)[0].cls

    def create(self, scene, seed: int = 0) -> Method:
        """The method on ``scene`` with ``seed``, as :func:`create` makes it from ``spec``."""
        method = create(self.name, scene, seed=seed, **self.settings)
        if self.settings:
            method.label = self.spec
        return method


def parse(spec: str) -> MethodSpec:
    """``spec`` checked once, without a scene and without making the method: its name, its
    settings (unknown ones, each value, the method's cross-checks: the one-line
    :class:`MethodError` of making it) -> :class:`MethodSpec`."""
    name, extra = parse_spec(spec, "method setting", MethodError)
    cls = _entry(name)[0].cls
    if cls is None:
        return MethodSpec(spec, name, extra)
    values = cls.check_settings(extra)
    return MethodSpec(spec, name, {k: values[k] for k in extra}, values.get("output", cls.output))
