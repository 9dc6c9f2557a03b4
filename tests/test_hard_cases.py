"""The hard cases (docs/hard-cases.md) for the ground truth, RT-N and ReSTIR, run in
check mode (SLC_CHECK=1: the first NaN/Inf or negative value in any stage
output or returned image raises), with error bounds against an independent
reference instead of finiteness alone:

- rectangular lights: a deterministic midpoint quadrature over the light with
  exact visibility (:func:`helpers.quadrature_direct`, 64 x 64 points; pixels
  where it has not converged, i.e. differs from a 32 x 32 quadrature by more
  than 0.1%, are left out: a few next to the grazing light and in the
  penumbra of the box);
- the hemisphere-sized light: the closed-form irradiance of a rectangle;
- the point light: the closed form I cos / d^2 (through the same quadrature);
- zero radiance: exactly 0.

Plane pixels only (y = 0; the box top for ``inside`` is excluded with the
light seen directly). Measured figures are in each test's docstring.

The second part runs ``slc`` (default settings) on the hard cases
that tests/test_cones.py does not cover: a point-like sphere light, a
light behind the surface, grazing incidence, a half-occluded large light and
a light that moves and stops (both in check mode here), more lights than
``max_cones``, a light that switches off. The table of all cases and bounds:
docs/hard-cases.md.
"""
import numpy as np
import pytest

from helpers import HARD_POINT, HARD_RECTS, hard_scene, quadrature_direct, rect_irradiance, z_test
from slc.core import check
from slc import methods
from slc.scene import views
from slc.reference.groundtruth import direct_mis
from slc.methods import FrameContext
from slc.scene.gbuffer import frame_gbuffers
from slc.core.timing import StageTimer

W, H = 48, 32
KINDS = ["grazing", "point", "hemisphere", "zero", "huge", "inside"]


@pytest.fixture(autouse=True)
def check_mode(monkeypatch):
    monkeypatch.setenv(check.ENV, "1")


_CACHE = {}


@pytest.fixture(scope="module", autouse=True)
def _release_cases():
    """The cases' scenes go with the file (tests/conftest.py: a live scene joins later kernels)."""
    yield
    _CACHE.clear()


def case(kind):
    """(scene, G-buffer, reference N x 3, mask of tested pixels)."""
    if kind in _CACHE:
        return _CACHE[kind]
    sc = hard_scene(kind)
    gb = frame_gbuffers(sc, views.single(sc), 0, W, H)[0]
    p = np.array(gb.si.p).T
    mask = np.array(gb.valid) & (np.abs(p[:, 1]) < 1e-4)
    if kind == "hemisphere":
        (c, u, v, L), = HARD_RECTS[kind].values()
        E = rect_irradiance(p[:, 0], p[:, 2], -u[0], u[0], -v[2], v[2], c[1], L)
        ref = np.repeat((0.5 / np.pi * E)[:, None], 3, axis=1)
    else:
        rects = list(HARD_RECTS.get(kind, {}).values())
        pts = [HARD_POINT] if kind == "point" else []
        ref = quadrature_direct(sc, gb, rects, pts, n=64)
        coarse = quadrature_direct(sc, gb, rects, pts, n=32)
        mask &= np.abs(ref - coarse).max(axis=1) <= 1e-3 * np.maximum(ref.max(axis=1), 1e-12)
    assert mask.sum() > 800, (kind, mask.sum())
    _CACHE[kind] = (sc, gb, ref, mask)
    return _CACHE[kind]


def render(spec, sc, gb, frames=1, seed=0):
    """Direct light of the last of ``frames`` frames (N x 3), every stage output
    and the returned image checked (check mode)."""
    m = methods.create(spec, sc, seed=seed)
    timer = StageTimer()
    for f in range(frames):
        timer.begin_frame()
        with check.scope(spec, f, [gb]):
            d = m.render(FrameContext(f), [gb], timer)
            check.images(d, [gb])
        timer.end_frame()
    return np.array(d[0], np.float64).T


