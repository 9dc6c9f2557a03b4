"""The cone shading returns raw values: a NaN made while shading (here by a
BSDF whose reflectance is NaN) reaches the method's image instead of being
replaced by 0, and check mode stops at the stage that made it ('shade'),
naming the method and the pixel."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.core import check

from slc import methods

from slc.scene import scenes, views
from slc.run.pipeline import RunConfig, run_sequence

W, H = 32, 18


@pytest.fixture()
def nan_floor():
    """The Cornell box with a NaN in the floor's reflectance (its own copy)."""
    s = scenes.load("cornell")
    p = mi.traverse(s.mi_scene)
    key = "floor_001.bsdf.reflectance.value"
    p[key] = mi.Color3f(float("nan"), 0.5, 0.5)
    p.update()
    return s


def _cfg():
    return RunConfig(width=W, height=H, frames=2, warmup=0, eval_frames=[], keep_images=True,
                     measure_overlap=False)


def test_nan_reaches_image_unmasked(nan_floor, monkeypatch):
    monkeypatch.delenv(check.ENV, raising=False)
    res = run_sequence(nan_floor, methods.create("slc", nan_floor), views.single(nan_floor), _cfg())
    img = np.asarray(next(iter(res.last.values())))
    red = img[..., 0].ravel()
    assert np.isnan(red).any(), "the floor's NaN reflectance was masked"
    # only the red channel of the floor is bad: the other channels stay finite
    assert np.isfinite(img[..., 1]).all() and np.isfinite(img[..., 2]).all()


def test_check_mode_stops_at_shade(nan_floor, monkeypatch):
    monkeypatch.setenv(check.ENV, "1")
    with pytest.raises(check.CheckError) as e:
        run_sequence(nan_floor, methods.create("slc", nan_floor), views.single(nan_floor), _cfg())
    msg = str(e.value)
    assert "stage 'shade'" in msg and "NaN" in msg and "pixel" in msg and "slc" in msg, msg
    assert "\n" not in msg
