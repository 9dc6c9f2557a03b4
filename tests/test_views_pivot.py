"""An overlap rig keeps every viewer on the scene: a camera outside the scene's
bounding box (the cornell box, seen through its open side) is fanned about its
look-at point (``pivot="auto"``), one inside (the atrium) about its eye."""
import numpy as np

import slc.backend  # noqa: F401
from slc import views
from slc.gbuffer import render_gbuffer
from slc.scenes import load


def _valid_per_viewer(sc, vs, w=48, h=27):
    return [int(np.count_nonzero(np.array(render_gbuffer(sc, v.camera(0), w, h, None, v.name).valid))) for v in vs]


def test_pivot_follows_where_the_camera_is():
    assert views.fan_pivot(load("cornell")) == "target"
    assert views.fan_pivot(load("atrium")) == "eye"


def test_cornell_fan_about_the_target_sees_the_box_in_every_view():
    sc = load("cornell")
    eye = _valid_per_viewer(sc, views.overlap_rig(sc, 16, 0.75, pivot="eye"))
    auto = _valid_per_viewer(sc, views.overlap_rig(sc, 16, 0.75, pivot="auto"))
    assert min(eye) == 0                      # the old fan: views looking out of the box
    assert min(auto) > 0.25 * max(auto), auto  # every view holds a good part of the box
    # the calibrated overlap is still reached (within the calibration's tolerance)
    _, got = views.calibrated_step(sc, 16, 0.75, pivot="target")
    assert abs(got - 75.0) < 10.0, got
