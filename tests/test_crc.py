"""CRC grid cache: voxelization, occupancy, ray marching, the occupancy
optimization being exact at shaded points, and agreement with a
path-traced reference."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc import scenes, views
from slc.crc import CRCCache, Grid
from slc.crc import volume
from slc.crc.march import visible
from slc.crc.quality import pdiff
from slc.crc.reference import indirect_diffuse
from slc.gbuffer import to_image
from slc.pipeline import gbuffers_for
from slc.timing import NullTimer

from helpers import plane_under_rect_light

W, H = 64, 36


@pytest.fixture(scope="module")
def cornell():
    return scenes.load("cornell")


def _render(scene, frames=1, **kw):
    c = CRCCache(scene, **kw)
    v = views.single(scene)
    for f in range(frames):
        gbs = gbuffers_for(scene, v, f, W, H)
        out = c.render(f, gbs, NullTimer())
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
    changes nothing at the shaded points (same per-cell random streams)."""
    kw = dict(encoding="y3co1cg1", bounces=bounces, vpls=1024, samples=16, secondary_rays=8)
    c_on, _, on = _render(cornell, occupancy=True, **kw)
    _, _, off = _render(cornell, occupancy=False, **kw)
    assert c_on.occupancy_ratio() < 0.9
    assert np.isfinite(on).all() and (on >= 0).all()
    assert on.mean() > 0
    assert np.allclose(on, off, rtol=1e-4, atol=1e-6 * off.max())


def test_against_path_traced_reference(cornell):
    """1 and 2 bounces vs the path tracer: mean indirect light per channel
    within 20%; Y3Co3Cg3 reproduces RGB3 exactly; Y3Co1Cg1 stays close."""
    kw = dict(vpls=2048, samples=32, secondary_rays=16, blend=0.5)
    _, gbs, rgb3 = _render(cornell, frames=4, encoding="rgb3", bounces=1, **kw)
    _, _, y333 = _render(cornell, frames=4, encoding="y3co3cg3", bounces=1, **kw)
    _, _, y311 = _render(cornell, frames=4, encoding="y3co1cg1", bounces=1, **kw)
    _, _, two = _render(cornell, frames=4, encoding="rgb3", bounces=2, **kw)
    gb = gbs[0]
    ref1 = to_image(gb, indirect_diffuse(cornell.mi_scene, gb, spp=128, bounces=1))
    ref2 = to_image(gb, indirect_diffuse(cornell.mi_scene, gb, spp=128, bounces=2))
    m, r1, r2 = rgb3.mean((0, 1)), ref1.mean((0, 1)), ref2.mean((0, 1))
    assert np.all(np.abs(m - r1) < 0.2 * r1), (m, r1)
    assert np.all(np.abs(two.mean((0, 1)) - r2) < 0.2 * r2), (two.mean((0, 1)), r2)
    assert np.all(r2 > r1 * 1.05) and np.all(two.mean((0, 1)) > m * 1.05)
    assert np.allclose(y333, rgb3, rtol=1e-4, atol=1e-5 * rgb3.max())
    assert not np.allclose(y311, rgb3, rtol=1e-3)
    assert abs(y311.mean() - rgb3.mean()) < 0.05 * rgb3.mean()
    assert pdiff(rgb3 * 20, rgb3 * 20) == 0.0


def test_reference_has_no_indirect_light_on_a_lone_plane():
    s = plane_under_rect_light()
    gb = gbuffers_for(s, views.single(s), 0, 32, 18)[0]
    ind = to_image(gb, indirect_diffuse(s.mi_scene, gb, spp=16, bounces=2))
    assert np.all(ind == 0.0)


def test_rays_visibility_option(cornell):
    _, _, img = _render(cornell, encoding="y3co1cg1", visibility="rays", vpls=1024, samples=16)
    assert np.isfinite(img).all() and img.mean() > 0
    with pytest.raises(ValueError):
        CRCCache(cornell, visibility="cones")