def rel_errors(img, ref, mask):
    a, r = img[mask], ref[mask]
    return abs(a.mean() / r.mean() - 1.0), np.abs(a - r).mean() / r.mean()


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_ground_truth_hard_cases(kind):
    """2048 MIS samples. Measured (48x32): grazing mean -0.3%, per-pixel mean
    error 1.8%; hemisphere 0.01% / 0.3%; huge 0.00% / 0.09%; inside 0.02% / 0.44%;
    point exact (one delta light: no variance); zero exactly 0. Asserted: mean
    within 1%, per-pixel mean error below 3% (0.5% for huge and hemisphere)."""
    sc, gb, ref, mask = case(kind)
    gt = np.array(direct_mis(sc.mi_scene, gb, 2048), np.float64).T
    check.array(gt, f"ground truth ({kind})")
    if kind == "zero":
        assert np.all(gt == 0.0)
        return
    mean_err, pix_err = rel_errors(gt, ref, mask)
    assert mean_err < 0.01, (kind, mean_err)
    assert pix_err < (0.005 if kind in ("huge", "hemisphere") else 0.03), (kind, pix_err)


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "hemisphere"])
def test_rt_hard_cases_per_pixel_z_test(kind):
    """32 independent runs of rt16 (seeds 0..31) against the reference, per-pixel
    Z-test (Sidak-corrected 1% significance over all pixels and channels): an
    unbiased estimator must pass it at every pixel."""
    sc, gb, ref, mask = case(kind)
    runs = np.stack([render("rt16", sc, gb, seed=s) for s in range(32)])
    if kind == "zero":
        assert np.all(runs == 0.0)
        return
    t = z_test(runs[:, mask], ref[mask])
    assert t["p_min"] > t["alpha"], (kind, t["p_min"], t["alpha"], len(t["failed"]))
    # and the test has power: a 2% bias is rejected (measured smallest p-values ~1e-30 and below)
    t2 = z_test(runs[:, mask] * 1.02, ref[mask])
    assert t2["p_min"] < t2["alpha"], (kind, t2["p_min"])


def test_rt_hemisphere_light_image_mean():
    """Area sampling of a 120 m light 2 m above a point has a heavy tail (a
    sample straight below weighs about 1000x the mean): per pixel the relative
    standard deviation of one sample is about 20, so rt is unbiased but a
    per-pixel Z-test at practical sample counts is not meaningful (the sample
    variance itself does not converge). Asserted instead: the image mean of 16
    runs of rt64 is within 4 standard errors of the closed form (measured
    standard error about 2%), and the ground truth (MIS) gets the same
    pixels within 0.5% (test above)."""
    sc, gb, ref, mask = case("hemisphere")
    runs = np.stack([render("rt64", sc, gb, seed=s)[mask].mean() for s in range(16)])
    se = runs.std(ddof=1) / np.sqrt(len(runs))
    r = ref[mask].mean()
    assert se < 0.05 * r, (se, r)
    assert abs(runs.mean() - r) < 4 * se, (runs.mean(), r, se)


RESTIR_BOUNDS = {  # kind: (mean, per-pixel mean error), about 1.5x the measured figures
    "grazing": (0.02, 0.06), "point": (1e-4, 1e-4), "hemisphere": (0.02, 0.04),
    "huge": (0.005, 0.003), "inside": (0.04, 0.05),
}


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_restir_hard_cases(kind):
    """ReSTIR (RTXDI defaults: temporal + spatial reuse, bias=basic, initial
    visibility), 4 frames at a still camera, averaged over 8 independent seeds
    (frames of one run are correlated through the reservoirs, seeds are not).
    Measured (48x32; mean error, per-pixel mean error): grazing 0.15%, 3.9%;
    hemisphere 0.23%, 2.6%; huge 0.02%, 0.17%; inside 2.6%, 3.4% (darker: the
    known bias of RTXDI's initial visibility with basic 1/Z weights, an occluded
    initial sample keeps its M, see docs/restir.md); point exact; zero exactly 0.
    Bounds in RESTIR_BOUNDS."""
    sc, gb, ref, mask = case(kind)
    img = np.mean([render("restir", sc, gb, frames=4, seed=s) for s in range(8)], axis=0)
    if kind == "zero":
        assert np.all(img == 0.0)
        return
    mean_err, pix_err = rel_errors(img, ref, mask)
    print(f"restir {kind}: mean error {mean_err:.4f}, per-pixel {pix_err:.4f}")
    bm, bp = RESTIR_BOUNDS[kind]
    assert mean_err < bm and pix_err < bp, (kind, mean_err, pix_err)


# =============================================================================
# Surface Light Cones (slc, default settings on the on-surface cache): the hard
# cases that tests/test_cones.py does not cover, in check mode,
# raw outputs against an independent reference on the plane's pixels. The full
# table (these and the ones in test_cones.py) is docs/hard-cases.md.
# =============================================================================

SLC_FRAMES = 16       # 8 new-entry updates + 8 settled ones at a still camera


def _plane_scene(name, rects=(), spheres=(), blocker=None, light_transform=None):
    """A diffuse plane (albedo 0.5, 4 m x 4 m at y = 0, facing up) with
    rectangular lights ``(name, centre, u, v, radiance)`` (facing cross(u, v)),
    emissive spheres ``(centre, radius, radiance)`` and an optional blocker
    quad; the still camera of :func:`helpers.hard_scene`."""
    from slc.scene.builder import SceneBuilder, diffuse
    from slc.scene.camera import CameraPath
    b = SceneBuilder(name)
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    for k, c, u, v, L in rects:
        b.add_quad(c, u, v, bsdf=diffuse([0, 0, 0]), emission=[L] * 3, name=k,
                   transform=light_transform if k == "moving" else None)
    for c, r, L in spheres:
        b.add_sphere(c, r, subdivisions=3, bsdf=diffuse([0, 0, 0]), emission=[L] * 3, name="sphere")
    if blocker is not None:
        b.add_quad(*blocker, bsdf=diffuse([0.2] * 3), name="blocker")
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=8, fov=70)
    return b.build([cam])


