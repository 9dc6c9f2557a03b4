"""The meeting rig's shading speed-ups (docs/cones.md, "Per-viewer cost"): the per-scene BSDF table (``shading.bsdf_table``) and the entry frames
gathered inside the launch change no image; ``slc:conductor=sg`` (an option) shades GGX
conductor pixels in closed form within a measured error of the model's integral."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import plane_under_rect_light
from slc.lib.cones.shading import ConeShading, bsdf_table
from slc.scene.bsdf_table import KIND_DIFFUSE, KIND_NOT_PRINCIPLED, KIND_OTHER, KIND_PRINCIPLED
from slc.scene.builder import diffuse, principled, rough_conductor


def _inputs(sc):
    from test_cones import _storage_after
    return _storage_after(sc)


def _kind(sc, m):
    t = bsdf_table(sc)
    rid = dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(sc.mi_scene.shapes()[0].bsdf()))
    for sh in sc.mi_scene.shapes():
        if sh.id() == "plane" or "plane" in sh.id():
            rid = dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(sh.bsdf()))
    return int(dr.gather(mi.UInt32, t.kind, rid)[0]), t


def _bitmap():
    rgb = np.random.default_rng(1).uniform(0.1, 0.8, (8, 8, 3)).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(rgb), "raw": True}


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["diffuse", "principled", "principled_textured", "diffuse_textured", "conductor"])
def test_bsdf_table_same_images(kind):
    """Shading with the table gives the images of the virtual calls bit for bit, for
    constant BSDFs (read from the table) and textured ones (kept on the virtual calls),
    frozen or not; the table classifies them as expected."""
    b = {"diffuse": diffuse([0.5, 0.4, 0.3]),
         "principled": principled([0.45, 0.36, 0.28], roughness=0.22),
         "principled_textured": dict(principled([0.45, 0.36, 0.28], roughness=0.22), base_color=_bitmap()),
         "diffuse_textured": {"type": "diffuse", "reflectance": _bitmap()},
         "conductor": rough_conductor(0.12, "Cu")}[kind]
    sc = plane_under_rect_light(half=0.3, radiance=5.0, bsdf=b, name=f"table_{kind}")
    m, gb, slot, ok, tf = _inputs(sc)
    k, table = _kind(sc, m)
    # (a textured diffuse BSDF lacks the principled attributes: KIND_NOT_PRINCIPLED, its
    # reflectance still read through the virtual call)
    assert k == {"diffuse": KIND_DIFFUSE, "principled": KIND_PRINCIPLED,
                 "diffuse_textured": KIND_NOT_PRINCIPLED, "conductor": KIND_NOT_PRINCIPLED}.get(kind, KIND_OTHER)
    plain = np.array(ConeShading(3, freeze=False)(m.storage, slot, ok, gb.si, tf, 16, 5))
    tab = np.array(ConeShading(3, freeze=False, table=table)(m.storage, slot, ok, gb.si, tf, 16, 5))
    frozen = np.array(ConeShading(3, table=table)(m.storage, slot, ok, gb.si, tf, 16, 5))
    assert np.abs(plain).sum() > 0 and np.all(np.isfinite(plain))
    assert np.array_equal(plain, tab) and np.array_equal(plain, frozen)


def test_entry_frames_inside_the_launch():
    """Passing each pixel's entry index and the entries' frames (the gather inside the
    launch) gives the image of a frame gathered beforehand, bit for bit."""
    from slc.core.keys import INVALID
    sc = plane_under_rect_light(half=0.3, radiance=5.0, bsdf=principled([0.45, 0.36, 0.28], roughness=0.22),
                                name="entry_frames")
    m, gb, slot, ok, tf = _inputs(sc)
    fr = m.cache.begin_frame(12, [gb])
    index = mi.UInt32(fr.pixel_index[0])
    a = np.array(ConeShading(3, freeze=False)(m.storage, slot, ok, gb.si, tf, 16, 5))
    b = np.array(ConeShading(3, freeze=False)(m.storage, slot, ok, gb.si, index, 16, 5, None, fr.si.sh_frame))
    assert np.abs(a).sum() > 0 and np.array_equal(a, b)


@pytest.mark.slow
@pytest.mark.parametrize("alpha,half", [(0.12, 0.3), (0.12, 0.05), (0.3, 0.3)])
def test_conductor_sg_matches_model_integral(alpha, half):
    """A GGX copper plane (alpha 0.12 as the atrium's bronze, and 0.3) under a 0.6 m or
    0.1 m light: ``conductor=sg`` against the model's integral (mean of four 1024-direction
    MIS shadings of the same cones): image sum within 6 % and L1 within 15 % (measured:
    +4.3 / 8.6 %, +0.0 / 1.0 %, +1.6 / 5.3 %; the 16-direction quadrature's L1 4.4, 3.3,
    4.2 %); finite, the same frozen or not, and different from the quadrature."""
    sc = plane_under_rect_light(half=half, radiance=5.0, bsdf=rough_conductor(alpha, "Cu"),
                                name=f"cond_{alpha}_{half}")
    m, gb, slot, ok, tf = _inputs(sc)
    sg = np.array(ConeShading(3, freeze=False, conductor="sg")(m.storage, slot, ok, gb.si, tf, 16, 5))
    sg2 = np.array(ConeShading(3, conductor="sg")(m.storage, slot, ok, gb.si, tf, 16, 5))
    samp = ConeShading(3, freeze=False)
    s16 = np.array(samp(m.storage, slot, ok, gb.si, tf, 16, 5))
    ref = sum(np.array(samp(m.storage, slot, ok, gb.si, tf, 1024, 1 + k)) for k in range(4)) / 4
    print(f"alpha {alpha} half {half}: sg sum {sg.sum() / ref.sum():.4f} L1 {np.abs(sg - ref).sum() / ref.sum():.4f}; "
          f"16-dir L1 {np.abs(s16 - ref).sum() / ref.sum():.4f}")
    assert np.all(np.isfinite(sg)) and np.array_equal(sg, sg2)
    assert not np.array_equal(sg, s16)
    assert abs(sg.sum() / ref.sum() - 1) < 0.06, sg.sum() / ref.sum()
    assert np.abs(sg - ref).sum() / ref.sum() < 0.15, np.abs(sg - ref).sum() / ref.sum()
