"""Instant radiosity methods ``megaviews``, ``manylods`` and ``brute``.

All three generate the same VPLs per frame (:meth:`ManyViewIR.lights`),
render one dual-paraboloid shadow map per VPL (:meth:`ManyViewIR.shadow_maps`:
through the view hierarchy for ``megaviews``, per view for ``manylods``,
every leaf into every view for ``brute``) and gather them per pixel
(:meth:`ManyViewIR.gather`: :func:`.vpl.gather`, then :func:`.vpl.bilateral`).
The ``megaviews`` experiment calls these three steps itself (to time the
shadow maps alone on one VPL set); :meth:`ManyViewIR.render` chains them.

Output: *indirect* light (``output = "indirect"``, ``bounces`` reflections),
compared by the pipeline with :func:`slc.reference.references.reference_for`'s
indirect reference, not with the direct ground truth.
"""
from __future__ import annotations

import math
from contextlib import nullcontext
from dataclasses import dataclass

import mitsuba as mi

from slc.methods import Method, MethodError, Param, register
from slc.methods.megaviews import traversal as tv
from slc.methods.megaviews.maps import PAIR_BYTES
from slc.methods.megaviews import vpl as vp
from slc.methods.megaviews.hierarchy import SCENE_DEPTH, VIEW_DEPTH, SceneHierarchy, ViewHierarchy


@dataclass
class Lights:
    """The frame's virtual point lights and their shadow maps (with the view hierarchy
    gathering culls with), shared by every viewer's gathering."""
    vpls: vp.VPLSet
    maps: object
    tree: ViewHierarchy


