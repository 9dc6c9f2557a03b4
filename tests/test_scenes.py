"""Every built-in scene renders every method; paths, animation, rigs."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import render_frames
from slc import methods
from slc.scene import camera, checks, scenes, views

BUILTIN = scenes.builtin_names()
# every built-in scene; the fast tier (make check) loads the Cornell box only
CHECK_ONE = [n if n == "cornell" else pytest.param(n, marks=pytest.mark.slow) for n in BUILTIN]


def _load(name):
    try:
        return scenes.load(name)
    except checks.SceneError as e:  # sponza without ../shared
        pytest.skip(str(e))


def _methods():
    avail = methods.available()
    out = ["rt4"]
    for m in ("restir", "slc", "sh"):
        if m in avail:
            out.append(m)
    return out


@pytest.mark.parametrize("name", CHECK_ONE)
def test_scene_has_paths_and_materials(name):
    s = _load(name)
    assert len(s.camera_paths) >= 3
    for p in s.camera_paths[:3]:
        assert p.duration >= 4.0, (p.name, p.duration)     # at least 4 s at walking speed
        c0, c1 = p.at(0), p.at(p.n_frames // 2)
        assert np.all(np.isfinite(c0.origin)) and np.linalg.norm(c0.origin - c1.origin) + \
            np.linalg.norm(c0.target - c1.target) > 0, "camera path does not move"
    assert len(s.mi_scene.emitters()) >= 1
    if name not in ("sponza", "cornell"):
        kinds = {sh.bsdf().class_name() for sh in s.mi_scene.shapes()}
        assert kinds & {"RoughConductor", "Principled"}, kinds
        assert "SmoothDiffuse" in kinds, kinds


def _motion(path, frames, speed=1.0):
    """Per frame: distance moved (scene units) and view turn (degrees)."""
    v = camera.Viewer("v", path.at, speed=speed)
    cams = [v.camera(f) for f in frames]
    dist, turn = [], []
    for a, b in zip(cams, cams[1:]):
        fa, fb = a.basis()[0], b.basis()[0]
        dist.append(np.linalg.norm(b.origin - a.origin))
        turn.append(np.degrees(np.arctan2(np.linalg.norm(np.cross(fa, fb)), np.dot(fa, fb))))
    return np.array(dist), np.array(turn)


@pytest.mark.parametrize("name", CHECK_ONE)
def test_paths_move_at_walking_speed(name):
    """Every path of every built-in scene: at most 1.4 m/s and 30 deg/s at
    60 Hz in every frame, walking speed (within 10%) wherever the view does
    not turn near its limit, also past the path's end (it runs back)."""
    s = _load(name)
    step = camera.WALK_SPEED * s.unit / camera.FPS
    max_turn = camera.TURN_RATE / camera.FPS
    for p in s.camera_paths:
        frames = list(range(0, p.n_frames + 120, 3))
        d, t = _motion(p, [f + k for f in frames for k in (0, 1)][::1])
        d, t = d[::2], t[::2]           # consecutive pairs (f, f + 1)
        assert d.max() <= 1.02 * step, (p.name, d.max() / step)
        assert t.max() <= 1.05 * max_turn, (p.name, t.max() / max_turn)
        free = t < 0.5 * max_turn
        if len(p.keys) > 1 and free.any():
            assert np.median(d[free]) >= 0.9 * step, (p.name, np.median(d[free]) / step)


def test_camera_speed_multiplier():
    s = _load("atrium")
    v1 = views.single(s)[0]
    for k in (0.25, 0.5, 2.0, 4.0):
        vk = views.at_speed([v1], k)[0]
        for f in (0, 8, 40):
            a, b = vk.camera(f), v1.camera(f * k)
            assert np.allclose(a.origin, b.origin) and np.allclose(a.target, b.target)
        d, _ = _motion(s.camera_paths[0], [100, 101], speed=k)
        d1, _ = _motion(s.camera_paths[0], [100 * k, 100 * k + k])
        assert np.isclose(d[0], d1[0])
    with pytest.raises(ValueError):
        views.at_speed([v1], 0.0)
    # the scene's own animation keeps its clock
    s.set_frame(30)
    assert s.time == 30 / camera.FPS


