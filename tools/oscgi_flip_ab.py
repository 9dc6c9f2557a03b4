"""FLIP, frame time, kernels after warm-up and the last image's md5 of osc-gi settings, one
viewer on the scene's path. The osc-gi experiment's RunConfig (ref_spp 256,
warm-up F // 3, the last frame evaluated).

    PYTHONPATH=. python tools/oscgi_flip_ab.py cornell,atrium 160 90 24 osc-gi osc-gi:bias=1 ...
"""
import sys, hashlib, time
import slc.backend
import numpy as np
from slc import methods, scenes, views
from slc.pipeline import RunConfig, run_sequence
scene_names = sys.argv[1].split(",")
W, H, F = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
specs = sys.argv[5:]
for sn in scene_names:
    s = scenes.load(sn)
    v = views.single(s)
    cfg = RunConfig(width=W, height=H, frames=F, warmup=max(1, F // 3), eval_frames=[F - 1], seed=0, ref_spp=256,
                    measure_overlap=False)
    for spec in specs:
        m = methods.create(spec, s, seed=0)
        res = run_sequence(s, m, v, cfg)
        r = res.row()
        img = np.asarray(next(iter(res.last.values()))) if res.last else None
        md5 = hashlib.md5(np.ascontiguousarray(img).tobytes()).hexdigest()[:10] if img is not None else "-"
        flip = {k: round(v, 4) for k, v in r.items() if "flip" in k.lower() and isinstance(v, float)}
        print(sn, spec, flip, "ms", round(r["time_ms"], 1), "kernels", r["compiled_after_warmup"], "md5", md5, flush=True)
