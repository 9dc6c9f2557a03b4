"""many-lights: Surface Light Cones with many moving lights (the paper's Fig. 17).

The hangar with 3, 6, 12 and 24 small moving lights (total power kept):
FLIP and time against the light count for slc with 1-4 cones per entry, rt48
and restir, a speed-against-error plot per light count and image strips. The
paper: with many dominant lights three cones are too few and the hangar gets
noisy; this is the baseline the adaptive representation must beat (it lists
the small sphere lights in VISIBILITY records: docs/adaptive.md).

    slc run many-lights --quick [--lights 3 12] [--methods slc rt48]
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.run.adaptive_viz import add_choice_section  # noqa: E402 (after the path of a standalone run)
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.sweeps import scene_option_sweep  # noqa: E402

NAME = "many-lights"
FULL = dict(scene="hangar", lights=[3, 6, 12, 24], width=320, height=180, frames=120, warmup=10, eval_frames=[59, 119])
QUICK = dict(scene="hangar", lights=[3, 12, 24], width=160, height=90, frames=24, warmup=10, eval_frames=[23])
METHODS = ["rt48", "restir", "regir", "slc:max_cones=1", "slc:max_cones=2", "slc", "slc:max_cones=4", "adaptive"]


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--lights", type=int, nargs="+", help="light counts")


def run(opts):
    res = scene_option_sweep(opts, NAME, QUICK, FULL, METHODS, "lights",
                             "error and time against the number of moving lights")
    return add_choice_section(opts, NAME, res, "lights")


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
