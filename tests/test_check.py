"""Check mode (slc.core.check, SLC_CHECK / --check): the first NaN/Inf or negative
value raises with the method, stage and pixel; off, nothing is checked."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.core import check

from slc.scene import gbuffer, views
from slc.methods import Method
from slc.run.pipeline import RunConfig, run_sequence
from slc.core.timing import StageTimer

W, H = 24, 16
BAD_X, BAD_Y = 13, 9


class Stub(Method):
    """Returns 0.25 everywhere except one value at (BAD_X, BAD_Y) of viewer ``bad_viewer``,
    through a timed stage 'shade' (or raw, without stage outputs, when ``staged`` is False);
    :meth:`Method.render` names it and checks its images."""

    name = "stub"

    def __init__(self, scene, value=float("nan"), bad_viewer=0, staged=True, channel=1):
        super().__init__(scene)
        self.value, self.bad_viewer, self.staged, self.channel = value, bad_viewer, staged, channel

    def render_stages(self, ctx, gbuffers, timer):
        outs = []
        for v, gb in enumerate(gbuffers):
            a = np.full((gb.size, 3), 0.25, np.float32)
            if v == self.bad_viewer:
                a[BAD_Y * gb.width + BAD_X, self.channel] = self.value
            outs.append(mi.Color3f(a[:, 0], a[:, 1], a[:, 2]))
        if self.staged:
            with timer.stage("shade") as st:
                st.outputs(*outs)
        return outs


@pytest.fixture(scope="module")
def cornell(scene):
    return scene("cornell")


def _cfg(frames=2):
    return RunConfig(width=W, height=H, frames=frames, warmup=0, eval_frames=[], measure_overlap=False)


@pytest.fixture()
def check_on(monkeypatch):
    monkeypatch.setenv(check.ENV, "1")


@pytest.fixture()
def check_off(monkeypatch):
    monkeypatch.delenv(check.ENV, raising=False)


@pytest.mark.parametrize("value,kind", [(float("nan"), "NaN"), (float("inf"), "+Inf")])
def test_stage_output_nan_raises_with_pixel(cornell, check_on, value, kind):
    with pytest.raises(check.CheckError) as e:
        run_sequence(cornell, Stub(cornell, value=value), views.single(cornell), _cfg())
    msg = str(e.value)
    assert "\n" not in msg
    assert "stub" in msg and "frame 0" in msg and "stage 'shade'" in msg and kind in msg
    assert f"pixel ({BAD_X}, {BAD_Y})" in msg and f"entry {BAD_Y * W + BAD_X}" in msg


def test_image_check_names_viewer_and_negative(cornell, check_on):
    """A negative value is not an error in stage outputs (directions, SH
    coefficients are negative by nature) but it is in an image; the second
    viewer is named."""
    vs = views.overlap_rig(cornell, 2, 1.0)
    with pytest.raises(check.CheckError) as e:
        run_sequence(cornell, Stub(cornell, value=-0.5, bad_viewer=1), vs, _cfg())
    msg = str(e.value)
    assert "stage 'image'" in msg and "negative value -0.5" in msg
    assert f"viewer 1 pixel ({BAD_X}, {BAD_Y}) channel 1" in msg
    # unstaged method: the returned image is still checked
    with pytest.raises(check.CheckError, match=r"stage 'image': NaN at viewer 0 pixel \(13, 9\)"):
        run_sequence(cornell, Stub(cornell, staged=False), views.single(cornell), _cfg())


def test_check_off_does_not_raise_and_keeps_raw_values(cornell, check_off):
    """Off, the run finishes, and the NaN is not hidden: it reaches the composed image."""
    r = run_sequence(cornell, Stub(cornell), views.single(cornell), _cfg())
    img = next(iter(r.last.values()))
    assert np.isnan(img[BAD_Y, BAD_X, 1])
    assert np.isfinite(np.delete(img.reshape(-1, 3), BAD_Y * W + BAD_X, axis=0)).all()


def test_compose_is_raw(cornell):
    """compose adds the emission seen directly and keeps negative and non-finite values."""
    gb = gbuffer.render_gbuffer(cornell, views.single(cornell)[0].camera(0), W, H)
    d = np.zeros((gb.size, 3), np.float32)
    valid = np.array(gb.valid)
    i, j = np.nonzero(valid)[0][:2]
    d[i] = -1.0
    d[j] = np.inf
    out = gbuffer.to_image(gb, gbuffer.compose(gb, mi.Color3f(d[:, 0], d[:, 1], d[:, 2]))).reshape(-1, 3)
    em = gbuffer.to_image(gb, gb.emitted).reshape(-1, 3)
    assert np.allclose(out[i], em[i] - 1.0) and np.all(np.isinf(out[j]))


def test_stage_timer_checks_struct_leaves(check_on):
    """Float leaves of structs and nested lists are checked; integer and bool
    leaves are not; the stage name is in the message."""
    t = StageTimer()
    t.begin_frame()
    si = dr.zeros(mi.SurfaceInteraction3f, 4)      # t = +Inf: Mitsuba's "no hit", accepted
    si.p = mi.Point3f([0, 1, 2, 3], [0, 0, 0, 0], [0, 0, dr.nan, 0])
    with pytest.raises(check.CheckError, match=r"stage 'update': NaN in output 1\[0\]\.p\[2\] \(entry 2 of 4\)"):
        with t.stage("update") as st:
            st.outputs(mi.UInt32(0xFFFFFFFF), [si], mi.Bool(True))
    with t.stage("fine") as st:
        st.outputs(mi.UInt32(7), mi.Float(-1.0), mi.Vector3f(-1, 0, 0))


def test_env_values():
    import os
    old = os.environ.get(check.ENV)
    try:
        for v, on in (("1", True), ("yes", True), ("0", False), ("", False), ("off", False)):
            os.environ[check.ENV] = v
            assert check.enabled() is on
        check.enable(False)
        assert not check.enabled()
        check.enable()
        assert check.enabled()
    finally:
        if old is None:
            os.environ.pop(check.ENV, None)
        else:
            os.environ[check.ENV] = old


def test_ground_truth_checked(cornell, check_on, monkeypatch, tmp_path):
    """In check mode the ground-truth image is checked as well (a cached copy included)."""
    from slc.reference import groundtruth
    monkeypatch.setenv("SLC_CACHE", str(tmp_path))
    gb = gbuffer.render_gbuffer(cornell, views.single(cornell)[0].camera(0), W, H)
    groundtruth.ground_truth(cornell, gb, 0, "v", spp=16)                 # fine
    path = next((tmp_path / "gt").glob("*.npy"))
    a = np.load(path)
    a[BAD_Y, BAD_X, 2] = np.nan
    np.save(path, a)
    with pytest.raises(check.CheckError, match=r"gt frame 0 stage 'ground truth': NaN at viewer 0 pixel \(13, 9\)"):
        groundtruth.ground_truth(cornell, gb, 0, "v", spp=16)


def test_composed_image_checked(cornell, check_on, monkeypatch):
    """The image composed with the emission seen directly (what is written and
    compared) is checked too: a NaN in the emission is named at stage 'compose'."""
    from slc.reference import references
    real = references.compose

    def nan_emission(gb, value):
        out = real(gb, value)
        return dr.select(dr.arange(mi.UInt32, gb.size) == BAD_Y * gb.width + BAD_X, dr.nan, out)

    monkeypatch.setattr(references, "compose", nan_emission)
    with pytest.raises(check.CheckError, match=r"stub frame 0 stage 'compose': NaN at viewer 0 pixel \(13, 9\)"):
        run_sequence(cornell, Stub(cornell, value=0.25), views.single(cornell), _cfg())


# One method per family, and the stage whose outputs get a NaN in frame 1 (the VPL methods with
# 256 VPLs and depth-4 hierarchies: the same stages as their defaults', a tenth of the work).
_VPL = ":views=256,scene_depth=4,view_depth=4"
FAMILY_STAGES = [("rt4", "shade"), ("restir", "spatial"), ("slc", "update"), ("sh", "update"),
                 ("adaptive", "update"), ("crc", "bounce1_march"), ("osc-gi", "direct"), ("pt", "shade"),
                 ("megaviews" + _VPL, "traverse"), ("manylods" + _VPL, "push"), ("brute" + _VPL, "fuse")]


@pytest.mark.parametrize("spec,poisoned", FAMILY_STAGES, ids=[s.split(":")[0] for s, _ in FAMILY_STAGES])
def test_check_mode_sees_every_stage_of_every_method(cornell, check_on, monkeypatch, spec, poisoned):
    """Every timed stage of each method family declares its outputs to check mode, and
    a NaN in one stage's outputs stops the run naming method, frame and stage (frames
    0-1 at 12x8; the NaN is added to the stage's outputs in frame 1)."""
    from slc import methods
    from slc.core import timing
    state = {"stage": None, "frame": 0, "timed": set(), "declared": set()}
    real_stage, real_outputs = timing.StageTimer.stage, timing._Stage.outputs
    real_begin = timing.StageTimer.begin_frame

    def stage(self, name):
        state["stage"] = name
        state["timed"].add(name)
        return real_stage(self, name)

    def outputs(self, *values):
        if values:
            state["declared"].add(state["stage"])
        if state["frame"] == 1 and state["stage"] == poisoned:
            values = values + (mi.Float([0.0, dr.nan]),)
        real_outputs(self, *values)

    def begin_frame(self):
        state["frame"] = len(self.frames)
        real_begin(self)

    monkeypatch.setattr(timing.StageTimer, "stage", stage)
    monkeypatch.setattr(timing.StageTimer, "begin_frame", begin_frame)
    monkeypatch.setattr(timing._Stage, "outputs", outputs)
    m = methods.create(spec, cornell, seed=0)
    with pytest.raises(check.CheckError) as e:
        run_sequence(cornell, m, views.single(cornell),
                     RunConfig(width=12, height=8, frames=2, warmup=0, eval_frames=[], measure_overlap=False))
    msg = str(e.value)
    assert f"frame 1 stage '{poisoned}': NaN" in msg and m.name.split(":")[0] in msg, msg
    assert state["timed"] and state["timed"] <= state["declared"], (state["timed"], state["declared"])