class ManyViewIR(Method):
    r"""VPL instant radiosity with many-view shadow maps.

    .. math:: L(x) \approx \frac{C(x)}{S}\sum_{s=1}^{S}
              f_x\cos\theta_x\, f_k\cos\theta_k\,\frac{\Phi_k}{\max(d^2, d_{min}^2)}\, V_k(x)

    (see :mod:`.vpl`), with ``V_k`` read from VPL k's shadow map. The
    subclasses differ only in how the maps are rendered (``mode``).
    """
    name = "megaviews"
    shade_stage = "gather"
    mode = "megaviews"
    output = "indirect"
    params = (
        Param("views", 4096, "VPLs (views) per frame", lo=1, hi=4_000_000),
        Param("bounces", 1, "light-path bounces that leave VPLs (indirect bounces)", lo=1, hi=8),
        Param("res", 16, "shadow-map resolution per paraboloid face (a power of two)", lo=2, hi=1024),
        Param("scene_depth", SCENE_DEPTH, "scene octree levels (the paper: 11 on a GPU)", lo=1, hi=12),
        Param("view_depth", VIEW_DEPTH, "view octree levels", lo=1, hi=12),
        Param("samples", 64, "VPL samples per pixel", lo=1, hi=1 << 16),
        Param("cull_level", 6, "view-hierarchy level down to which gathering culls VPL nodes (the paper: 6)",
              lo=0, hi=12),
        Param("cutoff", 0.0, "gathering distance cut-off, fraction of the scene cube edge (0: off)", lo=0.0, hi=4.0),
        Param("cull", True, "frustum culling of scene-view pairs in the traversal (0: Fig. 10's culling-off run)"),
        Param("scene_h", True, "use the scene hierarchy (0: scene leaves x view root, the view-only run of Sec. 4.1)"),
        Param("split", "view", "multi-pass split: 'view' (the paper's, at the view root) or 'chunk' (exact chunks)",
              choices=("view", "chunk")),
        Param("split_level", -1, "multi-pass level of the view split (-1: found from the budget, as the paper)",
              lo=-1, hi=12),
        Param("filter", 4, "cross-bilateral filter radius in pixels (0: off)", lo=0, hi=32),
        Param("fusion", True, "fuse maps top-down (0: queries walk the ancestors)"),
        Param("budget", tv.DEFAULT_BUDGET, "pair-queue budget in pairs (multi-pass above it)",
              lo=1024, hi=1_000_000_000),
        Param("mpf", None, "multi-pixel filling (default: on from 64^2 maps up)", kind=bool),
    )

    def __init__(self, scene, **kw):
        super().__init__(scene, **kw)
        self.multi_pixel = self.res >= 64 if self.mpf is None else self.mpf
        self._sh = None
        self._maps = None
        self._vh = None
        self.last_stats = {}

    def validate(self) -> None:
        if self.res & (self.res - 1):
            raise MethodError(f"{self.name}: res must be a power of two (got {self.res})")

    def variant(self, **changes) -> "ManyViewIR":
        """The same method with some settings changed (validated), sharing
        the scene hierarchy when ``scene_depth`` stays the same."""
        m = type(self)(self.scene, seed=self.seed, **{**self.settings(), **changes})
        if m.scene_depth == self.scene_depth:
            m._sh = self._sh
        return m

    def use_scene_hierarchy(self, sh: SceneHierarchy) -> None:
        """Share a scene hierarchy built by another method instance (same
        scene, same ``scene_depth``)."""
        if sh.depth != self.scene_depth:
            raise ValueError(f"scene hierarchy of depth {sh.depth}, method needs {self.scene_depth}")
        self._sh = sh

    def scene_hierarchy(self) -> SceneHierarchy:
        if self._sh is None:
            self._sh = SceneHierarchy(self.scene.mi_scene, self.scene_depth)
        return self._sh

    def reset(self):
        self._maps = None

    # ------------------------------------------------------------------ steps
    def lights(self, seed: int) -> vp.VPLSet:
        """The frame's VPLs (``views`` of them, ``bounces`` per light path)."""
        return vp.generate(self.scene.mi_scene, self.views, self.bounces, seed)

    def shadow_maps(self, vpls: vp.VPLSet, timer=None, phi: float = math.pi / 2):
        """(maps, octree view hierarchy for gathering) of views at the VPLs
        (hemispheres, ``phi = pi/2``; ``pi`` for omnidirectional views)."""
        sh = self.scene_hierarchy()
        with (timer.stage("view_hierarchy") if timer is not None else nullcontext()) as st:
            tree = ViewHierarchy(vpls.position, vpls.normal, phi, self.view_depth)
            flat = None if self.mode == "megaviews" else ViewHierarchy(vpls.position, vpls.normal, phi, flat=True)
            if st is not None:
                st.outputs(*[(h.positions_np, h.directions_np) for h in (tree, flat) if h is not None])
        mode = "viewonly" if (self.mode == "megaviews" and not self.scene_h) else self.mode
        maps = tv.render_maps(sh, tree if flat is None else flat, self.res, mode, cull=self.cull,
                              budget_pairs=self.budget, fusion=self.fusion, timer=timer,
                              multi_pixel=self.multi_pixel, split=self.split,
                              split_level=None if self.split_level < 0 else self.split_level)
        self._maps, self._vh = maps, tree
        self.last_stats = maps.stats.as_dict()
        return maps, tree

    def gather(self, gb, vpls: vp.VPLSet, maps, tree, seed: int):
        """Indirect light at the G-buffer points (gathering, then the filter)."""
        sh = self.scene_hierarchy()
        L = vp.gather(sh, vpls, maps, gb, self.samples, seed, self.cull_level, cull_tree=tree,
                      fused=self.fusion, cutoff=self.cutoff * sh.tree.edge)
        return vp.bilateral(gb, L, self.filter) if self.filter > 0 else L

    def update_frame(self, ctx, gbuffers, timer) -> "Lights":
        with timer.stage("vpl") as st:
            vpls = self.lights(self.seed_for(ctx.frame))
            st.outputs(vpls.flux, vpls.position, vpls.normal)
        maps, tree = self.shadow_maps(vpls, timer)
        with timer.stage("maps") as st:
            st.outputs(maps.depth)
        return Lights(vpls=vpls, maps=maps, tree=tree)

    def shade(self, ctx, fr: "Lights", v: int, gb) -> mi.Color3f:
        return self.gather(gb, fr.vpls, fr.maps, fr.tree, self.seed_for(ctx.frame, v))

    # --------------------------------------------------------------- figures
    def memory(self) -> dict:
        """Bytes by part (after :meth:`shadow_maps`): pair-queue peak, all
        maps, scene and view hierarchies (see ``docs/megaviews.md``)."""
        out = {"scene_hierarchy": self.scene_hierarchy().memory_bytes() if self._sh is not None else 0,
               "maps": 0, "view_hierarchy": 0, "pair_queue": 0}
        if self._maps is not None:
            out["maps"] = self._maps.memory_bytes()
            out["view_hierarchy"] = self._maps.view_h.memory_bytes()
            out["pair_queue"] = self._maps.stats.peak_pairs * PAIR_BYTES
        return out

    def memory_bytes(self) -> int:
        return int(sum(self.memory().values()))

    def stats(self):
        return {k: float(v) for k, v in self.last_stats.items()}


class MegaViews(ManyViewIR):
    __doc__ = ManyViewIR.__doc__ + "\n    Maps by concurrent scene-view hierarchy traversal.\n"
    name = mode = "megaviews"


class ManyLoDs(ManyViewIR):
    __doc__ = ManyViewIR.__doc__ + "\n    Maps by a scene-hierarchy traversal per view.\n"
    name = mode = "manylods"


class BruteForce(ManyViewIR):
    __doc__ = ManyViewIR.__doc__ + "\n    Maps by splatting every scene leaf into every view.\n"
    name = mode = "brute"


register("megaviews", MegaViews,
         help="VPL instant radiosity, shadow maps by concurrent scene-view traversal (indirect light)")
register("manylods", ManyLoDs,
         help="VPL instant radiosity, shadow maps by per-view scene-hierarchy traversal (indirect light)")
register("brute", BruteForce,
         help="VPL instant radiosity, every scene leaf splatted into every view (indirect light)")
