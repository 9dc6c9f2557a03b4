"""The ``name:key=value,...`` syntax shared by method specs (``slc:max_cones=2``) and scene specs
(``hangar:lights=24``)."""
from __future__ import annotations


class SpecError(ValueError):
    """A ``key=value`` item without its ``=`` or key (one-line message)."""


def parse_spec(spec: str, what: str = "setting", error: type[ValueError] = SpecError) -> tuple[str, dict]:
    """``"slc:max_cones=2,bias=0.5"`` -> ``("slc", {"max_cones": "2", "bias": "0.5"})``; values stay
    strings (each method's or scene's own settings convert and check them). ``what`` names an item in
    the error message, ``error`` its class (``MethodError`` for a method spec, ``SceneError`` for a
    scene's)."""
    name, _, rest = spec.partition(":")
    settings = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq or not k.strip():
            raise error(f"bad {what} '{item}' in '{spec}' (expected key=value)")
        settings[k.strip()] = v.strip()
    return name.strip(), settings
