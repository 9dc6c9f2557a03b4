"""point-lights: a gallery lit only by 16-64 point and spot lights.

Delta lights are the case the Surface Light Cones paper calls overkill for
cones ("a simple visibility/occlusion caching approach may work
significantly better"): FLIP and time against the light count for slc, sh,
rt48 and restir; the baseline of the adaptive representation's visibility
mode.

    slc run point-lights --quick [--lights 16 64]
"""
from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__" and __package__ is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slc.run.adaptive_viz import add_choice_section  # noqa: E402 (after the path of a standalone run)
from slc.run.experiment import add_common_arguments  # noqa: E402
from slc.run.sweeps import scene_option_sweep  # noqa: E402

NAME = "point-lights"
FULL = dict(scene="lamps", lights=[16, 32, 64], width=320, height=180, frames=120, warmup=10, eval_frames=[59, 119])
QUICK = dict(scene="lamps", lights=[16, 64], width=160, height=90, frames=24, warmup=10, eval_frames=[23])
METHODS = ["rt48", "restir", "regir", "slc", "slc:max_cones=4", "sh", "adaptive"]


def add_arguments(p):
    add_common_arguments(p)
    p.add_argument("--lights", type=int, nargs="+", help="light counts")


def run(opts):
    res = scene_option_sweep(opts, NAME, QUICK, FULL, METHODS, "lights",
                             "error and time against the number of point/spot lights")
    return add_choice_section(opts, NAME, res, "lights")


if __name__ == "__main__":
    from slc.run.cli import run_experiment_standalone
    sys.exit(run_experiment_standalone(__file__))