def _slc_frames(sc, frames, at=(), spec="slc", hook=None, **kw):
    """Run ``spec`` on ``sc`` for ``frames`` frames at the still camera in check
    mode; return ({frame: (G-buffer, image N x 3)} for frames in ``at`` (and the
    last)). ``hook(frame)`` runs before each frame (e.g. switching a light)."""
    m = methods.create(spec, sc, **kw)
    viewers = views.single(sc)
    timer = StageTimer()
    out = {}
    for f in range(frames):
        if hook is not None:
            hook(f)
        gb = frame_gbuffers(sc, viewers, f, W, H)[0]
        timer.begin_frame()
        with check.scope(spec, f, [gb]):
            d = m.render(FrameContext(f), [gb], timer)
            check.images(d, [gb])
        timer.end_frame()
        if f in at or f == frames - 1:
            out[f] = (gb, np.array(d[0], np.float64).T)
    return out


def _plane_mask(gb):
    p = np.array(gb.si.p).T
    return np.array(gb.valid) & (np.abs(p[:, 1]) < 1e-4)


def _quad_ref(sc, gb, rects, mask, n=64):
    """Quadrature reference (helpers.quadrature_direct) and the mask narrowed
    to pixels where 64 x 64 and 32 x 32 points agree within 0.1%."""
    rs = [(c, u, v, L) for _, c, u, v, L in rects]
    ref = quadrature_direct(sc, gb, rs, [], n=n)
    coarse = quadrature_direct(sc, gb, rs, [], n=n // 2)
    mask = mask & (np.abs(ref - coarse).max(axis=1) <= 1e-3 * np.maximum(ref.max(axis=1), 1e-12))
    return ref, mask


def _report(name, img, ref, mask, bounds):
    assert mask.sum() > 600, (name, mask.sum())
    mean_err, pix_err = rel_errors(img, ref, mask)
    mean_err = (img[mask].mean() / ref[mask].mean() - 1.0)
    print(f"slc hard case {name}: mean error {mean_err:+.4f}, per-pixel {pix_err:.4f} ({mask.sum()} px)")
    mean_err = abs(mean_err)
    bm, bp = bounds
    assert mean_err < bm and pix_err < bp, (name, mean_err, pix_err)


# case: (bound on |mean / reference - 1|, bound on per-pixel mean abs error / mean): about
# 1.5x the measured figures, the mean bound at least 2%. Measured (48x32, default slc on the
# on-surface cache, check mode; mean error, per-pixel error):
#   point-like +0.4%, 5.3%   behind -0.3%, 4.7%   grazing-far -0.2%, 8.3%
#   half-occluded +0.3%, 6.6%   many-lights +0.4%, 4.1%   moving-stopped +2.0%, 8.5%
#   switched-off (20 frames after the switch) -0.4%, 6.3%
# (without the update's cosine-weighted sums many-lights measures -3.4%, 6.5% and grazing-far
# +1.1%, 10.1%: their bounds fail that update)
SLC_BOUNDS = {"point-like": (0.02, 0.21), "behind": (0.02, 0.15), "grazing-far": (0.02, 0.125),
              "half-occluded": (0.02, 0.12), "many-lights": (0.02, 0.062),
              "moving-stopped": (0.03, 0.13), "switched-off": (0.02, 0.10)}


@pytest.mark.slow
def test_slc_point_like_sphere_light():
    """An emissive sphere of radius 4 mm (1e-3 of the 4 m scene) 0.7 m above
    the plane: a cone of about 0.3 degrees. Reference: the closed form of a
    sphere above the horizon, E = L A_proj cos / d^2, with A_proj the
    icosphere's mean projected area (Cauchy: surface area / 4; it varies with
    direction by under 1%)."""
    import trimesh
    c, r, L = np.array([0.2, 0.7, 0.1]), 0.004, 2.0e4
    sc = _plane_scene("hard_pointlike", spheres=[(c, r, L)])
    (gb, img), = _slc_frames(sc, SLC_FRAMES).values()
    mask = _plane_mask(gb)
    p = np.array(gb.si.p, np.float64).T
    d = c - p
    d2 = np.sum(d * d, axis=1)
    A = trimesh.creation.icosphere(subdivisions=3, radius=r).area / 4.0
    E = L * A * np.maximum(d[:, 1], 0.0) / np.sqrt(d2) / d2
    ref = np.repeat((0.5 / np.pi * E)[:, None], 3, axis=1)
    _report("point-like", img, ref, mask, SLC_BOUNDS["point-like"])


BEHIND = [("front", [0, 1.0, 0], [0.2, 0, 0], [0, 0, 0.2], 10.0),
          ("behind", [3.0, -0.7, 0], [0, 0, 0.5], [0, 0.3, 0], 50.0)]   # below the horizon, facing -x


@pytest.mark.slow
def test_slc_light_behind_the_surface():
    """A bright light below the plane's horizon (beyond its edge, so no shadow
    ray is blocked: only the cosine keeps it out) next to a small light in
    front: the plane must get the front light alone (quadrature of it; the
    behind light adds exactly 0 to the reference by the BSDF's cosine)."""
    sc = _plane_scene("hard_behind", rects=BEHIND)
    (gb, img), = _slc_frames(sc, SLC_FRAMES).values()
    ref, mask = _quad_ref(sc, gb, BEHIND[:1], _plane_mask(gb))
    full = quadrature_direct(sc, gb, [(c, u, v, L) for _, c, u, v, L in BEHIND], [], n=32)
    assert np.allclose(full, quadrature_direct(sc, gb, [(c, u, v, L) for _, c, u, v, L in BEHIND[:1]], [], n=32))
    _report("behind", img, ref, mask, SLC_BOUNDS["behind"])


GRAZING_FAR = [("light", [0, 0.25, -3.0], [1.0, 0, 0], [0, 0.1, 0], 40.0)]   # 3-7 degrees above the horizon


@pytest.mark.slow
def test_slc_grazing_incidence():
    """A light 3 m away, 3 to 7 degrees above the horizon, facing the plane
    (not touching it: the touching one is test_cones.py's ``grazing``):
    every plane point sees it at grazing incidence (cos 0.05-0.12)."""
    sc = _plane_scene("hard_grazing_far", rects=GRAZING_FAR)
    (gb, img), = _slc_frames(sc, SLC_FRAMES).values()
    ref, mask = _quad_ref(sc, gb, GRAZING_FAR, _plane_mask(gb))
    _report("grazing-far", img, ref, mask, SLC_BOUNDS["grazing-far"])


HALF = [("light", [0, 1.0, 0], [0.5, 0, 0], [0, 0, 0.5], 8.0)]


@pytest.mark.slow
def test_slc_half_occluded_large_light_check_mode():
    """test_cones.py's half-occluded large light (1 m x 1 m at 1 m, a thin
    blocker at 0.5 m over the half x < 0), in check mode on the default slc,
    against the quadrature with exact visibility."""
    sc = _plane_scene("hard_half", rects=HALF, blocker=([-0.4, 0.5, 0], [0.4, 0, 0], [0, 0, -0.6]))
    (gb, img), = _slc_frames(sc, 24).values()
    ref, mask = _quad_ref(sc, gb, HALF, _plane_mask(gb))
    _report("half-occluded", img, ref, mask, SLC_BOUNDS["half-occluded"])


MANY = [(f"l{i}", [1.2 * np.cos(a), 0.9 + 0.2 * (i % 2), 1.2 * np.sin(a) - 0.3],
         [0.08, 0, 0], [0, 0, 0.08], 60.0) for i, a in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False))]


