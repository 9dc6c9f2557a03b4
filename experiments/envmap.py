"""envmap: a courtyard lit only by an environment map (the paper's Fig. 18).

The ``skylit`` scene under (a) the two HDR skies of ``../shared/envmaps/``
(a sunset, a studio; skipped with a note when absent) and (b) a map made in
code that is hard for cones: many small bright regions over a dim sky. FLIP
and time for slc, sh (spherical harmonics, which the paper expects to fit
smooth light better), rt48 and restir, with plots and image strips.

    slc run envmap --quick [--maps spots venice]
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.run import experiment as ex  # noqa: E402 (after the path of a standalone run)
from slc.run.adaptive_viz import add_choice_section  # noqa: E402
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.sweeps import variant_experiment  # noqa: E402
from slc.scene.scenes import ENVMAPS_DIR  # noqa: E402

NAME = "envmap"
FULL = dict(scene="skylit", maps=["venice", "studio", "spots"], width=320, height=180, frames=120, warmup=10, eval_frames=[59, 119])
QUICK = dict(scene="skylit", maps=["venice", "spots"], width=160, height=90, frames=24, warmup=10, eval_frames=[23])
METHODS = ["rt48", "restir", "regir", "slc", "slc:max_cones=4", "sh", "adaptive"]


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--maps", nargs="+", help="environment maps: venice, studio (../shared/envmaps), spots, constant")


def run(opts):
    pr = ex.apply_common(opts, QUICK if opts.quick else FULL)
    scene = (opts.scene or [pr["scene"]])[0]
    maps = opts.maps or pr["maps"]
    if not opts.maps:
        missing = [m for m in maps if m in ("venice", "studio") and not any(ENVMAPS_DIR.glob(f"{m}*.hdr"))]
        if missing:
            print(f"note: skipping {', '.join(missing)} (no HDR file in {ENVMAPS_DIR})", file=sys.stderr)
        maps = [m for m in maps if m not in missing]
    variants = [(m, f"{scene}:env={m}") for m in maps]
    specs = opts.methods or ex.available_methods(METHODS)
    res = variant_experiment(opts, NAME, pr, specs, variants, "envmap",
                             f"{scene}: error and time per environment map")
    return add_choice_section(opts, NAME, res, "envmap")


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
