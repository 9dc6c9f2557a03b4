"""MegaViews against ManyLoDs at large view counts: shadow-map time of one
call per method and count (after a warm-up call at 1024 views, which compiles
the kernels), CPU time, pairs, passes and peak memory, as JSON lines.

    python tools/megaviews_scale.py 65536 262144 [--scene cornell] [--methods megaviews manylods]

Cornell box, scene and view octree depth 6, 16^2 maps (docs/megaviews.md,
"Speed-up over ManyLoDs"). ManyLoDs takes ~4 min at 256K views and ~18 min at
1M on 2 cores. Not part of `slc run megaviews`: that experiment also gathers and
compares every point with the reference, which at these counts takes longer
than the maps.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("views", nargs="+", type=int)
    p.add_argument("--scene", default="cornell")
    p.add_argument("--methods", nargs="+", default=["megaviews", "manylods"])
    p.add_argument("--depth", type=int, default=6)
    a = p.parse_args()

    import drjit as dr

    from slc import methods

    from slc.scene import scenes
    from slc.core.timing import StageTimer

    s = scenes.load(a.scene)
    s.set_frame(0)
    base = {m: methods.create(m, s, seed=0, scene_depth=a.depth, view_depth=a.depth) for m in a.methods}
    sh = base[a.methods[0]].scene_hierarchy()
    for m in base.values():
        m.use_scene_hierarchy(sh)
    for n in a.views:
        vpls = base[a.methods[0]].variant(views=n).lights(0)
        for mode in a.methods:
            m = base[mode].variant(views=n, res=16)
            m.shadow_maps(base[mode].variant(views=1024).lights(0))      # warm-up: kernels
            dr.sync_thread()
            c0, t0 = time.process_time(), time.perf_counter()
            timer = StageTimer()
            timer.begin_frame()
            maps, _ = m.shadow_maps(vpls, timer)
            timer.end_frame()
            dr.sync_thread()
            st = maps.stats.as_dict()
            print(json.dumps(dict(scene=a.scene, views=n, method=mode, wall_s=round(time.perf_counter() - t0, 3),
                                  cpu_s=round(time.process_time() - c0, 3), pairs=int(st["pairs"]),
                                  passes=int(st["passes"]), split_level=int(st["split_level"]),
                                  peak_rss_gb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, 2))),
                  flush=True)
            del maps


if __name__ == "__main__":
    main()