@pytest.mark.slow
def test_slc_more_lights_than_max_cones():
    """Eight small lights on a ring around the plane's centre, all visible
    from every plane point, with max_cones = 3: cones must merge (case D) and
    still carry every light's energy."""
    sc = _plane_scene("hard_many", rects=MANY)
    (gb, img), = _slc_frames(sc, SLC_FRAMES, max_cones=3).values()
    ref, mask = _quad_ref(sc, gb, MANY, _plane_mask(gb), n=32)
    _report("many-lights", img, ref, mask, SLC_BOUNDS["many-lights"])


STOP = 12


def _moving(t):
    from slc.scene.builder import translate
    return translate([0.04 * min(t * 60.0, STOP), 0.0, 0.0])


@pytest.mark.slow
def test_slc_light_moves_then_stops():
    """A 0.2 m light at 1 m moves 4 cm per frame for 12 frames, then stops
    (test_cones.py's moving light, here in check mode on the default slc):
    the error 20 frames after the stop, against the quadrature of the light
    at its final place."""
    rect = [("moving", [0, 1.0, 0], [0.1, 0, 0], [0, 0, 0.1], 20.0)]
    sc = _plane_scene("hard_moving", rects=rect, light_transform=_moving)
    res = _slc_frames(sc, STOP + 21, at=(STOP, STOP + 10))
    final = [(k, np.array(c) + [0.04 * STOP, 0, 0], u, v, L) for k, c, u, v, L in rect]
    errs = {}
    for f, (gb, img) in res.items():
        ref, mask = _quad_ref(sc, gb, final, _plane_mask(gb), n=32)
        errs[f] = rel_errors(img, ref, mask)
    print("moving light, (mean, per-pixel) error by frame:", errs)
    assert errs[STOP][1] > errs[STOP + 10][1] > errs[STOP + 20][1] or errs[STOP + 20][1] < 0.05, errs
    gb, img = res[STOP + 20]
    ref, mask = _quad_ref(sc, gb, final, _plane_mask(gb), n=32)
    _report("moving-stopped", img, ref, mask, SLC_BOUNDS["moving-stopped"])