def test_paths_are_deterministic():
    a, b = _load("atrium"), _load("atrium")
    for pa, pb in zip(a.camera_paths, b.camera_paths):
        for f in (0, 17, 333, 5000):
            assert np.array_equal(pa.at(f).origin, pb.at(f).origin)
            assert np.array_equal(pa.at(f).target, pb.at(f).target)


@pytest.mark.parametrize("name", CHECK_ONE)
def test_every_method_renders_finite_and_deterministic(name, monkeypatch):
    """Check mode on: every stage output finite, every returned image finite and
    >= 0 (raw values, nothing clamped), a lit image, the same images twice."""
    from slc.core import check
    monkeypatch.setenv(check.ENV, "1")
    s = _load(name)
    vs = views.single(s)
    for spec in _methods():
        imgs = []
        for _ in range(2):
            m = methods.create(spec, s, seed=3)
            out, _ = render_frames(s, m, vs, frames=3, width=48, height=27, seed=3, start=5)
            imgs.append(out[0])
        assert np.isfinite(imgs[0]).all(), (name, spec)
        assert imgs[0].max() > 0, (name, spec, "black image")
        assert np.array_equal(imgs[0], imgs[1]), (name, spec, "not deterministic")


@pytest.mark.slow
@pytest.mark.fresh_process
def test_animation_does_not_recompile_kernels():
    dyn = [n for n in BUILTIN if n in ("street", "hangar")]
    if not dyn:
        pytest.skip("no dynamic built-in scene")
    s = _load(dyn[0])
    assert s.dynamic
    m = methods.create("rt4", s)
    vs = views.single(s)
    render_frames(s, m, vs, frames=2, width=32, height=18)
    p0 = np.array(s.mi_scene.shapes()[0].bbox().min)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        render_frames(s, m, vs, frames=3, width=32, height=18, start=2)
        fresh = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit")]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert fresh == [], f"{len(fresh)} kernels compiled while animating"
    # and something did move
    moved = False
    for a in s.animated:
        moved |= not np.allclose(a.transform(0.0), a.transform(1.0))
    assert moved and np.all(np.isfinite(p0))


def test_rigs():
    s = _load("cornell")
    st = views.stereo(s, 2)
    assert len(st) == 4
    l, r = st[0].camera(3), st[1].camera(3)
    assert abs(np.linalg.norm(l.origin - r.origin) - 0.064 * s.unit) < 1e-9
    same = views.overlap_rig(s, 4, 1.0)
    assert all(np.allclose(v.camera(2).target, same[0].camera(2).target) for v in same)
    fan = views.overlap_rig(s, 3, 0.5)
    assert not np.allclose(fan[1].camera(0).target, fan[0].camera(0).target)
    meet = views.meeting(s, 8)
    for v in meet:
        c = v.camera(0)
        f, _, _ = c.basis()
        to_c = s.meeting_center - c.origin
        assert np.dot(f, to_c / np.linalg.norm(to_c)) > 0.999
    ind = views.independent(s, 5)
    assert len({tuple(np.round(v.camera(10).origin, 6)) for v in ind}) == 5


# ----------------------------------------------------------------------------- bad input: degenerate cameras

def test_degenerate_cameras_raise_one_line_scene_errors():
    """target == origin would give NaN in Camera.basis (and an image of
    NaN rays); a zero or >= 180 degree field of view would render garbage. Each
    is a SceneError with one line naming the problem; a view straight along
    the up axis (a legitimate pose of a path) gets a finite orthonormal basis."""
    from slc.scene.camera import Camera, CameraPath
    from slc.scene.checks import SceneError
    with pytest.raises(SceneError, match="degenerate camera.*no view direction") as e:
        Camera(np.array([0.0, 1.0, 3.0]), np.array([0.0, 1.0, 3.0])).basis()
    assert "\n" not in str(e.value)
    with pytest.raises(SceneError, match="key 1 looks at its own origin"):
        CameraPath([([0, 1, 3], [0, 0, 0]), ([1, 1, 1], [1, 1, 1])], fov=45)
    for fov in (0.0, -10.0, 180.0, float("nan")):
        with pytest.raises(SceneError, match="field of view"):
            CameraPath([([0, 1, 3], [0, 0, 0])], fov=fov)
    with pytest.raises(SceneError, match="not two finite 3D points"):
        CameraPath([([0, float("inf"), 3], [0, 0, 0])], fov=45)
    f, r, u = Camera(np.array([0.0, 3.0, 0.0]), np.array([0.0, 0.0, 0.0])).basis()   # looking straight down
    B = np.stack([f, r, u])
    assert np.all(np.isfinite(B)) and np.allclose(B @ B.T, np.eye(3), atol=1e-12)


