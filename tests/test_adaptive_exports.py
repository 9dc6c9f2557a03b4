"""adaptive (and the SH caches) on scenes written as exporters write them (scenes/*_export.py):
two-sided walls whose normals face away from the light, mirrored meshes whose geometric
normals point inwards, smooth plastic under an environment map. Each test measures a
shape's mean against the 2048-sample ground truth at the same G-buffer points; the figures
measured are in the docstrings, the bounds fail the faults they were written for."""
import numpy as np
import pytest

from slc import methods
from slc.core import check
from slc.core.timing import NullTimer
from slc.methods import FrameContext
from slc.reference.groundtruth import ground_truth
from slc.scene.gbuffer import frame_gbuffers
from slc.scene import views

W, H = 64, 36


def _run(scene, spec, frames, path=0):
    """(G-buffer, image N x 3, ground truth N x 3) of ``spec`` after ``frames`` frames of
    viewer ``path``, in check mode."""
    m = methods.create(spec, scene, seed=3)
    vs = views.single(scene, path)
    for f in range(frames):
        gb = frame_gbuffers(scene, vs, f, W, H)[0]
        with check.scope(spec, f, [gb]):
            d = m.render(FrameContext(f), [gb], NullTimer())
            check.images(d, [gb])
    img = np.array(d[0], np.float64).T
    ref = ground_truth(scene, gb, frames - 1, vs[0].name).reshape(-1, 3).astype(np.float64)
    return gb, img, ref


def _shape_means(scene, gb, img, ref, names):
    """{shape id: (method mean luminance, ground-truth mean luminance, pixels)}."""
    idx = np.array(gb.shape_index)
    ok = np.array(gb.valid)
    ids = [sh.id() for sh in scene.mi_scene.shapes()]
    lum = np.array([0.2126, 0.7152, 0.0722])
    out = {}
    for n in names:
        m = ok & (idx == ids.index(n))
        out[n] = (float((img[m] @ lum).mean()), float((ref[m] @ lum).mean()), int(m.sum()))
    return out


@pytest.fixture(scope="module")
def box(scene):
    return scene("box_export")


@pytest.mark.parametrize("spec", ["adaptive", "adaptive:force=sh", "sh"])
def test_two_sided_walls_facing_away_are_lit(box, spec):
    """box_export's walls and ceiling are two-sided rectangles whose normals point out of the
    box: the light reaches their back sides, which the camera sees. A cache that takes light
    only above an entry's normal rendered them black (adaptive: walls 0% of the ground truth,
    FLIP 0.58 at 320x180). Measured (64x36, 12 frames, the sweep path's frame 11): wall
    means within 3% (adaptive), 6% (SH records) of the ground truth; bound 10%, and no wall
    below 0.9x."""
    gb, img, ref = _run(box, spec, 12)
    walls = _shape_means(box, gb, img, ref, ["back", "right", "floor"])
    for name, (a, r, n) in walls.items():
        assert n > 20 and r > 0, (name, n, r)
        assert abs(a / r - 1.0) < 0.10, (spec, name, a / r)


@pytest.fixture(scope="module")
def preview(scene):
    return scene("preview_export")


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["adaptive:force=sh", "sh"])
def test_sh_records_of_a_mirrored_mesh(preview, spec):
    """preview_export's plastic cube is placed by a mirroring matrix: its geometric normals
    point into it, its shading normals out. SH records that drop every sample below the
    geometric normal's horizon leave the cube black (0% of the ground truth); tested against
    the geometric normal turned to the shading normal's side, it carries SH's own error on smooth plastic under a sun, as the plastic sphere beside it does.
    Measured (64x36, 12 frames): cube 1.32x (adaptive:force=sh) and 1.34x (sh) the ground
    truth's mean, sphere 1.14x and 1.12x; bound: the cube within [0.7, 1.5]x."""
    gb, img, ref = _run(preview, spec, 12)
    s = _shape_means(preview, gb, img, ref, ["plastic_cube", "plastic_ball"])
    (c, rc, nc), (b, rb, nb) = s["plastic_cube"], s["plastic_ball"]
    assert nc > 20 and nb > 20
    assert 0.7 < c / rc < 1.5, (c / rc, b / rb)


@pytest.mark.slow
def test_lamp_room_walls_facing_away_are_lit(scene):
    """lamp_export's walls and ceiling are two-sided rectangles facing out of the room, lit
    from inside by a 5 cm light in a lamp shade and a ceiling panel: at 397f359 the lamp's
    light on them was missing (0% of the ground truth). Measured (64x36, 12 frames): ceiling
    +1.4%, north wall -1.9%, west wall -0.3%; bound 5%."""
    s = scene("lamp_export")
    gb, img, ref = _run(s, "adaptive", 12)
    for name, (a, r, n) in _shape_means(s, gb, img, ref, ["ceiling", "wall_n", "wall_w"]).items():
        assert n > 100 and r > 0, (name, n)
        assert abs(a / r - 1.0) < 0.05, (name, a / r)


@pytest.mark.slow
def test_hard_shadow_edges_traced_at_the_pixel(scene):
    """sun_export has one directional light: every shadow edge is hard, and one shadow ray
    per pixel is exact. A visible fraction cached per entry made the edges blocky (at
    397f359, 64x36, path 1: 89 of 1552 pixels more than 5% off, mean error 8.1%); entries a
    shadow edge crosses now have their pixels trace the light (measured: 0 pixels, mean error
    2.0e-5). Bounds: at most 0.5% of the pixels 5% off, mean error 0.1%."""
    s = scene("sun_export")
    gb, img, ref = _run(s, "adaptive", 12, path=1)
    ok = np.array(gb.valid)
    lum = np.array([0.2126, 0.7152, 0.0722])
    a, r = img[ok] @ lum, ref[ok] @ lum
    bad = np.abs(a - r) > 0.05 * np.maximum(r, r.mean())
    assert bad.sum() <= 0.005 * ok.sum(), (bad.sum(), ok.sum())
    assert np.abs(a - r).mean() < 1e-3 * r.mean()


@pytest.mark.slow
def test_glossy_floor_keeps_a_lights_highlight(scene):
    """gallery_export's floor is rough aluminium (all of its light in a glossy lobe) under a
    spot, a point light and a disk light that no VISIBILITY record lists. A record with the two
    delta lights listed shades the disk's light, its residual, as uniform radiance over the
    floor's hemisphere: the disk's highlight spread over the whole floor, 10x the ground truth
    away from it. Glossy entries with a narrow residual now need theta_glossy, and do not start
    in VISIBILITY as the majority. Measured (64x36, 12 frames, the plinths path, the floor's
    mean absolute error over its mean): 27.8 before, 0.37 now (slc 0.34); bound 0.5."""
    s = scene("gallery_export")
    gb, img, ref = _run(s, "adaptive", 12, path=1)
    ids = [sh.id() for sh in s.mi_scene.shapes()]
    m = np.array(gb.valid) & (np.array(gb.shape_index) == ids.index("floor"))
    lum = np.array([0.2126, 0.7152, 0.0722])
    a, r = img[m] @ lum, ref[m] @ lum
    assert m.sum() > 300 and r.mean() > 0, m.sum()
    assert np.abs(a - r).mean() / r.mean() < 0.5, np.abs(a - r).mean() / r.mean()