SWITCH = [("stays", [-0.3, 1.0, 0], [0.1, 0, 0], [0, 0, 0.1], 20.0),
          ("off", [0.4, 0.8, 0], [0.1, 0, 0], [0, 0, 0.1], 40.0)]
OFF_AT = 16


_SWITCH_OFF = {}


def _switch_off_errors():
    """Two lights; the brighter one switches off at frame 16 (radiance 0 through
    mi.traverse, the emitter table re-read). Rendered once per pytest session: rt16's
    (mean, per-pixel) error 2 frames after the switch, and slc's at frames 15, 18,
    26 and 36 (the switch + 20), against the quadrature of the lights that are on."""
    if _SWITCH_OFF:
        return _SWITCH_OFF
    import mitsuba as mi

    from slc.scene import emitter_sampling

    def switching(spec, frames, at):
        sc = _plane_scene("hard_switch", rects=SWITCH)
        params = mi.traverse(sc.mi_scene)
        key = [k for k in params.keys() if k.startswith("off") and k.endswith("radiance.value")]
        assert len(key) == 1, list(params.keys())

        def hook(f):
            if f == OFF_AT:
                params[key[0]] = mi.Color3f(0.0)
                params.update()
                emitter_sampling.for_scene(sc.mi_scene).rebuild()
        return sc, _slc_frames(sc, frames, at=at, spec=spec, hook=hook)

    sc, rt = switching("rt16", OFF_AT + 3, ())
    gb, img = rt[OFF_AT + 2]
    ref, mask = _quad_ref(sc, gb, SWITCH[:1], _plane_mask(gb), n=32)
    _SWITCH_OFF["rt16"] = rel_errors(img, ref, mask)
    sc, res = switching("slc", OFF_AT + 21, (OFF_AT - 1, OFF_AT + 2, OFF_AT + 10))
    for f, (gb, img) in res.items():
        on = SWITCH if f < OFF_AT else SWITCH[:1]
        ref, mask = _quad_ref(sc, gb, on, _plane_mask(gb), n=32)
        _SWITCH_OFF[f] = (img, ref, mask) if f == OFF_AT + 20 else rel_errors(img, ref, mask)
    print("switched-off light, (mean, per-pixel) error:",
          {k: rel_errors(*v) if k == OFF_AT + 20 else v for k, v in _SWITCH_OFF.items()})
    return _SWITCH_OFF


@pytest.mark.slow
def test_slc_light_switches_off():
    """20 frames after the switch slc's image is within SLC_BOUNDS of the light that
    stays on: a shrink-test ray that hits the dark light's front side counts as a
    light that left (C / 3, motion reported). Measured -0.5%, 6.7% (2 frames after the
    switch 53%, 10 after 0.4%)."""
    img, ref, mask = _switch_off_errors()[OFF_AT + 20]
    _report("switched-off", img, ref, mask, SLC_BOUNDS["switched-off"])


# ------------------------------------------------------------------------------------------------
# Scale, position, degenerate geometry, a camera inside a solid, a small bright sun, and slc's
# hemisphere-sized light at its default settings. Each: the methods it applies to, in check mode
# (this module's autouse fixture), 32x24, against a closed form, a quadrature or exactly 0; bounds
# about 1.5x the figures measured at this size (mean bound at least 2%), printed with -s.

SMALL_W, SMALL_H = 32, 24
# frames per method (cache methods need a few to fill their entries)
FRAMES = {"rt16": 1, "restir": 4, "slc": 10, "adaptive": 10, "osc-gi": 10}


def _small_frames(sc, spec):
    """Image (N x 3) and G-buffer of ``spec``'s last frame at SMALL_W x SMALL_H, in check mode."""
    global W, H
    saved = W, H
    W, H = SMALL_W, SMALL_H
    try:
        (gb, img), = _slc_frames(sc, FRAMES[spec], spec=spec).values()
    finally:
        W, H = saved
    return gb, img


def _bounded(name, img, ref, mask, bound):
    assert mask.sum() > 300, (name, mask.sum())
    a, r = img[mask], ref[mask]
    mean_err = a.mean() / r.mean() - 1.0
    pix_err = np.abs(a - r).mean() / r.mean()
    print(f"hard case {name}: mean error {mean_err:+.4f}, per-pixel {pix_err:.4f} ({mask.sum()} px)")
    assert abs(mean_err) < bound[0] and pix_err < bound[1], (name, mean_err, pix_err, bound)