def test_scene_without_shapes_raises():
    """A scene with emitters only has nothing to shade: one-line SceneError
    from the Scene itself (XML and .py scenes alike)."""
    from slc.scene.builder import SceneBuilder
    from slc.scene.camera import CameraPath
    from slc.scene.checks import SceneError
    b = SceneBuilder("emitters_only")
    b.add_point_light([0, 2, 0], [10.0] * 3)
    with pytest.raises(SceneError, match="no shapes"):
        b.build([CameraPath([([0, 1, 3], [0, 0, 0])], fov=45)])


@pytest.mark.slow
def test_sponza_shape_order_is_the_same_in_every_process():
    """Mitsuba's XML loader returns sponza's merged meshes in an order that changes
    from run to run; the cache layout and its keys follow the shape order, so
    ``scenes/sponza.py`` numbers the shapes in a fixed order. Two processes must
    see the same shapes in the same order (it differed before the fix)."""
    if not (scenes.SHARED_DIR / "scenes" / "sponza" / "sponza.xml").exists():
        pytest.skip("sponza needs ../shared/scenes/sponza")
    outs = [o[0] for o in _sponza_orders_in_three_processes()]
    assert outs[0] == outs[1] == outs[2]


_SPONZA_ORDERS = []


def _sponza_orders_in_three_processes() -> list[list[str]]:
    """In three fresh processes (run once per pytest session, shared by the two tests below):
    the shapes of the built-in sponza in order, and those of its XML file loaded with
    ``load_xml``, as two printed lines per process."""
    if not _SPONZA_ORDERS:
        import subprocess
        import sys
        from pathlib import Path
        xml = scenes.SHARED_DIR / "scenes" / "sponza" / "sponza.xml"
        code = ("from slc.core import backend; backend.init(); from slc.scene import scenes\n"
                "s = scenes.load('sponza'); print('ORDER', [(sh.id(), sh.face_count()) for sh in s.mi_scene.shapes()])\n"
                f"s = scenes.load_xml({str(xml)!r})\n"
                "print('ORDER', [(sh.id(), sh.primitive_count(), sh.class_name()) for sh in s.mi_scene.shapes()], "
                "len(s.mi_scene.emitters()), len(s.mi_scene.sensors()))\n")
        root = Path(__file__).resolve().parents[1]
        for _ in range(3):
            out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True)
            _SPONZA_ORDERS.append([ln for ln in out.stdout.splitlines() if ln.startswith("ORDER ")])
            assert len(_SPONZA_ORDERS[-1]) == 2, out.stdout[-2000:]
    return _SPONZA_ORDERS


@pytest.mark.slow
def test_xml_scene_shape_order_is_the_same_in_every_process():
    """The same problem for any user XML scene loaded with ``load_xml``
    (``slc render --scene my.xml``): three processes must see the same shapes
    in the same order. Loaded with plain ``mi.load_file`` the
    order differed between processes (``load_xml`` turns Mitsuba's mesh
    merging off, which returned the merged meshes in a varying order)."""
    xml = scenes.SHARED_DIR / "scenes" / "sponza" / "sponza.xml"
    if not xml.exists():
        pytest.skip("needs ../shared/scenes/sponza")
    outs = [o[1] for o in _sponza_orders_in_three_processes()]
    assert outs[0] == outs[1] == outs[2]


