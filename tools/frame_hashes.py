"""Frame hashes of every method's default settings, for refactors that must keep images bit-identical.

    python tools/frame_hashes.py [--res 64x36] [--frames 6] [--only METHOD ...] > hashes.txt
    python tools/frame_hashes.py --scenes all --methods adaptive adaptive:force=sh > hashes.txt

Renders each (scene, method, rig) case of ``CASES`` (or, with ``--scenes``, every method of
``--methods`` on one viewer of each scene named, ``all``: every built-in scene) for a few
frames and prints one line per case:
the md5 of every viewer's raw last-frame image (float32 bytes, viewers in order). Two checkouts
compared with ``diff`` on this output agree bit for bit or name the case that changed. Run it from
the checkout under test (``python tools/frame_hashes.py`` puts that checkout's ``slc`` first).
"""
from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# (scene, method, rig, viewers): every method family with its defaults on the atrium and the
# Cornell box, and one multi-viewer rig.
CASES = [(scene, m, "single", 1)
         for scene in ("atrium", "cornell")
         for m in ("rt16", "rt48", "restir", "slc", "slc:fetch=bilinear", "sh", "adaptive",
                   "crc", "osc-gi", "pt", "megaviews", "manylods", "brute")]
CASES += [("atrium", m, "overlap", 4) for m in ("slc", "adaptive", "restir", "osc-gi")]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--res", default="64x36", help="image size WxH (default 64x36)")
    p.add_argument("--frames", type=int, default=6, help="frames rendered per case (default 6)")
    p.add_argument("--only", nargs="*", default=None, help="run only these methods")
    p.add_argument("--scenes", nargs="*", default=None,
                   help="scenes (all: every built-in scene) instead of CASES, one viewer each")
    p.add_argument("--methods", nargs="*", default=None, help="method specs with --scenes (default: CASES' methods)")
    opts = p.parse_args(argv)
    w, h = (int(v) for v in opts.res.split("x"))

    from slc import methods

    from slc.scene import scenes, views
    from slc.run.experiment import release_scenes
    from slc.run.pipeline import RunConfig, run_sequence
    import numpy as np

    cases = CASES
    if opts.scenes is not None:
        names = scenes.builtin_names() if opts.scenes == ["all"] else opts.scenes
        specs = opts.methods or list(dict.fromkeys(m for _, m, _, _ in CASES))
        cases = [(s, m, "single", 1) for s in names for m in specs]
    loaded = {}
    for scene_name, method, rig, n in cases:
        if opts.only and method not in opts.only:
            continue
        if scene_name not in loaded:
            loaded.clear()               # one scene alive at a time: the scene before is freed, so
            release_scenes()             # that its objects leave Dr.Jit's virtual call tables
            loaded[scene_name] = scenes.load(scene_name)
        s = loaded[scene_name]
        m = methods.create(method, s, seed=0)
        vs = views.make_rig(s, rig, n, 1.0)
        cfg = RunConfig(width=w, height=h, frames=opts.frames, warmup=1, seed=0, eval_frames=[],
                        measure_overlap=False)
        r = run_sequence(s, m, vs, cfg)
        md5 = hashlib.md5()
        for vname in sorted(r.last):
            md5.update(np.ascontiguousarray(np.asarray(r.last[vname], dtype=np.float32)).tobytes())
        print(f"{scene_name:8s} {rig:8s} {n:2d} {method:22s} {md5.hexdigest()}", flush=True)
        del m, r                         # the method holds its scene
    return 0


if __name__ == "__main__":
    sys.exit(main())
