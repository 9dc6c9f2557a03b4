"""RT-N and the ground truth agree for every emitter kind."""
import mitsuba as mi
import numpy as np
import pytest

from slc.scene import gbuffer, views

from slc.reference import groundtruth

from slc import methods
from slc.scene.gbuffer import frame_gbuffers
from slc.scene.camera import CameraPath
from slc.scene.scenes import SHARED_DIR, Scene

ENVMAP = SHARED_DIR / "envmaps" / "studio_small_03_1k.hdr"


def _scene(kind):
    d = {"type": "scene",
         "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
         "block": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.3, 0.4, 0]).scale(0.4),
                   "bsdf": {"type": "roughconductor", "alpha": 0.2}}}
    if kind == "point":
        d["light"] = {"type": "point", "position": [0.5, 2.0, 0.5], "intensity": {"type": "rgb", "value": [8, 8, 8]}}
    elif kind == "sphere":
        d["light"] = {"type": "sphere", "center": [-0.5, 1.5, 0.5], "radius": 0.3,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6, 5, 4]}}}
    elif kind == "constant":
        d["light"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.8, 0.9, 1.0]}}
    elif kind == "envmap":
        if not ENVMAP.exists():
            pytest.skip("envmap not present in ../shared")
        d["light"] = {"type": "envmap", "filename": str(ENVMAP)}
    elif kind == "directional":
        d["light"] = {"type": "directional", "direction": [-0.3, -1, -0.2], "irradiance": {"type": "rgb", "value": [2, 2, 2]}}
    cam = CameraPath([([0, 2.0, 3.0], [0, 0.2, 0])], frames=64, fov=50)
    return Scene(kind, mi.load_dict(d), [cam, cam, cam])


@pytest.mark.parametrize("kind", ["point", "sphere"] + [pytest.param(k, marks=pytest.mark.slow)
                                                 for k in ("constant", "envmap", "directional")])
def test_rt_matches_ground_truth_mean(kind):
    s = _scene(kind)
    gb = frame_gbuffers(s, views.single(s), 0, 64, 48)[0]
    gt = groundtruth.ground_truth(s, gb, 0, kind)
    m = methods.create("rt256", s, seed=1)
    img = gbuffer.to_image(gb, gbuffer.compose(gb, m.shade(methods.FrameContext(0), None, 0, gb)))
    assert np.isfinite(img).all() and np.isfinite(gt).all()
    valid = np.array(gb.valid).reshape(48, 64)
    a, b = img[valid].mean(), gt[valid].mean()
    assert b > 1e-3, "scene is black"
    assert abs(a - b) / b < 0.02, (kind, a, b)
