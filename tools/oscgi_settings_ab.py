"""osc-gi settings side by side (session gi11): FLIP, time, update ms, kernels after warm-up, md5 of the last image,
and with PROBE=1 the share of cache rays hitting a back face and black pixels.

    SEED=0 [PROBE=1] PYTHONPATH=. python tools/oscgi_settings_ab.py SCENES "SPEC;SPEC;..." [WxH] [FRAMES]
"""
import sys, os, json, hashlib
import numpy as np
import mitsuba as mi
from slc import scenes, views, methods
from slc.pipeline import RunConfig, run_sequence
scs = sys.argv[1].split(",")
specs = sys.argv[2].split(";")
W, H = (int(x) for x in sys.argv[3].split("x")) if len(sys.argv) > 3 else (160, 90)
frames = int(sys.argv[4]) if len(sys.argv) > 4 else 24
seed = int(os.environ.get("SEED", 0))
cfg = RunConfig(width=W, height=H, frames=frames, warmup=frames // 3, eval_frames=[frames - 1], seed=seed, ref_spp=256,
                measure_overlap=False)
for name in scs:
    s = scenes.load(name)
    v = views.single(s)
    for spec in specs:
        m = methods.create(spec, s, seed=seed)
        if os.environ.get("PROBE"):
            m.probe_origins = True
        res = run_sequence(s, m, v, cfg)
        r = res.row()
        img = next(iter(res.images.values()))["img"]
        out = {"scene": name, "spec": spec, "seed": seed, "flip": round(r.get("flip", float("nan")), 5),
               "time_ms": round(r["time_ms"], 1), "update_ms": round(res.stages.get("update", float("nan")), 1), "compiled_after_warmup": r["compiled_after_warmup"],
               "mean": float(np.mean(img)),
               "md5": hashlib.md5(np.ascontiguousarray(np.asarray(img, np.float32)).tobytes()).hexdigest()[:10]}
        if os.environ.get("PROBE"):
            b, n = m.origin_probe
            out["backface_share"] = b / max(n, 1)
            out["black_px"] = float(np.mean(np.max(np.asarray(img), axis=-1) <= 0.0))
        print(json.dumps(out), flush=True)
