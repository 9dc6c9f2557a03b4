"""Instant radiosity methods ``megaviews``, ``manylods`` and ``brute``.

All three generate the same VPLs per frame, render one dual-paraboloid
shadow map per VPL (through the view hierarchy for ``megaviews``, per view
for ``manylods``, every leaf into every view for ``brute``) and gather
them per pixel (:func:`.vpl.gather`, then :func:`.vpl.bilateral`).

Note: :meth:`render` returns the *indirect* illumination from the VPLs
(one bounce by default), not direct light: these methods are compared in
the ``megaviews`` experiment against a one-bounce indirect reference, not
against :mod:`slc.groundtruth`.
"""
from __future__ import annotations

import math


from ..methods import Method
from . import traversal as tv
from . import vpl as vp
from .hierarchy import SCENE_DEPTH, VIEW_DEPTH, SceneHierarchy, ViewHierarchy


class ManyViewIR(Method):
    """VPL instant radiosity with many-view shadow maps.

    Parameters (defaults): ``mode`` (``megaviews``/``manylods``/``brute``),
    ``views`` (VPL count, 4096), ``bounces`` (1), ``res`` (map resolution
    per paraboloid face, 16), ``scene_depth`` (7), ``view_depth`` (7),
    ``samples`` (VPL samples per pixel, 64), ``cull_level`` (2),
    ``filter`` (cross-bilateral radius, 4; 0 = off), ``fusion`` (1; 0 =
    direct queries through the ancestors), ``budget`` (pair-queue budget
    in pairs, 16M), ``mpf`` (multi-pixel filling; default on
    from 64^2 maps up, off below, as in the paper's timings).
    """
    shared = True
    output = "indirect"

    def __init__(self, scene, mode: str = "megaviews", views: int = 4096, bounces: int = 1, res: int = 16,
                 scene_depth: int = SCENE_DEPTH, view_depth: int = VIEW_DEPTH, samples: int = 64,
                 cull_level: int = 2, filter: int = 4, fusion: int = 1, budget: int = tv.DEFAULT_BUDGET,
                 mpf: int | None = None, **kw):
        super().__init__(scene, **kw)
        self.name = mode
        self.mode = mode
        self.views, self.bounces, self.res = int(views), int(bounces), int(res)
        self.scene_depth, self.view_depth = int(scene_depth), int(view_depth)
        self.samples, self.cull_level, self.filter = int(samples), int(cull_level), int(filter)
        self.fusion, self.budget, self.mpf = bool(fusion), int(budget), (
            self.res >= 64 if mpf is None else bool(mpf))
        self._sh = None
        self._maps = None
        self._vh = None
        self.last_stats = {}

    def settings(self):
        return dict(mode=self.mode, views=self.views, bounces=self.bounces, res=self.res,
                    scene_depth=self.scene_depth, view_depth=self.view_depth, samples=self.samples)

    def scene_hierarchy(self) -> SceneHierarchy:
        if self._sh is None:
            self._sh = SceneHierarchy(self.scene.mi_scene, self.scene_depth)
        return self._sh

    def reset(self):
        self._maps = None

    def shadow_maps(self, vpls: vp.VPLSet, timer=None):
        """(maps, octree view hierarchy for gathering) for ``vpls``."""
        sh = self.scene_hierarchy()
        from contextlib import nullcontext
        with (timer.stage("view_hierarchy") if timer is not None else nullcontext()):
            tree = ViewHierarchy(vpls.position, vpls.normal, math.pi / 2, self.view_depth)
            flat = None if self.mode == "megaviews" else ViewHierarchy(vpls.position, vpls.normal,
                                                                       math.pi / 2, flat=True)
        maps = tv.render_maps(sh, tree if flat is None else flat, self.res, self.mode,
                              budget_pairs=self.budget, fusion=self.fusion, timer=timer,
                              multi_pixel=self.mpf)
        return maps, tree

    def render(self, ctx, gbuffers, timer):
        with timer.stage("vpl") as st:
            vpls = vp.generate(self.scene.mi_scene, self.views, self.bounces, self.seed_for(ctx.frame))
            st.outputs(vpls.flux)
        maps, tree = self.shadow_maps(vpls, timer)
        self._maps, self._vh = maps, tree
        outs = []
        with timer.stage("gather") as st:
            for v, gb in enumerate(gbuffers):
                L = vp.gather(self.scene_hierarchy(), vpls, maps, gb, self.samples, self.seed_for(ctx.frame, v),
                              self.cull_level, cull_tree=tree, fused=self.fusion)
                if self.filter > 0:
                    L = vp.bilateral(gb, L, self.filter)
                outs.append(L)
            st.outputs(*outs)
        self.last_stats = maps.stats.as_dict()
        return outs

    def memory_bytes(self) -> int:
        b = self.scene_hierarchy().memory_bytes() if self._sh is not None else 0
        if self._maps is not None:
            b += self._maps.memory_bytes() + self._maps.view_h.memory_bytes()
            b += self._maps.stats.peak_pairs * tv.PAIR_BYTES
        return int(b)

    def stats(self):
        return {k: float(v) for k, v in self.last_stats.items()}