def _lit_plane(name, scale=1.0, origin=(0.0, 0.0, 0.0)):
    """The plane (4 x 4 m, albedo 0.5) under a 0.5 x 0.5 m light of radiance 10 at 1 m,
    all lengths times ``scale`` and moved to ``origin`` (unit 1: nothing tells the
    methods the scene's size)."""
    from slc.scene.builder import SceneBuilder, diffuse
    from slc.scene.camera import CameraPath
    o = np.asarray(origin, float)
    b = SceneBuilder(name)
    b.add_quad(o, [2 * scale, 0, 0], [0, 0, -2 * scale], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_quad(o + [0, scale, 0], [0.25 * scale, 0, 0], [0, 0, 0.25 * scale], bsdf=diffuse([0] * 3),
               emission=[10.0] * 3, name="light")
    return b.build([CameraPath([(o + scale * np.array([0, 0.8, 1.2]), o)], frames=8, fov=70)])


def _lit_plane_reference(gb, scale=1.0, origin=(0.0, 0.0, 0.0)):
    """(closed form N x 3, plane pixels) of :func:`_lit_plane`: the rectangle's irradiance,
    which does not change with the scale."""
    o = np.asarray(origin, float)
    p = np.array(gb.si.p, np.float64).T
    mask = np.array(gb.valid) & (np.abs(p[:, 1] - o[1]) < 1e-3 * scale)
    E = rect_irradiance((p[:, 0] - o[0]) / scale, (p[:, 2] - o[2]) / scale, -0.25, 0.25, -0.25, 0.25, 1.0, 10.0)
    return np.repeat((0.5 / np.pi * E)[:, None], 3, axis=1), mask


# method: (mean, per-pixel) bound. Measured (mean / per-pixel) at x1e-3, x1e3, 1 km and 10 km
# from the origin: rt16 +0.2% / 4.6% (all four); restir +0.1..+1.0% / 2.8-3.3%; slc -0.5..-1.5% /
# 6.3-6.6%; adaptive as slc; osc-gi -0.04% / 2.0%.
SCALE_BOUNDS = {"rt16": (0.02, 0.07), "restir": (0.02, 0.05), "slc": (0.025, 0.10), "adaptive": (0.025, 0.10),
                "osc-gi": (0.02, 0.031)}
SCALES = {"x1e-3": (1e-3, (0, 0, 0)), "x1e3": (1e3, (0, 0, 0)), "1km-away": (1.0, (1e3, 0, -1e3)),
          "10km-away": (1.0, (1e4, 0, -1e4))}


@pytest.mark.slow
@pytest.mark.parametrize("spec", sorted(SCALE_BOUNDS))
@pytest.mark.parametrize("where", sorted(SCALES))
def test_scene_scale_and_distance_from_origin(where, spec):
    """The lit plane at 1e-3 and 1e3 times its size, and 1 km and 10 km from the origin
    (float32 spacing there 6e-5 m and 1e-3 m): every method within its bound of the
    closed form."""
    scale, origin = SCALES[where]
    sc = _lit_plane(f"hard_{where}", scale, origin)
    gb, img = _small_frames(sc, spec)
    ref, mask = _lit_plane_reference(gb, scale, origin)
    _bounded(f"{where} {spec}", img, ref, mask, SCALE_BOUNDS[spec])


def _degenerate_scene():
    """The lit plane built with zero-area triangles in both meshes (a repeated corner,
    three equal corners, three collinear corners) and a second emitter whose every
    triangle has zero area (radiance 50)."""
    from slc.scene.builder import SceneBuilder, diffuse
    from slc.scene.camera import CameraPath
    b = SceneBuilder("hard_degenerate")
    V = np.array([[-2, 0, 2], [2, 0, 2], [2, 0, -2], [-2, 0, -2], [0, 0, 0], [1, 0, 0]], float)
    b.add_mesh(V, np.array([[0, 1, 2], [0, 2, 3], [4, 4, 4], [4, 5, 4], [0, 4, 2]]), bsdf=diffuse([0.5] * 3),
               name="plane")
    L = np.array([[-0.25, 1, -0.25], [0.25, 1, -0.25], [0.25, 1, 0.25], [-0.25, 1, 0.25], [0, 1, 0]], float)
    b.add_mesh(L, np.array([[0, 1, 2], [0, 2, 3], [4, 4, 4], [0, 4, 2], [1, 1, 3]]), bsdf=diffuse([0] * 3),
               emission=[10.0] * 3, name="light")
    Z = np.array([[0.5, 0.8, 0], [0.6, 0.8, 0], [0.7, 0.8, 0]], float)
    b.add_mesh(Z, np.array([[0, 1, 2], [0, 0, 1]]), bsdf=diffuse([0] * 3), emission=[50.0] * 3, name="zero_area")
    return b.build([CameraPath([([0, 0.8, 1.2], [0, 0, 0])], frames=8, fov=70)])


# Measured (mean / per-pixel): rt16 +0.4% / 22% (half the samples go to the zero-area emitter,
# uniform choice: noise, no bias); restir -3.1% / 8.2%; slc -0.7% / 6.7%; adaptive as slc;
# osc-gi -0.6% / 4.9%.
DEGENERATE_BOUNDS = {"rt16": (0.02, 0.33), "restir": (0.047, 0.123), "slc": (0.02, 0.10),
                     "adaptive": (0.02, 0.10), "osc-gi": (0.02, 0.073)}


@pytest.mark.slow
@pytest.mark.parametrize("spec", sorted(DEGENERATE_BOUNDS))
def test_degenerate_triangles_and_zero_area_emitter(spec):
    """Zero-area triangles in the plane and the light, and an emitter of zero area: no
    NaN anywhere (check mode), and the light of the rest within the bound of the
    closed form (the zero-area emitter adds nothing)."""
    sc = _degenerate_scene()
    gb, img = _small_frames(sc, spec)
    ref, mask = _lit_plane_reference(gb)
    _bounded(f"degenerate {spec}", img, ref, mask, DEGENERATE_BOUNDS[spec])


def test_degenerate_triangles_ground_truth():
    """The ground truth (Mitsuba's sampling, MIS) on the degenerate scene, 256 samples:
    finite in check mode and near the closed form (measured +0.3% / 5.3%; half the light
    samples go to the zero-area emitter)."""
    sc = _degenerate_scene()
    gb, _ = _small_frames(sc, "rt16")
    g = np.array(direct_mis(sc.mi_scene, gb, 256), np.float64).T
    check.images([g.astype(np.float32)], [gb], stage="ground truth")
    ref, mask = _lit_plane_reference(gb)
    _bounded("degenerate ground truth", g, ref, mask, (0.01, 0.08))


INSIDE_METHODS = ["rt16", "restir", "slc", "adaptive", "osc-gi"]


@pytest.fixture(scope="module")
def camera_in_box():
    """The lit plane with the camera inside a closed box (0.6 m cube around it): every
    pixel sees the inside of the box, the back of its faces."""
    from slc.scene.builder import SceneBuilder, diffuse
    from slc.scene.camera import CameraPath
    b = SceneBuilder("hard_camera_inside")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_quad([0, 1, 0], [0.25, 0, 0], [0, 0, 0.25], bsdf=diffuse([0] * 3), emission=[10.0] * 3, name="light")
    b.add_box([-0.3, 0.5, 0.9], [0.3, 1.1, 1.5], bsdf=diffuse([0.5] * 3), name="box")
    return b.build([CameraPath([([0, 0.8, 1.2], [0, 0, 0])], frames=8, fov=70)])


@pytest.mark.slow
@pytest.mark.parametrize("spec", INSIDE_METHODS)
def test_camera_inside_a_solid(camera_in_box, spec):
    """Seen from inside a closed box, every pixel is the back of a one-sided diffuse face:
    the ground truth is exactly 0 there, and so is every method's image (check mode: no
    NaN, nothing negative)."""
    gb, img = _small_frames(camera_in_box, spec)
    valid = np.array(gb.valid)
    assert valid.all()
    g = np.array(direct_mis(camera_in_box.mi_scene, gb, 16), np.float64).T
    print(f"hard case camera inside ({spec}): max {img[valid].max():.3g}, ground truth max {g.max():.3g}")
    assert g.max() == 0.0 and img[valid].max() == 0.0


def _sun_scene():
    """The plane (albedo 0.5) alone under an environment map of 128 x 64 texels: radiance
    0.05 everywhere but one texel of 1e5 at 35 degrees from the zenith (about 2.8 degrees
    across, 700 times the irradiance of the rest of the sky)."""
    from slc.scene.builder import SceneBuilder, diffuse
    from slc.scene.camera import CameraPath
    sky = np.full((64, 128, 3), 0.05, np.float32)
    sky[12, 40] = 1e5
    b = SceneBuilder("hard_sun")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    b.add_envmap(bitmap=sky)
    return b.build([CameraPath([([0, 0.8, 1.2], [0, 0, 0])], frames=8, fov=70)])


def _sky_irradiance(sc, n=2048):
    """Quadrature of the upper hemisphere (+y) of the scene's environment, as Mitsuba
    evaluates it (bilinear texels): E = sum L(w) cos(theta) dw on an n x 2n midpoint grid
    in (theta, phi); the sun spans about 60 x 60 grid points."""
    import drjit as dr
    import mitsuba as mi
    env, = [e for e in sc.mi_scene.emitters() if e.is_environment()]
    th = (np.arange(n) + 0.5) * (0.5 * np.pi / n)
    ph = (np.arange(2 * n) + 0.5) * (np.pi / n)
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*[mi.Float(-d[:, k].astype(np.float32)) for k in range(3)])
    L = np.array(mi.Color3f(env.eval(si)), np.float64).T
    w = (np.cos(T) * np.sin(T)).reshape(-1) * (0.5 * np.pi / n) * (np.pi / n)
    return (L * w[:, None]).sum(0)


