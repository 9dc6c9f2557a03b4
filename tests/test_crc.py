"""CRC grid cache as a method: voxelization, occupancy, ray marching, the
occupancy optimization being exact at shaded points, agreement with the
indirect reference (slc.reference.references), its settings, and the pipeline
comparing it with the indirect reference."""
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc import methods

from slc.reference import references

from slc.scene import views
from slc.methods.crc import CRCCache, Grid
from slc.methods.crc import volume
from slc.methods.crc.march import visible
from slc.methods.crc.quality import de76_fraction, delta_e76, pdiff
from slc.methods.crc.quality import _xyz_lab_yee
from slc.scene.builder import diffuse_cornell
from slc.scene.gbuffer import frame_gbuffers, to_image
from slc.methods import FrameContext, MethodError
from slc.run.pipeline import RunConfig, run_sequence
from slc.core.timing import NullTimer

from helpers import plane_under_rect_light, slc_cli

W, H = 64, 36
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cornell(scene):
    return scene("cornell")


def _render(scene, frames=1, **kw):
    c = methods.create("crc", scene, **kw)
    v = views.single(scene)
    for f in range(frames):
        gbs = frame_gbuffers(scene, v, f, W, H)
        out = c.render(FrameContext(f), gbs, NullTimer())
    return c, gbs, to_image(gbs[0], out[0])


