"""Checks that a loaded ``mi.Scene`` can be rendered, and :class:`SceneError`.

:class:`SceneError` is the one-line error of every scene that cannot be
loaded. :func:`check_emitters` (at least one emitter, each of a supported
type) and :func:`check_values` (finite, non-negative values of light and
reflectance) run on every :class:`slc.scene.scenes.Scene`;
:func:`slc.scene.camera.check_camera` checks its cameras.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.core.errors import SceneError

SUPPORTED_EMITTERS = ("area", "point", "spot", "envmap", "constant", "directional")


def check_emitters(mi_scene: mi.Scene, name: str) -> None:
    """Raise SceneError when the scene has no emitter or an unsupported one."""
    ems = mi_scene.emitters()
    if len(ems) == 0:
        raise SceneError(f"scene '{name}' has no emitters (direct illumination needs at least one light)")
    for e in ems:
        cls = e.class_name()
        plugin = {"AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
                  "EnvironmentMapEmitter": "envmap", "ConstantBackgroundEmitter": "constant",
                  "DirectionalEmitter": "directional"}.get(cls)
        if plugin is None:
            raise SceneError(f"scene '{name}': emitter type '{cls}' is not supported "
                             f"(supported: {', '.join(SUPPORTED_EMITTERS)})")


_SIGNED_BSDFS = ("BumpMap",)    # a height map and its scale are signed: finiteness only


def check_values(mi_scene: mi.Scene, name: str) -> None:
    """Raise :class:`SceneError` (one line) at the first non-finite or negative
    value of an emitter (radiance, intensity, irradiance, scale, environment
    map) or of a BSDF, textures included (a bitmap with a NaN texel). Positions
    and transforms are not values of light or reflectance and are not checked."""
    for e in mi_scene.emitters():
        if e.get_shape() is None:
            _check_params(e, name, f"emitter {_label(e, None)}", signed=False)
    seen = []
    for i, sh in enumerate(mi_scene.shapes()):
        if sh.is_emitter():
            _check_params(sh.emitter(), name, f"area light of shape {_label(sh, i)}", signed=False)
        b = sh.bsdf()
        if b is None or any(b is x for x in seen):
            continue
        seen.append(b)
        _check_params(b, name, f"BSDF {_label(b, None)} of shape {_label(sh, i)}",
                      signed=b.class_name() in _SIGNED_BSDFS)


def _label(obj, index) -> str:
    """'id' (Class), or #index (Class) for objects without an id."""
    ident = f"'{obj.id()}'" if obj.id() else (f"#{index}" if index is not None else "")
    return f"{ident} ({obj.class_name()})".strip()


def _check_params(obj, scene_name: str, what: str, signed: bool) -> None:
    params = mi.traverse(obj)
    for key in params.keys():
        v = params[key]
        if isinstance(v, float):
            a = np.array([v])
        elif isinstance(v, (mi.Float, mi.Color3f, mi.TensorXf)):
            flat = v.array if isinstance(v, mi.TensorXf) else v
            finite = bool(dr.all(dr.isfinite(flat), axis=None))
            if finite and (signed or bool(dr.all(flat >= 0.0, axis=None))):
                continue                                   # the usual case: no read-back of the data
            a = np.asarray(flat, dtype=np.float64).ravel()
        else:
            continue                                       # positions, transforms, integers
        bad = ~np.isfinite(a) if signed else ~(np.isfinite(a) & (a >= 0.0))
        if bad.any():
            x = float(a[np.argmax(bad)])
            kind = "NaN" if np.isnan(x) else ("Inf" if np.isinf(x) else f"negative value {x:g}")
            raise SceneError(f"scene '{scene_name}': {what} has {kind} in '{key}' "
                             f"(emitter, BSDF and texture values must be finite"
                             f"{'' if signed else ' and >= 0'})")
