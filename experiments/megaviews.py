"""megaviews: scaling of many-view rendering (MegaViews Figs. 10, 11, 12, 13, 16).

Shadow maps of VPL sets are rendered by ``megaviews`` (concurrent scene-view
traversal), ``manylods`` (scene hierarchy per view) and ``brute`` (every
scene leaf into every view, only where leaves x views stays under a pair
limit). Time is view-hierarchy build + traversal + push + fusion (one
timed run after a warm-up of the same method and size class; ``reps``
timed runs, median), broken down by stage (Fig. 10b/c); memory is the
pair-queue peak + all maps + hierarchies. Every row also gathers the VPLs
at a G-buffer and compares the indirect light with the indirect reference
(:func:`slc.reference.references.reference_for`, the VPLs' own bounce count) at the
same points: PSNR/SSIM/FLIP and the relative error of the mean (``mean_err``,
worst channel) and the median per-pixel relative luminance error
(``med_err``), the measures of ``tests/test_megaviews.py``.

Sweeps (``sweep`` column):

* ``views``: 1-bounce VPLs of growing count, 16^2 maps (Fig. 10a);
* ``distribution``: one view count with 1-bounce, 4-bounce and uniformly
  random views (Figs. 10a, 11);
* ``culling``: megaviews without pair culling (Fig. 10b, culling off);
* ``view-only``: view hierarchy without scene hierarchy (Sec. 4.1), small
  view counts, next to megaviews at the same counts;
* ``depth``: scene = view octree depth (Fig. 13; pairs, multi-pass level,
  time, error per depth), with the paper's view-root multi-pass split;
* ``resolution``: map resolution (Figs. 12, 14);
* ``gather``: gathering with culling down to level 0 / the paper's level 6
  and with a distance cut-off, at equal samples without the filter (Fig. 16);
* ``particles``: omnidirectional views (Sec. 5.2), time only;
* ``pipeline``: whole frames through :func:`slc.run.pipeline.run_sequence`.

    python experiments/megaviews.py --quick
    slc run megaviews --quick [--scene cornell] [--scene sponza]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

if __name__ == "__main__" and __package__ is None:  # runnable alone
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import drjit as dr  # noqa: E402 (after the path of a standalone run)
import numpy as np  # noqa: E402

from slc import methods  # noqa: E402
from slc.core import io  # noqa: E402
from slc.core.timing import StageTimer  # noqa: E402
from slc.methods.megaviews import vpl as vp  # noqa: E402
from slc.methods.megaviews.hierarchy import sample_surface  # noqa: E402
from slc.reference import metrics, references  # noqa: E402
from slc.run import experiment  # noqa: E402
from slc.run.pipeline import RunConfig, run_case  # noqa: E402
from slc.scene.gbuffer import frame_gbuffers  # noqa: E402
from slc.scene import views  # noqa: E402

NAME = "megaviews"
METHODS = ["megaviews", "manylods", "brute"]

FULL = dict(scenes=["cornell", "sponza"], views=[1024, 4096, 16384, 65536], res=[16, 32, 64], res_views=4096,
            dist_views=16384, viewonly=[64, 256], depths=[5, 6, 7, 8], depth_views=4096, particles=[4096, 16384],
            gres=64, reps=1, scene_depth=7, view_depth=7, brute_pairs=3e8, ref_spp=512, seq_views=4096,
            seq_frames=3, gather_samples=16, seq_methods=METHODS)
QUICK = dict(scenes=["cornell"], views=[1024, 4096, 16384], res=[], res_views=1024,
             dist_views=4096, viewonly=[64], depths=[5, 7], depth_views=1024, particles=[],
             gres=32, reps=1, scene_depth=6, view_depth=6, brute_pairs=6e7, ref_spp=256, seq_views=1024,
             seq_frames=2, gather_samples=16, seq_methods=["megaviews"])
STAGES = ["view_hierarchy", "traverse", "push", "fuse"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="small preset (a few minutes on 2 cores)")
    p.add_argument("--scene", action="append", help="scene name or .xml path (repeatable)")
    p.add_argument("--methods", nargs="+", help="subset of megaviews manylods brute")
    p.add_argument("--views", nargs="+", type=int, help="view counts of the views sweep")
    p.add_argument("--res", nargs="+", type=int, help="map resolutions of the resolution sweep")
    p.add_argument("--depths", nargs="+", type=int, help="octree depths of the depth sweep")
    p.add_argument("--scene-depth", type=int, help="scene (and view) octree depth")
    p.add_argument("--out", default="out", help="output folder (results go to OUT/megaviews)")
    p.add_argument("--seed", type=int, default=0)


def _time_maps(m, vpls, reps, phi=math.pi / 2):
    """(median ms, stage medians, maps, octree view hierarchy) of the
    method's shadow-map rendering of ``vpls`` (one untimed warm-up run when
    this method and setting have not run yet: kernel compilation)."""
    key = (m.name, m.res, m.cull, m.scene_h, phi)   # sizes and depths build no new kernels
    timer = StageTimer()
    if key not in _WARM:
        _WARM.add(key)
        m.shadow_maps(vpls, phi=phi)
    for _ in range(reps):
        timer.begin_frame()
        maps, tree = m.shadow_maps(vpls, timer, phi=phi)   # every stage ends evaluated and synced
        timer.end_frame()
    summ = timer.summary(0)
    return summ["total"], {k: summ.get(k, 0.0) for k in STAGES}, maps, tree


_WARM: set = set()


def _errors(gb, img, ref):
    """(worst-channel relative error of the image mean, median per-pixel
    relative luminance error), as tests/test_megaviews.py measures them."""
    valid = np.array(gb.valid, bool).reshape(gb.height, gb.width)
    x, r = img[valid], ref[valid]
    mean_err = np.abs(x.mean(0) - r.mean(0)) / np.maximum(r.mean(0), 1e-12)
    lx, lr = x.mean(1), r.mean(1)
    e = np.abs(lx - lr) / np.maximum(lr, 0.1 * lr.mean())
    return float(np.max(mean_err)), float(np.median(e))


def _random_views(s, n, seed):
    """``n`` views at uniform random surface points of the scene, each
    looking along its normal (Fig. 11's random distribution)."""
    P, N, _, _ = sample_surface(s.mi_scene, n, seed=seed + 11)
    k = np.random.default_rng(seed).choice(len(P), n, replace=len(P) < n)
    return vp.VPLSet(None, None, P[k] + 1e-3 * N[k], N[k], np.zeros(n))


def run(opts) -> dict:
    preset, modes = _preset(opts)
    names = experiment.load_and_validate(opts.scene or preset["scenes"], [], bool(opts.scene))
    out = Path(opts.out) / NAME
    rows, notes = [], []
    for s in experiment.each_scene(names):
        _SceneRun(s, opts, preset, modes, out, rows, notes).run()
    return experiment.load_part("megaviews_report").write(sys.modules[__name__], out, opts, preset, modes,
                                                          names, rows, notes)


def _preset(opts) -> tuple[dict, list]:
    """(the preset with the command line's overrides, the methods), the methods checked."""
    preset = dict(QUICK if opts.quick else FULL)
    if opts.views:
        preset["views"] = opts.views
    if opts.res:
        preset["res"] = opts.res
    if opts.depths:
        preset["depths"] = opts.depths
    if opts.scene_depth:
        preset["scene_depth"] = preset["view_depth"] = opts.scene_depth
    modes = opts.methods or METHODS
    for m in modes:
        if m not in METHODS:
            raise experiment.ExperimentError(f"unknown method '{m}' (megaviews: {', '.join(METHODS)})")
    return preset, modes


class _SceneRun:
    """The sweeps of one scene: the methods' first instances (sharing one scene hierarchy),
    the G-buffer the VPLs are gathered at, the indirect references by bounce count, and the
    rows and notes every measure adds to."""

    def __init__(self, s, opts, preset: dict, modes: list, out: Path, rows: list, notes: list):
        self.s, self.opts, self.preset, self.modes, self.out = s, opts, preset, modes, out
        self.rows, self.notes = rows, notes
        # every method and sweep setting is checked (one-line error) before any work
        base = dict(scene_depth=preset["scene_depth"], view_depth=preset["view_depth"])
        specs = [dict(views=n, res=16) for n in preset["views"]]
        specs += [dict(views=preset["res_views"], res=r) for r in preset["res"]]
        specs += [dict(scene_depth=d, view_depth=d) for d in preset["depths"]]
        s.set_frame(0)
        self.first = {mode: methods.create(mode, s, seed=opts.seed, **base) for mode in modes}
        for m in self.first.values():
            for sp in specs:
                m.variant(**sp)
        self.base_method = next(iter(self.first.values()))    # the first method: VPL sets and hierarchies
        sh = self.base_method.scene_hierarchy()
        for m in self.first.values():
            m.use_scene_hierarchy(sh)
        self.n_leaves = int(sh.size - sh.tree.level_start[sh.depth])
        self.gb = frame_gbuffers(s, views.single(s), 0, preset["gres"], preset["gres"])[0]
        self.refs = {}

    def run(self) -> None:
        """Every sweep, in the order the warm-ups of :func:`_time_maps` assume."""
        self.views_sweep()
        sets = self.distributions()
        if "megaviews" in self.modes:
            self.megaviews_sweeps(sets["vpl1"])
        self.resolution_sweep()
        if "megaviews" in self.modes:
            self.gather_sweep(sets["vpl1"])
        self.particles()
        self.pipeline()

    # ------------------------------ measures ------------------------------

    def ref_for(self, bounces):
        s, gb = self.s, self.gb
        if bounces not in self.refs:
            self.refs[bounces] = references.reference_for("indirect", s, gb, 0, gb.viewer,
                                                          spp=self.preset["ref_spp"], bounces=bounces)
            io.write_hdr_and_png(self.out / "images" / f"{s.name}_reference_b{bounces}", self.refs[bounces],
                                 references.exposure_for("indirect", s, self.refs[bounces]))
        return self.refs[bounces]

    def quality(self, img, bounces, tag):
        ref = self.ref_for(bounces)
        exposure = references.exposure_for("indirect", self.s, ref)
        q = metrics.evaluate(ref, img, exposure)
        me, md = _errors(self.gb, img, ref)
        io.write_hdr_and_png(self.out / "images" / f"{self.s.name}_{tag}", img, exposure)
        return {"flip": q["flip"], "psnr": q["psnr"], "ssim": q["ssim"], "mean_err": me, "med_err": md}

    def measure(self, kind, mode, vpls, dist="vpl1", gather=True, phi=math.pi / 2, **setting):
        s, preset, opts, gb = self.s, self.preset, self.opts, self.gb
        bounces = 4 if dist == "vpl4" else 1
        if mode == "brute" and self.n_leaves * vpls.n > preset["brute_pairs"]:
            self.notes.append(f"{s.name}: brute skipped at {vpls.n} views ({kind}) "
                              f"({self.n_leaves} leaves x {vpls.n} views > {preset['brute_pairs']:.0e} pairs)")
            return None
        m = self.first[mode].variant(views=max(vpls.n, 1), bounces=bounces, **setting)
        ms, stages, maps, tree = _time_maps(m, vpls, preset["reps"], phi)
        st = maps.stats.as_dict()
        mem = {k: v / 2 ** 20 for k, v in m.memory().items()}
        lsh = m.scene_hierarchy()
        row = {"scene": s.name, "method": mode, "label": m.label or m.name, "viewers": 1, "sweep": kind,
               "distribution": dist, "views": int(vpls.n), "resolution": int(m.res), "depth": m.scene_depth,
               "time_ms": ms, **{f"{k}_ms": v for k, v in stages.items()},
               "memory_mb": m.memory_bytes() / 2 ** 20,
               "pair_queue_mb": mem["pair_queue"], "maps_mb": mem["maps"],
               "leaf_maps_mb": maps.leaf_maps_bytes() / 2 ** 20,
               "hierarchy_mb": mem["scene_hierarchy"] + mem["view_hierarchy"],
               "views_per_render": st["views_per_render"], "pairs": st["pairs"], "rendered": st["rendered"],
               "culled": st["culled"], "multi_pixel": st["multi_pixel"], "passes": st["passes"],
               "split_level": st["split_level"], "wasted_pairs": st["wasted_pairs"],
               "scene_leaves": int(lsh.size - lsh.tree.level_start[lsh.depth]),
               "cull": int(m.cull), "scene_h": int(m.scene_h)}
        if gather and vpls.si is not None:
            L = m.gather(gb, vpls, maps, tree, opts.seed)
            tag = f"{kind}_{mode}_{dist}_{vpls.n}_{m.res}_d{m.scene_depth}" + ("" if m.cull else "_nocull")
            row.update(self.quality(vp.to_image(gb, L), bounces, tag))
        self.rows.append(row)
        print(f"{s.name} {kind} {mode} {dist} views={vpls.n} res={m.res} depth={m.scene_depth}: {ms:.1f} ms "
              f"({', '.join(f'{k} {v:.0f}' for k, v in stages.items())}), {row['memory_mb']:.1f} MB, "
              f"{st['pairs']:.3g} pairs, {st['views_per_render']:.2f} views/render"
              + (f", PSNR {row['psnr']:.2f}, mean err {row['mean_err']:.3f}" if "psnr" in row else ""),
              flush=True)
        return row

    # ------------------------------ sweeps ------------------------------

    def views_sweep(self) -> None:
        """Views sweep (Fig. 10a)."""
        for n in self.preset["views"]:
            vpls = self.base_method.variant(views=n).lights(self.opts.seed)
            for mode in self.modes:
                self.measure("views", mode, vpls)

    def distributions(self) -> dict:
        """View distributions (Figs. 10a, 11); returns the VPL sets by distribution."""
        nd, seed = self.preset["dist_views"], self.opts.seed
        sets = {"vpl1": self.base_method.variant(views=nd).lights(seed),
                "vpl4": self.base_method.variant(views=nd, bounces=4).lights(seed),
                "random": _random_views(self.s, nd, seed)}
        for dist in ("vpl4", "random"):
            for mode in [x for x in self.modes if x != "brute"]:
                self.measure("distribution", mode, sets[dist], dist)
        return sets

    def megaviews_sweeps(self, vpl1) -> None:
        """Culling off (Fig. 10b), view hierarchy without scene hierarchy (Sec. 4.1), hierarchy
        depth with the view-root multi-pass (Fig. 13)."""
        self.measure("culling", "megaviews", vpl1, cull=False)
        for n in self.preset["viewonly"]:
            vpls = self.base_method.variant(views=n).lights(self.opts.seed)
            self.measure("view-only", "megaviews", vpls, scene_h=False)
            self.measure("view-only", "megaviews", vpls)
        vpls = self.base_method.variant(views=self.preset["depth_views"]).lights(self.opts.seed)
        for d in self.preset["depths"]:
            self.measure("depth", "megaviews", vpls, scene_depth=d, view_depth=d)

    def resolution_sweep(self) -> None:
        """Map resolution (Figs. 12, 14)."""
        vpls = self.base_method.variant(views=self.preset["res_views"]).lights(self.opts.seed)
        for res in self.preset["res"]:
            for mode in self.modes:
                self.measure("resolution", mode, vpls, res=res)

    def gather_sweep(self, vpls) -> None:
        """Gathering: culling level and distance cut-off at equal samples, no filter (Fig. 16)."""
        s, gb, seed = self.s, self.gb, self.opts.seed
        m = self.first["megaviews"].variant(views=vpls.n)
        maps, tree = m.shadow_maps(vpls)
        for cl, cut in ((0, 0.0), (2, 0.0), (6, 0.0), (6, 0.25)):
            g = m.variant(views=vpls.n, cull_level=cl, cutoff=cut, filter=0, samples=self.preset["gather_samples"])
            for _ in range(2):   # the first call compiles
                dr.sync_thread()
                t0 = time.perf_counter()
                L = g.gather(gb, vpls, maps, tree, seed)
                dr.eval(L)
                dr.sync_thread()
            row = {"scene": s.name, "method": "megaviews", "label": g.label or g.name, "viewers": 1,
                   "sweep": "gather", "distribution": "vpl1", "views": vpls.n, "resolution": 16,
                   "cull_level": cl, "cutoff": cut, "samples": g.samples,
                   "gather_ms": (time.perf_counter() - t0) * 1e3,
                   **self.quality(vp.to_image(gb, L), 1, f"gather_cull{cl}_cut{cut}")}
            self.rows.append(row)
            print(f"{s.name} gather cull_level={cl} cutoff={cut}: PSNR {row['psnr']:.2f}, "
                  f"median err {row['med_err']:.3f}", flush=True)

    def particles(self) -> None:
        """Glowing particles (omnidirectional views, Sec. 5.2), time only."""
        s = self.s
        rs = np.random.default_rng(self.opts.seed + 5)
        for n in self.preset["particles"]:
            P = rs.uniform(s.bbox_min + 0.05 * (s.bbox_max - s.bbox_min),
                           s.bbox_max - 0.05 * (s.bbox_max - s.bbox_min), (n, 3))
            part = vp.VPLSet(None, None, P, np.tile([0.0, 1.0, 0.0], (n, 1)), np.zeros(n))
            for mode in [x for x in self.modes if x != "brute"]:
                self.measure("particles", mode, part, "particles", gather=False, phi=math.pi)

    def pipeline(self) -> None:
        """Whole frames through the common pipeline (:mod:`slc.run.pipeline`)."""
        s, preset, seed = self.s, self.preset, self.opts.seed
        gres = preset["gres"]
        cfg = RunConfig(width=gres, height=gres, frames=preset["seq_frames"], warmup=1, seed=seed,
                        eval_frames=[preset["seq_frames"] - 1], ref_spp=preset["ref_spp"], keep_images=False)
        for mode in [x for x in self.modes if x in preset["seq_methods"]]:
            if mode == "brute" and self.n_leaves * preset["seq_views"] > preset["brute_pairs"]:
                continue
            spec = (f"{mode}:views={preset['seq_views']},scene_depth={preset['scene_depth']},"
                    f"view_depth={preset['view_depth']}")
            row = run_case(s, spec, views.single(s), cfg, seed=seed, sweep="pipeline",
                           distribution="vpl1", views=preset["seq_views"], resolution=16)
            row.pop("_result")
            self.rows.append(row)
            print(f"{s.name} pipeline {mode} views={preset['seq_views']}: {row['time_ms']:.1f} ms per frame, "
                  f"PSNR {row['psnr']:.2f} vs the indirect reference", flush=True)


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
