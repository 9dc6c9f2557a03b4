"""Y3Co1Cg1 against Y3Co3Cg3 on the final frame (the CRC paper's Table 1 protocol,
experiments/_crc_protocol.py) with two of the paper's remedies swept: the chroma scale
(``bleeding``: "the over-saturation can be easily treated by scaling down the CoCg
coefficients") and the grid resolution ("a higher volume resolution would mitigate the
issue"); Y3Co3Cg3 of the same resolution each time. The crc experiment's quick preset (128x72,
8 frames, its scenes), 1 bounce: one JSON line per run (scene, sweep, value, Lab RMSE of the
final frame), and with --md a Markdown table per sweep.

    PYTHONPATH=. python tools/crc_sweeps.py [--scenes cornell atrium] [--bounces 1] [--md out.md]
"""
import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.run import experiment as ex  # noqa: E402 (after the path of a standalone run)

crc = ex.load("crc")
ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--scenes", nargs="+", default=crc.QUICK_SCENES, help="scene names (default: the quick preset's)")
ap.add_argument("--bleeding", nargs="+", type=float, default=[0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0],
                help="chroma scales of Y3Co1Cg1 (default 0-2)")
ap.add_argument("--resolution", nargs="+", type=int, default=[16, 24, 32],
                help="grid cells on the scene box's longest side (default 16 24 32)")
ap.add_argument("--bounces", type=int, default=1, help="indirect bounces (default 1)")
ap.add_argument("--md", help="write the tables to this Markdown file")
opts = ap.parse_args()


def main() -> int:
    from slc import methods
    from slc.reference.metrics import lab_rmse
    from slc.reference.references import reference_for
    from slc.run.pipeline import RunConfig, run_sequence
    from slc.scene.gbuffer import frame_gbuffers
    from slc.scene import views
    P = crc.QUICK
    W, H, f = P["width"], P["height"], P["frames"] - 1
    cfg = RunConfig(width=W, height=H, frames=P["frames"], warmup=P["warmup"], eval_frames=[], measure_overlap=False)
    names = ex.load_and_validate(opts.scenes, [], True)
    rows = []
    for sc in ex.each_scene(names):
        v = views.single(sc)
        gb = frame_gbuffers(sc, v, f, W, H)[0]
        direct = reference_for("direct", sc, gb, f, gb.viewer, spp=P["direct_spp"])

        done = {}

        def final(**kw):
            spec = crc.spec_of({"resolution": P["resolution"], "bounces": opts.bounces, "bleeding": 1.0, **kw})
            if spec not in done:
                done[spec] = direct + run_sequence(sc, methods.create(spec, sc, seed=0), v, cfg).last[gb.viewer]
            return done[spec]

        def row(sweep, value, ref, test):
            r = {"scene": sc.name, "bounces": opts.bounces, "sweep": sweep, "value": value,
                 "lab_rmse_final": lab_rmse(ref, test, sc.exposure)}
            rows.append(r)
            print(json.dumps(r), flush=True)

        ref = final(encoding="y3co3cg3")
        for b in opts.bleeding:
            row("bleeding", b, ref, final(encoding="y3co1cg1", bleeding=b))
        for n in opts.resolution:
            row("resolution", n, final(encoding="y3co3cg3", resolution=n), final(encoding="y3co1cg1", resolution=n))
    if opts.md:
        Path(opts.md).write_text(markdown(rows))
    return 0


def markdown(rows) -> str:
    md = ("# crc-sweeps\n\nFinal frame (ground-truth direct + the cache's indirect light), Lab RMSE [%] of "
          "Y3Co1Cg1 (the paper's offset decoding) against Y3Co3Cg3 of the same sampling and grid; 128x72, 8 "
          "frames, the last one compared, 1 bounce unless stated. *bleeding*: the scale of Co and Cg at "
          "reconstruction (1: none); *resolution*: grid cells on the scene box's longest side.\n")
    for sweep in ("bleeding", "resolution"):
        rs = [r for r in rows if r["sweep"] == sweep]
        values = sorted({r["value"] for r in rs})
        md += f"\n## {sweep}\n\n| scene | b | " + " | ".join(f"{v:g}" for v in values) + " | best |\n|"
        md += "---|" * (len(values) + 3) + "\n"
        for name in dict.fromkeys(r["scene"] for r in rs):
            by = {r["value"]: r["lab_rmse_final"] for r in rs if r["scene"] == name}
            best = min(by, key=by.get)
            md += (f"| {name} | {rs[0]['bounces']} | " + " | ".join(f"{by[v]:.2f}" if v in by else "-" for v in values)
                   + f" | {best:g}: {by[best]:.2f} |\n")
    return md


if __name__ == "__main__":
    sys.exit(main())
