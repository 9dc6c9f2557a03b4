"""osc-gi session gi10: the stochastic bilinear lookup of the hemisphere texels (``trilinear``)
and sharp reflections by BSDF rays into the secondary cells (``sharp``)."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import slc.backend  # noqa: F401
from slc import methods, references, views
from slc.methods import FrameContext
from slc.oscgi import HemiGrid
from slc.pipeline import gbuffers_for
from slc.scenes import CameraPath, SceneBuilder, diffuse, rough_conductor
from slc.timing import NullTimer


def test_stochastic_texel_is_unbiased_for_the_bilinear_blend():
    """The texel chosen by ``HemiGrid.texel_stochastic`` (one per uniform u) has, over many u,
    the mean of the bilinear blend of the 4 texels around the direction (clamped at the grid's
    edge), computed here in numpy from ``bilinear``; and the chosen texel is always one of them."""
    G = HemiGrid(8)
    rng = np.random.default_rng(3)
    vals = rng.uniform(0.0, 1.0, G.n)
    n_dir, n_u = 200, 4000
    sq = rng.uniform(0.0, 1.0, (n_dir, 2))
    d = mi.warp.square_to_cosine_hemisphere(mi.Point2f(np.repeat(sq[:, 0], n_u), np.repeat(sq[:, 1], n_u)))
    u = mi.Point2f(rng.uniform(0.0, 1.0, n_dir * n_u), rng.uniform(0.0, 1.0, n_dir * n_u))
    t = np.array(G.texel_stochastic(d, u)).reshape(n_dir, n_u)
    mean = vals[t].mean(axis=1)
    i0, j0, fx, fy = (np.array(a)[::n_u] for a in G.bilinear(d))
    blend = np.zeros(n_dir)
    for a in (0, 1):
        for b in (0, 1):
            w = (fx if a else 1.0 - fx) * (fy if b else 1.0 - fy)
            k = np.clip(j0 + b, 0, 7) * 8 + np.clip(i0 + a, 0, 7)
            blend += w * vals[k]
            # every chosen texel is one of the footprint's 4
    allowed = np.stack([np.clip(j0 + b, 0, 7) * 8 + np.clip(i0 + a, 0, 7) for a in (0, 1) for b in (0, 1)], 1)
    assert all(np.isin(t[r], allowed[r]).all() for r in range(n_dir))
    # standard error of a mean of n_u draws of values in [0, 1]: <= 0.5 / sqrt(n_u) = 0.0079
    assert np.abs(mean - blend).max() < 5 * 0.5 / math.sqrt(n_u), np.abs(mean - blend).max()
    # the nearest texel differs from the blend (the test would not see a missing interpolation)
    nearest = vals[np.array(G.texel(d))[::n_u]]
    assert np.abs(nearest - blend).mean() > 0.05


def _mirror_scene():
    """A near-mirror aluminium floor (GGX alpha 0.01, z in [-0.8, 2]) in front of a wall (z = -2)
    of 4 vertical stripes, white and black, lit by a quad facing the wall from z = -1 (no light
    reaches the mirror from it: no caustics); the camera sees the stripes reflected in the floor."""
    b = SceneBuilder("mirror_stripes")
    b.add_quad([0, 0, 0.6], [2, 0, 0], [0, 0, -1.4], bsdf=rough_conductor(0.01, "Al"), name="mirror")
    for s in range(4):
        b.add_quad([-1.5 + s, 1.0, -2.0], [0.5, 0, 0], [0, 1.0, 0], bsdf=diffuse([0.8] * 3 if s % 2 else [0.02] * 3),
                   name=f"stripe{s}")
    b.add_quad([0, 1.6, -1.0], [0, 0.3, 0], [0.6, 0, 0], bsdf=diffuse([0, 0, 0]), emission=[15.0] * 3, name="light")
    cam = CameraPath([([0.0, 0.7, 2.2], [0.0, 0.1, -1.0]), ([0.0, 0.7, 2.2], [0.0, 0.1, -1.0])], frames=2, fov=50)
    return b.build([cam])


def _indirect_error(s, spec, frames=10, w=48, h=32):
    m = methods.create(spec, s, seed=0)
    v = views.single(s)
    for f in range(frames):
        gbs = gbuffers_for(s, v, 0, w, h)
        out = m.render(FrameContext(f), gbs, NullTimer())
    img = references.image_of(m.output, gbs[0], out[0])
    ref = references.reference_for("indirect", s, gbs[0], 0, "test", spp=256, bounces=references.reference_bounces(m))
    assert np.isfinite(img).all()
    return np.abs(img - ref).mean() / ref.mean(), img.mean() / ref.mean()


@pytest.mark.slow
def test_sharp_reflections_resolve_a_mirrored_wall():
    """The mirror floor reflects the striped wall: read from the entries' 8x8 texels the
    stripes blur (each texel spans ~11 degrees); BSDF rays into the wall's cells (``sharp``)
    resolve them: the mean absolute error of the indirect light against the 256-path reference
    falls by at least a quarter, and the mean stays within 15% of the reference."""
    s = _mirror_scene()
    off, _ = _indirect_error(s, "osc-gi:output=indirect")
    on, mean_on = _indirect_error(s, "osc-gi:output=indirect,sharp=0.05")
    assert on < 0.75 * off, (on, off)
    assert abs(mean_on - 1.0) < 0.15, mean_on