SUN_METHODS = ["rt16", "restir", "slc", "adaptive", "osc-gi"]


@pytest.fixture(scope="module")
def sun():
    sc = _sun_scene()
    return sc, _sky_irradiance(sc)


@pytest.mark.slow
@pytest.mark.parametrize("spec", SUN_METHODS)
def test_small_bright_hdr_sun(sun, spec):
    """A small, very bright sun in an HDR environment over an open plane: every plane
    point sees the whole sky, so the reference is one number, the quadrature of the sky's
    irradiance (times albedo / pi)."""
    sc, E = sun
    gb, img = _small_frames(sc, spec)
    mask = _plane_mask(gb)
    ref = np.broadcast_to(0.5 / np.pi * E, img.shape)
    _bounded(f"sun {spec}", img, ref, mask, SUN_BOUNDS[spec])


@pytest.mark.slow
def test_small_bright_hdr_sun_ground_truth(sun):
    """The ground truth (256 samples) on the sun scene against the same quadrature."""
    sc, E = sun
    gb, _ = _small_frames(sc, "rt16")
    g = np.array(direct_mis(sc.mi_scene, gb, 256), np.float64).T
    check.images([g.astype(np.float32)], [gb], stage="ground truth")
    _bounded("sun ground truth", g, np.broadcast_to(0.5 / np.pi * E, g.shape), _plane_mask(gb), SUN_BOUNDS["gt"])