def test_voxelization_covers_plane_and_nothing_else():
    s = plane_under_rect_light(plane_half=1.0)
    grid = Grid.around(s.bbox_min, s.bbox_max, 8)
    geo = grid.finer()
    flags = np.array(volume.voxelize(volume.scene_triangles(s.mi_scene), geo))
    nx, ny, nz = geo.dims
    ids = np.nonzero(flags)[0]
    iy = (ids // nx) % ny
    yc = geo.lo[1] + (iy + 0.5) * geo.h
    # every set voxel touches the plane y = 0 or the light y = 1
    assert np.all(np.minimum(np.abs(yc), np.abs(yc - 1.0)) <= geo.h)
    # every point of the plane lies in a set voxel
    rng = np.random.default_rng(0)
    p = np.stack([rng.uniform(-1, 1, 2000), np.zeros(2000), rng.uniform(-1, 1, 2000)], 1)
    v = np.floor((p - geo.lo) / geo.h).astype(int)
    assert flags[(v[:, 2] * ny + v[:, 1]) * nx + v[:, 0]].all()


def test_scene_triangles_of_rectangles_by_matrix_and_analytic_shapes():
    """Shapes as exported scenes write them: a rectangle placed by a mirroring, non-uniformly
    scaling matrix (a mesh whose positions are not among its traversed parameters), a sphere
    and a disk (analytic). Every one gives triangles on its surface with its closed-form area."""
    M = mi.ScalarTransform4f([[-2.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.5, 2.0], [0.0, -3.0, 0.0, -1.0], [0, 0, 0, 1]])
    sc = mi.load_dict({"type": "scene",
                       "rect": {"type": "rectangle", "to_world": M},
                       "ball": {"type": "sphere", "center": [0.0, 5.0, 0.0], "radius": 0.5},
                       "disk": {"type": "disk", "to_world": mi.ScalarTransform4f().translate([0.0, -3.0, 0.0])
                                .rotate([1.0, 0.0, 0.0], 90.0).scale(0.25)}})
    tris = volume.scene_triangles(sc)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    c = tris.mean(axis=1)
    rect, ball, disk = np.abs(c[:, 1] - 2.0) < 1e-6, np.abs(c[:, 1] - 5.0) < 0.6, np.abs(c[:, 1] + 3.0) < 1e-5
    assert (rect | ball | disk).all() and rect.any() and ball.any() and disk.any()
    assert np.isclose(area[rect].sum(), 4.0 * 6.0, rtol=1e-5)      # edges 2 x 2, scaled by 2 and 3
    assert abs(area[ball].sum() / (4 * np.pi * 0.25) - 1.0) < 0.01
    assert abs(area[disk].sum() / (np.pi * 0.0625) - 1.0) < 0.01
    r = np.linalg.norm(tris[ball].reshape(-1, 3) - [0.0, 5.0, 0.0], axis=1)
    assert np.allclose(r, 0.5, rtol=1e-4)


def test_dilation_of_one_cell():
    grid = Grid(lo=np.zeros(3), h=1.0, dims=(5, 6, 7))
    occ = dr.zeros(mi.UInt32, grid.n_cells)
    dr.scatter(occ, mi.UInt32(1), grid.flat(mi.Vector3i(2, 3, 3)))
    d = np.array(volume.dilate(occ, grid))
    assert d.sum() == 27
    corner = dr.zeros(mi.UInt32, grid.n_cells)
    dr.scatter(corner, mi.UInt32(1), mi.UInt32(0))
    assert np.array(volume.dilate(corner, grid)).sum() == 8  # clipped at the border


def test_march_visibility_agrees_with_rays(cornell):
    c = CRCCache(cornell, resolution=16)
    c._voxelize()
    rng = np.random.default_rng(1)
    n = 4000
    a = rng.uniform([-0.95, 0.05, -0.95], [0.95, 1.95, 0.95], size=(n, 3))
    b = rng.uniform([-0.95, 0.05, -0.95], [0.95, 1.95, 0.95], size=(n, 3))
    A, B = mi.Point3f(a.T.astype(np.float32)), mi.Point3f(b.T.astype(np.float32))
    vm = np.array(visible(c.geometry, c.geo, A, B, mi.Float(0.5), mi.Bool(True), start_offset=0.0,
                          end_offset=0.0))
    d = B - A
    ray = mi.Ray3f(A, dr.normalize(d))
    ray.maxt = dr.norm(d)
    vr = ~np.array(cornell.mi_scene.ray_test(ray))
    agree = np.mean(vm == vr)
    assert 0.05 < vr.mean() < 0.95  # both outcomes occur
    assert agree > 0.9, agree


@pytest.mark.parametrize("bounces", [1, 2])
def test_occupancy_is_exact_at_shaded_points(cornell, bounces):
    """Dilation by one cell: restricting cache points to occupied cells
    changes nothing at the shaded points (per-cell keyed random streams)."""
    kw = dict(encoding="y3co1cg1", bounces=bounces, samples=16, secondary_rays=8, depth_stride=1)
    c_on, _, on = _render(cornell, occupancy=True, **kw)
    _, _, off = _render(cornell, occupancy=False, **kw)
    assert c_on.occupancy_ratio() < 0.9
    assert np.isfinite(on).all() and (on >= 0).all()     # raw output: nothing is masked
    assert on.mean() > 0
    assert np.allclose(on, off, rtol=1e-4, atol=1e-6 * off.max())


@pytest.mark.slow
def test_against_indirect_reference():
    """1 and 2 bounces vs the indirect reference on an all-diffuse Cornell
    box (CRC models diffuse reflection only: on the real box's rough-metal
    block its Lambertian reconstruction is 5-6x too bright, docs/sh-crc.md):
    mean indirect light per channel within 20%; 2 bounces add light to both.
    With the paper's defaults (RSM, 10 march samples) 1 bounce measured 2-4%
    low (light-traced VPLs the same; dense marching 12-16% low: the thick
    geometry voxels over-occlude); 2 bounces: see the comment below."""
    scene = diffuse_cornell()
    kw = dict(vpls=2048, samples=32, secondary_rays=16, blend=0.5, encoding="rgb3")
    _, gbs, one = _render(scene, frames=4, bounces=1, **kw)
    # secondary bounces with Mitsuba rays (true albedo at the hits): measured
    # 3-4% low; the march assumes a grey albedo of 0.5 (the walls are 0.73)
    # and measured 26-33% too little light here
    _, _, two = _render(scene, frames=4, bounces=2, visibility="rays", **kw)
    gb = gbs[0]
    ref1 = to_image(gb, references.indirect_light(scene.mi_scene, gb, spp=128, bounces=1))
    ref2 = to_image(gb, references.indirect_light(scene.mi_scene, gb, spp=128, bounces=2))
    m, m2, r1, r2 = one.mean((0, 1)), two.mean((0, 1)), ref1.mean((0, 1)), ref2.mean((0, 1))
    assert np.all(np.abs(m - r1) < 0.2 * r1), (m, r1)
    assert np.all(np.abs(m2 - r2) < 0.2 * r2), (m2, r2)
    assert np.all(r2 > r1 * 1.05) and np.all(m2 > m * 1.05)


def test_encodings(cornell):
    """Y3Co3Cg3 reproduces RGB3 and Y2Co2Cg2 reproduces RGB2 exactly (a
    linear transform of the same bands); Y3Co1Cg1 differs but keeps the mean
    within 5%."""
    kw = dict(vpls=2048, samples=32, secondary_rays=16, blend=0.5, bounces=1)
    _, _, rgb3 = _render(cornell, frames=4, encoding="rgb3", **kw)
    _, _, y333 = _render(cornell, frames=4, encoding="y3co3cg3", **kw)
    _, _, y311 = _render(cornell, frames=4, encoding="y3co1cg1", **kw)
    assert np.allclose(y333, rgb3, rtol=1e-4, atol=1e-5 * rgb3.max())
    _, _, rgb2 = _render(cornell, frames=2, encoding="rgb2", **kw)
    _, _, y222 = _render(cornell, frames=2, encoding="y2co2cg2", **kw)
    assert np.allclose(y222, rgb2, rtol=1e-4, atol=1e-5 * rgb2.max())
    assert not np.allclose(rgb2, rgb3, rtol=1e-3)
    assert not np.allclose(y311, rgb3, rtol=1e-3)
    assert abs(y311.mean() - rgb3.mean()) < 0.05 * rgb3.mean(), (y311.mean((0, 1)), rgb3.mean((0, 1)))


def test_de76_fraction_counts_pixels_above_one_jnd():
    """The simpler measure: grey 0.18 (L* = 49.5) against grey steps of +10%
    (dE76 = 2.11, below one JND) and +12% (2.52, above; dE76 of a grey step
    is the change of L*)."""
    img = np.full((8, 8, 3), 0.18, np.float32)
    test = img.copy()
    test[:2] *= 1.10
    test[2:5] *= 1.12
    de = delta_e76(img, test)
    assert 2.0 < de[:2].min() and de[:2].max() < 2.3 and 2.3 < de[2:5].min() < 2.6
    assert de76_fraction(img, test) == pytest.approx(3 / 8 * 100)
    assert de76_fraction(img, img * 1.10) == 0.0 and de76_fraction(img, img * 1.12) == 100.0


def test_pdiff_on_images_with_known_differences():
    """Yee's PerceptualDiff (the paper's pdiff) on constructed pairs, grey
    0.5 = 50 cd/m^2 (threshold versus intensity there: 3.2 cd/m^2):
    identical images -> 0; a 16 x 16 block (6.25% of the pixels) at twice
    the luminance -> exactly those pixels; a uniform +5% (2.5 cd/m^2) is
    below the threshold and +10% (5 cd/m^2) above it, but the same +10% on
    a high-contrast random texture is masked; an equal-luminance colour
    shift fails only when (da*^2 + db*^2) exceeds the threshold elevation
    (>= 1): da* = 0.27 passes, da* = 1.36 fails."""
    img = np.full((64, 64, 3), 0.5)
    assert pdiff(img, img) == 0.0
    block = img.copy()
    block[8:24, 8:24] *= 2.0
    assert pdiff(img, block) == pytest.approx(6.25)
    assert pdiff(block, img) == pytest.approx(6.25)
    assert pdiff(img, img * 1.05) == 0.0 and pdiff(img, img * 1.10) == 100.0
    tex = np.repeat(np.random.default_rng(0).choice([0.1, 0.9], size=(64, 64))[..., None], 3, 2)
    assert pdiff(tex, tex * 1.10) == 0.0
    k = 0.297361 / 0.627355                    # d(R, G) along which Adobe-RGB Y is constant
    for d, want in ((0.002, 0.0), (0.01, 6.25)):
        shift = img.copy()
        shift[8:24, 8:24] += np.array([d, -d * k, 0.0])
        (lab0, y0), (lab1, y1) = _xyz_lab_yee(img), _xyz_lab_yee(shift)
        assert np.allclose(y0, y1, atol=1e-12)
        assert pdiff(img, shift) == pytest.approx(want)
    with pytest.raises(ValueError):
        pdiff(img, img[:32])


def test_reference_has_no_indirect_light_on_a_lone_plane():
    s = plane_under_rect_light()
    gb = frame_gbuffers(s, views.single(s), 0, 32, 18)[0]
    ind = to_image(gb, references.indirect_light(s.mi_scene, gb, spp=16, bounces=2))
    assert np.all(ind == 0.0)


def test_rays_visibility_option():
    """Visibility by Mitsuba rays instead of the voxel march, one frame on the
    all-diffuse Cornell box against a 64-spp indirect reference: the image mean per
    channel within 15% and relMSE below 0.03. Measured: +7.6 / +2.8 / +10.3%, relMSE
    0.0199 (the march: +2.2 / +3.6 / +14.6%, 0.0187)."""
    from slc.reference.metrics import rel_mse
    scene = diffuse_cornell()
    _, gbs, img = _render(scene, encoding="y3co1cg1", visibility="rays", vpls=1024, samples=16)
    ref = to_image(gbs[0], references.indirect_light(scene.mi_scene, gbs[0], spp=64, bounces=1))
    ratio = img.mean((0, 1)) / ref.mean((0, 1))
    assert np.all(np.abs(ratio - 1) < 0.15) and rel_mse(ref, img) < 0.03, (ratio, rel_mse(ref, img))


@pytest.mark.parametrize("spec,words", [
    ("crc:visibility=cones", ["visibility", "march, rays"]), ("crc:encoding=bogus", ["encoding"]),
    ("crc:bounces=0", ["bounces"]), ("crc:resolution=1", ["resolution"]), ("crc:blend=abc", ["blend"]),
    ("crc:samples=-4", ["samples"]), ("crc:occupancy=maybe", ["occupancy"]), ("crc:vpl=5", ["unknown"])])
def test_bad_settings_are_refused(cornell, spec, words):
    with pytest.raises(MethodError) as e:
        methods.create(spec, cornell)
    msg = str(e.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_bad_setting_through_the_experiment_is_one_line(tmp_path):
    out = tmp_path / "out"
    r = slc_cli(["run", "crc", "--quick", "--scene", "cornell", "--methods", "crc:encoding=bogus", "--out", out])
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "encoding" in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert not (out / "crc").exists()


def test_pipeline_compares_crc_with_the_indirect_reference(cornell):
    """run_sequence picks the reference by the method's output: for crc the
    indirect reference of its own bounce count, not the direct ground truth."""
    m = methods.create("crc:bounces=2,vpls=512,samples=8,secondary_rays=4", cornell)
    assert m.output == "indirect"
    cfg = RunConfig(width=32, height=18, frames=2, warmup=1, ref_spp=16)
    r = run_sequence(cornell, m, views.single(cornell), cfg)
    (im,) = r.images.values()
    gb = frame_gbuffers(cornell, views.single(cornell), 1, 32, 18)[0]
    ind = references.reference_for("indirect", cornell, gb, 1, gb.viewer, spp=16, bounces=2)
    direct = references.reference_for("direct", cornell, gb, 1, gb.viewer, spp=16)
    assert np.array_equal(im["gt"], ind)
    assert not np.allclose(im["gt"], direct)
    assert np.isfinite(im["img"]).all() and "flip" in r.metrics


def test_render_gt_uses_the_reference_of_the_output_kind(tmp_path):
    """``slc render --gt`` with an indirect method compares it with the
    indirect reference (and says so), not with the direct ground truth, and the
    figures it writes are the measured ones."""
    out = tmp_path / "r"
    r = slc_cli(["render", "--scene", "cornell", "--method", "crc:vpls=256,samples=4", "--res", "32x18",
                 "--frames", "2", "--warmup", "1", "--gt", "--out", out])
    assert r.returncode == 0, r.stderr
    assert "vs the indirect reference" in r.stdout, r.stdout
    import json
    row = json.loads((out / "timings.json").read_text())
    # measured FLIP 0.284, relMSE 0.410 (the Cornell box's rough-metal block: CRC's Lambertian
    # reconstruction is too bright there); within 1.2x
    assert row["flip"] < 0.34 and row["rel_mse"] < 0.49, row
    assert list(out.glob("*_strip.png"))


def test_halton_rectangle_and_paper_stride(cornell):
    """The precomputed Halton points are the radical inverses (bases 2, 3);
    the default depth stride is the paper's 10 at 1 MPixel scaled by the
    frame's side (1 at 128x72, 2 at 320x180), a set stride is kept."""
    from slc.methods.crc.bounces import halton
    assert np.allclose(halton(5, 2), [0, 1 / 2, 1 / 4, 3 / 4, 1 / 8])
    assert np.allclose(halton(5, 3), [0, 1 / 3, 2 / 3, 1 / 9, 4 / 9])
    c = CRCCache(cornell, samples=8)
    assert [c.stride_for(*wh) for wh in ((128, 72), (320, 180), (1000, 1000), (8, 8))] == [1, 2, 10, 1]
    assert CRCCache(cornell, depth_stride=10).stride_for(128, 72) == 10
    h = np.array(c.transport.halton_cells)
    assert h.shape == (2, 8) and np.allclose(h[1], halton(8, 3))


def test_stages_split_by_encoding_dependence(cornell):
    """Every timed stage is either one whose work scales with the
    coefficient count or one that does not depend on the encoding."""
    from slc.core.timing import StageTimer
    m = methods.create("crc:bounces=2,samples=8,secondary_rays=4,rsm_size=16", cornell)
    t = StageTimer()
    gbs = frame_gbuffers(cornell, views.single(cornell), 0, 32, 18)
    t.begin_frame()
    m.render(FrameContext(0), gbs, t)
    t.end_frame()
    stages = set(t.frames[0]) - {"total"}
    # ("scroll" runs only with the moving volume, volume=camera: tests/test_crc_moving.py)
    assert stages == (set(CRCCache.COEFFICIENT_STAGES) | set(CRCCache.FIXED_STAGES)) - {"scroll"}
