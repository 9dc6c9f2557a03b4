"""MegaViews: many-view rendering by concurrent scene-view hierarchy traversal.

Modules: :mod:`.octree` (sparse point octrees), :mod:`.hierarchy` (scene
and view hierarchies), :mod:`.paraboloid` (dual-paraboloid maps),
:mod:`.traversal` (the traversal, ManyLoDs and brute force, push, fusion,
queries), :mod:`.vpl` (instant radiosity: VPLs, gathering, bilateral
filter, one-bounce reference), :mod:`.particles` (glowing particles),
:mod:`.method` (the registered methods). See ``docs/megaviews.md``.

Importing this package only registers the method names (the heavy modules
load on first use).
"""
from __future__ import annotations

from ..methods import register


def _factory(mode):
    def make(scene, **kw):
        from .method import ManyViewIR
        return ManyViewIR(scene, mode=mode, **kw)
    return make


register("megaviews", _factory("megaviews"),
         help="VPL instant radiosity, shadow maps by concurrent scene-view traversal (indirect light)")
register("manylods", _factory("manylods"),
         help="VPL instant radiosity, shadow maps by per-view scene-hierarchy traversal (indirect light)")
register("brute", _factory("brute"),
         help="VPL instant radiosity, every scene leaf splatted into every shadow map (indirect light)")
