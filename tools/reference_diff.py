"""How much a change moves the ground truth, and the error figures measured against it.

``dump`` renders methods on built-in scenes (one viewer, the single-viewer quick
preset: 160x90, 24 frames, 10 warm-up, evaluated frames 15 and 23) with the ``slc``
found on ``PYTHONPATH`` and saves, per scene, method and evaluated frame, the image
and the 2048-sample ground truth it was compared with. ``compare`` reads two such
folders (say, of two checkouts) and prints per scene and frame the change of the
ground truth (signed change of its image mean, mean and 99th percentile of the
per-pixel relative change ``|B - A| / (A + 0.01)``, relMSE of B against A) and per method the FLIP of each
run's image against its own ground truth and of B's image against A's ground truth.

    PYTHONPATH=<checkout A> python tools/reference_diff.py dump out/ref-a
    PYTHONPATH=<checkout B> python tools/reference_diff.py dump out/ref-b
    python tools/reference_diff.py compare out/ref-a out/ref-b
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def dump(out: Path, scenes: list[str], methods: list[str], width: int, height: int, frames: int,
         warmup: int, eval_frames: list[int]) -> None:
    from slc import methods as mt
    from slc.scene import scenes as sc
    from slc.scene import views
    from slc.run.pipeline import RunConfig, run_sequence
    out.mkdir(parents=True, exist_ok=True)
    for name in scenes:
        s = sc.load(name)
        for spec in methods:
            m = mt.create(spec, s, seed=0)

            def keep(f, v, gb, img, gt, spec=spec):
                np.savez(out / f"{name}__{spec}__{f}.npz", img=img, gt=gt, exposure=s.exposure)

            cfg = RunConfig(width=width, height=height, frames=frames, warmup=warmup, eval_frames=eval_frames,
                            on_eval=keep)
            r = run_sequence(s, m, views.single(s), cfg)
            print(f"{name} {spec}: " + ", ".join(f"{k} {v:.4f}" for k, v in r.metrics.items()))


def compare(a: Path, b: Path) -> None:
    from slc.reference.metrics import evaluate, rel_mse
    files = sorted(p.name for p in a.glob("*.npz") if (b / p.name).exists())
    seen = set()
    print("| scene | frame | GT mean change | mean pixel rel. change | p99 pixel rel. change | relMSE(B vs A) |")
    print("|---|---|---|---|---|---|")
    for fn in files:
        scene, _, frame = fn[:-4].split("__")
        if (scene, frame) in seen:
            continue
        seen.add((scene, frame))
        ga, gb = np.load(a / fn)["gt"], np.load(b / fn)["gt"]
        rel = np.abs(gb - ga) / (ga + 1e-2)
        print(f"| {scene} | {frame} | {gb.mean() / ga.mean() - 1:+.4f} | {rel.mean():.4f} | "
              f"{np.percentile(rel, 99):.4f} | {rel_mse(ga, gb):.5f} |")
    print()
    print("| scene | method | frame | FLIP A vs GT A | FLIP B vs GT B | FLIP B vs GT A |")
    print("|---|---|---|---|---|---|")
    for fn in files:
        A, B = np.load(a / fn), np.load(b / fn)
        scene, spec, frame = fn[:-4].split("__")
        e = float(A["exposure"])
        fa = evaluate(A["gt"], A["img"], e)["flip"]
        fb = evaluate(B["gt"], B["img"], e)["flip"]
        fx = evaluate(A["gt"], B["img"], e)["flip"]
        print(f"| {scene} | {spec} | {frame} | {fa:.4f} | {fb:.4f} | {fx:.4f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="render and save images and ground truths")
    d.add_argument("out", type=Path)
    d.add_argument("--scenes", nargs="+", default=["atrium", "garden"])
    d.add_argument("--methods", nargs="+", default=["rt48", "slc"])
    d.add_argument("--res", default="160x90", help="W x H in pixels (default 160x90)")
    d.add_argument("--frames", type=int, default=24, help="frames rendered (default 24)")
    d.add_argument("--warmup", type=int, default=10, help="warm-up frames (default 10)")
    d.add_argument("--eval", type=int, nargs="+", default=[15, 23], help="evaluated frames (default 15 23)")
    c = sub.add_parser("compare", help="compare two dumps")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    o = p.parse_args()
    if o.cmd == "dump":
        w, h = (int(x) for x in o.res.lower().split("x"))
        dump(o.out, o.scenes, o.methods, w, h, o.frames, o.warmup, o.eval)
    else:
        compare(o.a, o.b)


if __name__ == "__main__":
    main()
