"""Bad input gets one clear line and exit code 2, and no partial results. The commands run
in this process (helpers.slc_cli); the entry point itself (``python -m slc.run.cli``, a fresh
interpreter) runs in test_scenes_and_methods_listing and for one bad scene file."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import slc_cli

ROOT = Path(__file__).resolve().parents[1]
SLC = [sys.executable, "-m", "slc.run.cli"]


def subprocess_run(args, cwd=None):
    return subprocess.run(SLC + args, capture_output=True, text=True, cwd=cwd or ROOT, timeout=600)


run = slc_cli


NO_EMITTER_XML = """<scene version="3.0.0">
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
</scene>"""
UNSUPPORTED_XML = """<scene version="3.0.0">
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
  <emitter type="projector"><float name="scale" value="1"/></emitter>
</scene>"""
INF_LIGHT_XML = """<scene version="3.0.0">
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="inf"/></emitter></shape>
</scene>"""
EMITTERS_ONLY_XML = """<scene version="3.0.0">
  <emitter type="point"><point name="position" x="0" y="2" z="0"/><rgb name="intensity" value="10"/></emitter>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
</scene>"""


def _camera_xml(lookat, fov=45):
    return f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="{fov}"/><transform name="to_world">{lookat}</transform></sensor>
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>
</scene>"""


CAMERA_SAME_XML = _camera_xml('<lookat origin="0,1,3" target="0,1,3" up="0,1,0"/>')       # target == origin
CAMERA_UP_XML = _camera_xml('<lookat origin="0,3,0" target="0,0,0" up="0,1,0"/>')         # up along the view
CAMERA_FOV_XML = _camera_xml('<lookat origin="0,1,3" target="0,0,0" up="0,1,0"/>', fov=0)  # zero field of view


def _py_scene(paths, shapes=True):
    return ("from slc.scene.builder import SceneBuilder, diffuse\n"
            "from slc.scene.camera import CameraPath\n"
            "def build(**options):\n"
            "    b = SceneBuilder('py_bad')\n"
            + ("    b.add_quad([0, 0, 0], [1, 0, 0], [0, 0, -1], bsdf=diffuse([0.7] * 3), name='floor')\n" if shapes else "")
            + "    b.add_point_light([0, 2, 0], [10, 10, 10])\n"
            f"    return b.build([{paths}])\n")


PY_NO_SHAPES = _py_scene("CameraPath([([0, 1, 3], [0, 1, 0]), ([1, 1, 3], [0, 1, 0])], fov=45)", shapes=False)
PY_CAMERA_SAME = _py_scene("CameraPath([([0, 1, 3], [0, 1, 3]), ([1, 1, 3], [0, 1, 0])], fov=45)")
PY_CAMERA_FOV = _py_scene("CameraPath([([0, 1, 3], [0, 1, 0]), ([1, 1, 3], [0, 1, 0])], fov=0)")
NAN_LIGHT_XML = INF_LIGHT_XML.replace('value="inf"', 'value="nan, 1, 1"')
NAN_TEXTURE_XML = """<scene version="3.0.0">
  <shape type="rectangle"><bsdf type="diffuse">
    <texture type="bitmap" name="reflectance"><string name="filename" value="nan.exr"/></texture></bsdf></shape>
  <shape type="sphere"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>
</scene>"""
GOOD_XML = """<scene version="3.0.0">
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>
</scene>"""


@pytest.fixture()
def xmls(tmp_path):
    paths = {}
    for name, text in [("none", NO_EMITTER_XML), ("unsupported", UNSUPPORTED_XML), ("good", GOOD_XML), ("inf", INF_LIGHT_XML),
                       ("broken", "<scene version='3.0.0'><shape type='nonexistent_plugin'/></scene>"),
                       ("garbage", "this is < not xml"), ("emitters_only", EMITTERS_ONLY_XML),
                       ("camera_same", CAMERA_SAME_XML), ("camera_up", CAMERA_UP_XML), ("camera_fov", CAMERA_FOV_XML),
                       ("nan_light", NAN_LIGHT_XML), ("nan_texture", NAN_TEXTURE_XML)]:
        p = tmp_path / f"{name}.xml"
        p.write_text(text)
        paths[name] = p
    import mitsuba as mi
    texels = np.full((4, 4, 3), 0.5, np.float32)
    texels[1, 2, 0] = np.nan
    mi.Bitmap(texels).write(str(tmp_path / "nan.exr"))
    for name, text in [("py_no_shapes", PY_NO_SHAPES), ("py_camera_same", PY_CAMERA_SAME),
                       ("py_camera_fov", PY_CAMERA_FOV)]:
        p = tmp_path / f"{name}.py"
        p.write_text(text)
        paths[name] = p
    return paths


def _one_line_error(r, *words):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr
    for w in words:
        assert w.lower() in lines[0].lower(), lines[0]


@pytest.mark.parametrize("case,words", [
    ("missing", ["not found"]), ("none", ["no emitters"]), ("unsupported", ["projector", "not supported"]),
    ("broken", ["cannot parse"]), ("garbage", ["cannot parse"]),
    ("emitters_only", ["no shapes"]), ("py_no_shapes", ["no shapes"]),
    ("camera_same", ["degenerate camera"]), ("camera_up", ["degenerate camera"]),
    ("camera_fov", ["degenerate camera", "field of view"]),
    ("py_camera_same", ["degenerate camera", "own origin"]), ("py_camera_fov", ["degenerate camera", "field of view"]),
    ("nan_light", ["area light", "NaN", "radiance"]), ("nan_texture", ["BSDF", "NaN", "reflectance.data"])])
