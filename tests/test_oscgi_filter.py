"""New entries seeded from finer levels (at the end), and the spatial filter of osc-gi
(slc/methods/oscgi/spatial.py) on a field with a closed form: inside the
furnace sphere (uniform emission E, albedo rho) the incoming radiance is the same in every
direction at every point, so a correct filter (weights normalised, parallax-corrected directions
mapped to the neighbour's texels, the irradiance re-summed) keeps the mean and adds no error."""
import sys
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from slc.scene import views

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_oscgi import _run, create, furnace  # noqa: E402


@pytest.fixture(scope="module")
def sphere():
    return furnace(0.5, 1.0)


@pytest.mark.slow
@pytest.mark.parametrize("parallax", [1, 0])
def test_filter_keeps_a_uniform_field_and_lowers_its_noise(sphere, parallax):
    rho, E = 0.5, 1.0
    expect = E * rho ** 2                       # one bounce after the first reflection
    v = views.single(sphere)
    base = "osc-gi:output=indirect,bounces=1,texel_rays=16"
    _, _, raw = _run(sphere, base + ",filter_radius=0", v, 4, 32, 18)
    m, _, filt = _run(sphere, base + ",filter_radius=3", v, 4, 32, 18, parallax=bool(parallax))
    raw, filt = np.asarray(raw[0]).mean(-1), np.asarray(filt[0]).mean(-1)
    assert np.isfinite(filt).all()
    # the mean is kept (the filter is a normalised average of estimates of the same value) ...
    assert abs(filt.mean() - raw.mean()) < 0.02 * expect, (filt.mean(), raw.mean(), expect)
    assert abs(filt.mean() - expect) < 0.10 * expect, (filt.mean(), expect)
    # ... the image changes (the filter ran) and the pixel error around the closed form does not
    # grow (a wrong texel mapping would add error; measured: 0.90x of the unfiltered error, the
    # field being almost noise-free here: next-event estimation on a sphere has no variance)
    assert np.abs(filt - raw).max() > 0.0
    e_raw, e_filt = np.abs(raw - expect).mean(), np.abs(filt - expect).mean()
    assert e_filt <= e_raw, (e_filt, e_raw)


def test_new_coarser_entries_start_from_their_finer_entries():
    """Frames at 64x36, then one at 16x9 (coarser cache levels, new entries without a coarser
    seed): with ``OSCGI.seed_finer`` the new entries start from the mean of the finer entries under
    them, so that first frame is closer to the reference than a start from nothing."""
    from slc.core import check
    from slc.reference import references
    from slc.methods import FrameContext
    from slc.scene.gbuffer import frame_gbuffers
    from slc.core.timing import NullTimer
    from slc.scene.builder import diffuse_cornell
    s = diffuse_cornell()
    v = views.single(s)
    errs = {}
    for sf in (1, 0):
        m = create("osc-gi:output=indirect", s, 0, seed_finer=bool(sf))
        for f in range(8):
            m.render(FrameContext(f), frame_gbuffers(s, v, 0, 64, 36), NullTimer())
        gbs = frame_gbuffers(s, v, 0, 16, 9)
        out = m.render(FrameContext(8), gbs, NullTimer())
        img = references.image_of("indirect", gbs[0], out[0])
        ref = references.reference_for("indirect", s, gbs[0], 0, "seed_finer", spp=256, bounces=2)
        errs[sf] = float(np.abs(img - ref).mean() / ref.mean())
        if sf:
            seeded = int(dr.count(m.primary.finer_seeded)[0])
    assert seeded > 0, seeded
    assert errs[1] < errs[0], errs