_VALUE_XML = """<scene version="3.0.0">
  <shape type="rectangle">{bsdf}</shape>
  <shape type="sphere"><point name="center" x="0" y="0" z="2"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="{radiance}"/></emitter></shape>
  {emitter}
</scene>"""
_NAN_TEXTURE = ('<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                '<string name="filename" value="nan.exr"/></texture></bsdf>')


@pytest.mark.parametrize("case,words", [
    (dict(radiance="nan, 1, 1"), ["area light", "#1 (Sphere)", "NaN", "'radiance.value'"]),
    (dict(radiance="-1, 1, 1"), ["area light", "negative value -1", "'radiance.value'"]),
    (dict(emitter='<emitter type="point"><point name="position" x="0" y="1" z="0"/>'
                  '<rgb name="intensity" value="inf"/></emitter>'), ["emitter (PointLight)", "Inf", "intensity"]),
    (dict(emitter='<emitter type="constant"><rgb name="radiance" value="-0.5"/></emitter>'),
     ["ConstantBackgroundEmitter", "negative value -0.5"]),
    (dict(bsdf='<bsdf type="diffuse"><rgb name="reflectance" value="0.5, nan, 0.5"/></bsdf>'),
     ["BSDF (SmoothDiffuse) of shape #0 (Rectangle)", "NaN", "'reflectance.value'"]),
    (dict(bsdf='<bsdf type="roughconductor"><float name="alpha" value="-0.1"/></bsdf>'),
     ["RoughConductor", "negative value -0.1", "'alpha.value'"]),
    (dict(bsdf=_NAN_TEXTURE), ["SmoothDiffuse", "NaN", "'reflectance.data'"]),
], ids=["nan-radiance", "negative-radiance", "inf-point-light", "negative-environment", "nan-reflectance",
        "negative-roughness", "nan-bitmap-texel"])
def test_bad_light_and_material_values_refused_at_load(tmp_path, case, words):
    """Non-finite or negative emitter, BSDF and texture values are refused when the
    scene loads, with one line naming the object, the parameter and the value."""
    texels = np.full((4, 4, 3), 0.5, np.float32)
    texels[1, 2, 0] = np.nan
    mi.Bitmap(texels).write(str(tmp_path / "nan.exr"))
    xml = tmp_path / "bad.xml"
    xml.write_text(_VALUE_XML.format(**{"bsdf": '<bsdf type="diffuse"/>', "radiance": "5", "emitter": "", **case}))
    with pytest.raises(checks.SceneError) as e:
        scenes.load(str(xml))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("scene 'bad'"), msg
    for w in words:
        assert w in msg, (w, msg)


def test_signed_bump_map_heights_load(tmp_path):
    """A bump map's heights are signed: only their finiteness is checked (every
    built-in scene loads through the same check in the tests above)."""
    mi.Bitmap(np.linspace(-1, 1, 16, dtype=np.float32).reshape(4, 4, 1)).write(str(tmp_path / "h.exr"))
    bump = ('<bsdf type="bumpmap"><texture type="bitmap"><boolean name="raw" value="true"/>'
            '<string name="filename" value="h.exr"/></texture><bsdf type="diffuse"/></bsdf>')
    xml = tmp_path / "bump.xml"
    xml.write_text(_VALUE_XML.format(bsdf=bump, radiance="5", emitter=""))
    assert scenes.load(str(xml)).mi_scene is not None


def test_scene_options_are_declared_and_unknown_ones_refused():
    """A built-in scene's name carries only the options its build reads (``OPTIONS`` or named
    parameters): a misspelt option is a one-line error, not a scene rendered with the default."""
    import re
    for name in scenes.builtin_names():
        definition = scenes._import_definition(scenes.SCENES_DIR / f"{name}.py")
        src = (scenes.SCENES_DIR / f"{name}.py").read_text()
        read = set(re.findall(r"options(?:\.get\(|\[)\"(\w+)\"", src))
        assert read <= set(scenes.scene_options(definition)), (name, read)
    with pytest.raises(checks.SceneError, match=r"unknown option 'light' for scene 'hangar' \(its options: lights, "):
        scenes.load("hangar:light=3")
    with pytest.raises(checks.SceneError, match=r"unknown option 'exposure' for scene 'box_export' \(its options: none"):
        scenes.load("box_export:exposure=2")
    with pytest.raises(checks.SceneError, match=r"unknown option 'foo' for scene 'cornell' \(its options: variant\)"):
        scenes.load("cornell:foo=1")