def test_bad_scene_files(xmls, tmp_path, case, words):
    path = tmp_path / "missing.xml" if case == "missing" else xmls[case]
    out = tmp_path / "out"
    runner = subprocess_run if case == "broken" else run
    r = runner(["run", "single-viewer", "--quick", "--scene", str(path), "--out", str(out)])
    _one_line_error(r, *words)
    assert not (out / "single-viewer" / "results.json").exists()
    assert not any(out.rglob("*")) if out.exists() else True


def test_unknown_scene_method_experiment(tmp_path):
    _one_line_error(run(["render", "--scene", "nowhere", "--out", str(tmp_path)]), "unknown scene", "nowhere")
    _one_line_error(run(["render", "--scene", "cornell", "--method", "magic", "--out", str(tmp_path)]),
                    "unknown method", "magic")
    _one_line_error(run(["run", "no-such-experiment"]), "unknown experiment")
    _one_line_error(run(["render", "--res", "banana"]), "resolution")
    _one_line_error(run(["--variant", "nonsense_rgb", "scenes"]), "variant")
    r = run(["run", "single-viewer", "--quick", "--methods", "rt4", "nope", "--out", str(tmp_path / "o")])
    _one_line_error(r, "unknown method", "nope")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args,words", [
    (["single-viewer", "--res", "0x10"], ["resolution", "0x10"]),
    (["single-viewer", "--res", "32x-2"], ["resolution", "32x-2"]),
    (["single-viewer", "--frames", "0"], ["--frames", "at least 1"]),
    (["overlap", "--viewers", "0", "4"], ["--viewers", "at least 1"]),
    (["crc", "--frames", "0"], ["--frames", "at least 1"]),
    (["crc", "--grid", "0"], ["--grid", "at least 2"])])
def test_bad_run_settings(tmp_path, args, words):
    """A size, frame count, viewer count or CRC grid below its least value stops the run with one
    line before anything is written (unchecked, a zero size fails inside every job's kernels and
    zero viewers make rows of nothing)."""
    out = tmp_path / "o"
    _one_line_error(run(["run", args[0], "--quick", *args[1:], "--out", str(out)]), *words)
    assert not out.exists()


@pytest.mark.parametrize("cmd", [["run", "single-viewer", "--quick", "--methods", "rt4"],
                                 ["render", "--scene", "cornell", "--method", "rt4"]])
@pytest.mark.parametrize("under", ["", "sub"])
def test_out_on_a_file_is_bad_input(tmp_path, cmd, under):
    """``--out`` at a file, or below one, stops with one line before anything renders."""
    f = tmp_path / "afile"
    f.write_text("kept")
    _one_line_error(run([*cmd, "--res", "16x9", "--out", str(f / under if under else f)]), "is a file, not a folder")
    assert f.read_text() == "kept" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_good_xml_scene_renders(xmls, tmp_path):
    """A plain Mitsuba XML scene renders: a diffuse (0.5) 2 x 2 m plane 2 m under a sphere
    light (radius 0.2 m, radiance 20). The plane's brightest pixel is within 3% of the
    closed form right under the light, 0.5 / pi * pi * 20 * 0.2^2 / 2^2 = 0.1 (measured
    0.0999), and FLIP against the ground truth below 0.01 (measured 0.0020)."""
    from slc.core.io import read_exr
    r = run(["render", "--scene", str(xmls["good"]), "--method", "rt4", "--res", "32x18", "--frames", "2",
             "--gt", "--out", str(tmp_path)])
    assert r.returncode == 0, r.stderr
    t = json.loads((tmp_path / "timings.json").read_text())
    assert t["method"] == "rt4" and t["time_ms"] > 0 and t["flip"] < 0.01, t
    assert list(tmp_path.glob("*.png"))
    img = read_exr(tmp_path / "good_rt4_orbit0.exr")       # (the fixture writes nan.exr beside it)
    plane = img[img.max(-1) < 1.0]               # the light itself shows at its radiance, 20
    assert abs(plane.max() / 0.1 - 1) < 0.03, plane.max()


def test_scenes_and_methods_listing():
    r = subprocess_run(["scenes"])
    assert r.returncode == 0 and "cornell" in r.stdout and "atrium" in r.stdout
    r = run(["methods"])
    assert r.returncode == 0 and "rt" in r.stdout


def test_indirect_method_refused_by_direct_light_experiment(tmp_path):
    r = run(["run", "single-viewer", "--quick", "--methods", "megaviews", "--out", str(tmp_path / "o")])
    _one_line_error(r, "indirect light")
    assert not (tmp_path / "o").exists()


def test_non_finite_light_refused_at_load_with_and_without_check(xmls, tmp_path):
    """A light of infinite radiance is refused when the scene loads (one line, exit 2,
    nothing written), with or without --check: no method runs on it."""
    args = ["render", "--scene", str(xmls["inf"]), "--method", "rt4", "--res", "32x18", "--frames", "2"]
    _one_line_error(run(args + ["--out", str(tmp_path / "raw")]), "area light", "Inf", "radiance")
    assert not (tmp_path / "raw").exists()
    _one_line_error(run(["--check"] + args + ["--out", str(tmp_path / "chk")]), "Inf", "radiance")
    assert not (tmp_path / "chk").exists()