# Measured (mean / per-pixel): rt16 +0.02% / 0.68%, restir -0.00% / 0.91%, slc +0.00% / 0.27%,
# adaptive +0.14% / 0.15% (the sun listed as a directional light), osc-gi +0.03% / 0.56%,
# ground truth +0.00% / 0.33%.
SUN_BOUNDS = {"rt16": (0.02, 0.0102), "restir": (0.02, 0.0137), "slc": (0.02, 0.0041), "adaptive": (0.02, 0.0023),
              "osc-gi": (0.02, 0.0084), "gt": (0.02, 0.005)}


# slc at its default settings under the hemisphere-sized light (a 120 m square 2 m above the
# plane, closed form): measured mean +0.14%, per-pixel 1.9% at 32x24 after 10 frames (without
# the update's cosine-weighted sums, +6.6% / 6.9%: a cone spread over its whole cap what the
# samples nearest its axis brought; docs/hard-cases.md).
HEMISPHERE_SLC_BOUND = (0.02, 0.04)


def _hemisphere_slc_errors():
    sc = hard_scene("hemisphere")
    gb, img = _small_frames(sc, "slc")
    p = np.array(gb.si.p, np.float64).T
    (c, u, v, L), = HARD_RECTS["hemisphere"].values()
    E = rect_irradiance(p[:, 0], p[:, 2], -u[0], u[0], -v[2], v[2], c[1], L)
    ref = np.repeat((0.5 / np.pi * E)[:, None], 3, axis=1)
    mask = _plane_mask(gb)
    a, r = img[mask], ref[mask]
    errs = abs(a.mean() / r.mean() - 1.0), np.abs(a - r).mean() / r.mean()
    print(f"hard case hemisphere slc (default settings): mean error {errs[0]:.4f}, per-pixel {errs[1]:.4f}")
    return errs


def test_slc_hemisphere_sized_light_default_settings():
    """slc with its default settings under the hemisphere-sized light, in check mode,
    against the closed form of the rectangle: within HEMISPHERE_SLC_BOUND."""
    mean_err, pix_err = _hemisphere_slc_errors()
    bm, bp = HEMISPHERE_SLC_BOUND
    assert mean_err < bm and pix_err < bp, (mean_err, pix_err)


@pytest.mark.slow
def test_slc_light_switches_off_before_the_switch():
    """The switch reaches the methods: rt16 is within 3% in the mean 2 frames after it;
    slc is within its bounds before the switch (one frame before)."""
    e = _switch_off_errors()
    assert e["rt16"][0] < 0.03, e["rt16"]
    assert e[OFF_AT - 1][0] < SLC_BOUNDS["switched-off"][0] and e[OFF_AT - 1][1] < SLC_BOUNDS["switched-off"][1], \
        e[OFF_AT - 1]
