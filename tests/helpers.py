"""Small scenes and loops shared by the tests."""
import numpy as np

from slc.scene import gbuffer
from slc.methods import FrameContext
from slc.scene.builder import SceneBuilder, diffuse
from slc.scene.camera import CameraPath
from slc.core.timing import NullTimer


def plane_under_rect_light(half=0.25, height=1.0, radiance=10.0, albedo=0.5, plane_half=2.0,
                           name="plane_light", bsdf=None, light_transform=None, blocker=None):
    """A horizontal plane y = 0 (facing up) under a rectangular light of size
    2*half x 2*half at ``height`` facing down; camera looking down at it. ``blocker``:
    (centre, u, v) of a grey quad between them."""
    b = SceneBuilder(name)
    b.add_quad([0, 0, 0], [plane_half, 0, 0], [0, 0, -plane_half],
               bsdf=bsdf if bsdf is not None else diffuse([albedo] * 3), name="plane")
    b.add_quad([0, height, 0], [half, 0, 0], [0, 0, half], bsdf=diffuse([0, 0, 0]),
               emission=[radiance] * 3, name="light", transform=light_transform)
    if blocker is not None:
        b.add_quad(*blocker, bsdf=diffuse([0.2] * 3), name="blocker")
    cam = CameraPath([([0.0, 0.8 * height, 1.2], [0.0, 0.0, 0.0])], frames=64, fov=60)
    return b.build([cam, cam, cam])


def rect_irradiance(px, pz, x1, x2, z1, z2, h, L):
    """Closed-form irradiance at (px, 0, pz) from a uniform Lambertian
    rectangle [x1,x2] x [z1,z2] at height h, parallel to the plane."""
    def G(X, Z):
        A, B = X / h, Z / h
        return 0.5 * (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
                      + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B)))
    return L * (G(x2 - px, z2 - pz) - G(x1 - px, z2 - pz) - G(x2 - px, z1 - pz) + G(x1 - px, z1 - pz))


def render_frames(scene, method, viewers, frames, width, height, seed=0, start=0):
    """Run ``frames`` frames; return the composed images of the last frame. In
    check mode (SLC_CHECK=1) stage outputs and returned images are checked."""
    from slc.core import check
    from slc.scene.gbuffer import frame_gbuffers
    out = None
    for f in range(start, start + frames):
        gbs = frame_gbuffers(scene, viewers, f, width, height)
        with check.scope(method.label or method.name, f, gbs):
            d = method.render(FrameContext(f), gbs, NullTimer())
            if check.enabled():
                check.images(d, gbs)
        out = [gbuffer.to_image(gb, gbuffer.compose(gb, x)) for gb, x in zip(gbs, d)]
    return out, gbs


# ----------------------------------------------------------------------------- hard cases

def hard_scene(kind):
    """The hard cases of DESIGN.md on a diffuse plane (albedo 0.5, y = 0, facing up):
    ``grazing`` (a 1 x 0.2 m light standing on the horizon), ``point``, ``hemisphere``
    (a 120 m square light 2 m above: nearly the whole hemisphere), ``zero`` (a black
    light and a point light below the plane), ``huge`` (radiance 1e6), ``inside`` (a box
    closed around part of the plane). Same scenes as tests/test_cones.py."""
    b = SceneBuilder(f"hard_{kind}")
    b.add_quad([0, 0, 0], [2, 0, 0], [0, 0, -2], bsdf=diffuse([0.5] * 3), name="plane")
    for k, (c, u, v, L) in HARD_RECTS.get(kind, {}).items():
        b.add_quad(c, u, v, emission=[L] * 3, name=k)
    if kind == "point":
        b.add_point_light(*HARD_POINT)
    elif kind == "zero":
        b.add_point_light([0, -1, 0], [1.0] * 3)        # below the plane: contributes nothing
    elif kind == "inside":
        b.add_box([-0.3, -0.1, -0.3], [0.3, 0.3, 0.3], bsdf=diffuse([0.5] * 3))
    cam = CameraPath([([0.0, 0.8, 1.2], [0.0, 0.0, 0.0])], frames=8, fov=70)
    return b.build([cam])


# kind -> {name: (centre, u, v, radiance)} of its rectangular lights (facing cross(u, v))
HARD_RECTS = {
    "grazing": {"light": ([0, 0.1, -1.5], [0.5, 0, 0], [0, 0.1, 0], 10.0)},
    "hemisphere": {"light": ([0, 2.0, 0], [60, 0, 0], [0, 0, 60], 1.0)},
    "zero": {"light": ([0, 1, 0], [0.2, 0, 0], [0, 0, 0.2], 0.0)},
    "huge": {"light": ([0, 1, 0], [0.05, 0, 0], [0, 0, 0.05], 1e6)},
    "inside": {"light": ([0, 1, 0], [0.2, 0, 0], [0, 0, 0.2], 5.0)},
}
HARD_POINT = ([0.2, 0.7, 0.1], [3.0] * 3)


def quadrature_direct(scene, gb, rects=(), points=(), n=48, chunk=1 << 21):
    """Deterministic reference of direct illumination at the G-buffer points
    (N x 3 numpy): midpoint rule on an n x n grid over each rectangular light
    ``(centre, u, v, radiance)`` (one-sided, facing cross(u, v)) and the point
    lights ``(position, intensity)``, with exact visibility (Mitsuba shadow rays)
    and the BSDF (cosine included). Independent of the Monte Carlo estimators
    it checks; accurate where the pixel is several grid cells from the light."""
    import drjit as dr
    import mitsuba as mi
    N = gb.size
    out = np.zeros((N, 3))
    lights = []
    for c, u, v, L in rects:
        c, u, v = (np.asarray(a, float) for a in (c, u, v))
        t = (np.arange(n) + 0.5) / n * 2 - 1
        a, b = np.meshgrid(t, t, indexing="ij")
        pts = c + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
        nl = np.cross(u, v)
        dA = 4 * np.linalg.norm(nl) / n ** 2
        nl /= np.linalg.norm(nl)
        lights.append((pts, nl, float(dA) * float(L), True))
    for p, I in points:
        lights.append((np.asarray([p], float), np.zeros(3), float(np.asarray(I, float)[0]), False))
    ctx = mi.BSDFContext()
    for pts, nl, scale, area in lights:
        M = len(pts)
        per = max(1, chunk // M)
        for s in range(0, N, per):
            idx = np.arange(s, min(N, s + per))
            pix = mi.UInt32(np.repeat(idx, M).astype(np.uint32))
            si = dr.gather(mi.SurfaceInteraction3f, gb.si, pix)
            ok = dr.gather(mi.Bool, gb.valid, pix)
            y = mi.Point3f(*[mi.Float(np.tile(pts[:, k], len(idx))) for k in range(3)])
            d = y - si.p
            r2 = dr.squared_norm(d)
            d = d / dr.sqrt(r2)
            cos_y = dr.maximum(-dr.dot(mi.Vector3f(*[float(x) for x in nl]), d), 0.0) if area else mi.Float(1.0)
            vis = ok & ~scene.mi_scene.ray_test(si.spawn_ray_to(y), ok)
            f = mi.Color3f(si.bsdf().eval(ctx, si, si.to_local(d), vis))
            c = dr.select(vis, f * (scale * cos_y / r2), 0.0)
            arr = np.array(c).T.reshape(len(idx), M, 3)
            out[idx] += arr.sum(axis=1)
    return out


# ----------------------------------------------------------------------------- per-pixel Z-test

def z_test(runs, ref, significance=0.01, ref_var=None, rel_floor=1e-4, var_runs=None):
    """Per-pixel Z-test of independent runs of an estimator against a reference
    mean, in the manner of Mitsuba's ``mi.testing.RenderingRegressionTest``:
    ``z = |mean(runs) - ref| / sqrt(var(runs) / K + ref_var)``, two-sided p-value
    ``2 (1 - Phi(z))`` per pixel and channel, significance Sidak-corrected for the
    number of tests, ``1 - (1 - significance)^(1 / n)``. ``runs``: (K, N, 3);
    ``ref``: (N, 3); ``ref_var``: variance of the reference mean (0 for a closed
    form). ``var_runs`` (K', N, 3): a separate batch of runs to take the variance
    of one run from (as Mitsuba takes it from its reference render), so that the
    statistic is not a t statistic with few degrees of freedom; default: ``runs``.
    The standard error is floored at ``rel_floor * |ref|`` (float32 round-off of a
    zero-variance estimator, e.g. one point light) and 1e-12.
    Returns dict(p_min, alpha, n, failed (indices), z)."""
    from scipy.special import erfc
    runs = np.asarray(runs, np.float64)
    ref = np.asarray(ref, np.float64)
    K = runs.shape[0]
    mean = runs.mean(axis=0)
    var = (runs if var_runs is None else np.asarray(var_runs, np.float64)).var(axis=0, ddof=1) / K
    if ref_var is not None:
        var = var + np.asarray(ref_var, np.float64)
    se = np.sqrt(var + np.square(rel_floor * np.abs(ref)) + 1e-24)
    z = np.abs(mean - ref) / se
    p = erfc(z / np.sqrt(2.0))                  # = 2 (1 - Phi(z))
    n = p.size
    alpha = 1.0 - (1.0 - significance) ** (1.0 / n)
    return dict(p_min=float(p.min()), alpha=alpha, n=n, failed=np.argwhere(p <= alpha), z=z)


def independent_runs(spec, scene, gbs, seeds, frames=1):
    """The first viewer's direct light (N x 3, float64) after ``frames`` frames,
    one independent run of method ``spec`` per seed, stacked."""
    from slc import methods
    out = []
    for s in seeds:
        m = methods.create(spec, scene, seed=s)
        for f in range(frames):
            d = m.render(FrameContext(f), gbs, NullTimer())
        out.append(np.array(d[0], np.float64).T)
    return np.stack(out)


def run_case(code: str, *args, timeout: int = 600) -> dict:
    """Run ``code`` (a script that prints ``RESULT <json>``) with ``args`` in a
    fresh Python process with the repository on its path; returns the last
    RESULT as a dict. A fresh process: kernels an earlier test built stay in the
    process's in-memory cache and would hide a kernel built anew."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                       env=env, timeout=timeout, cwd=root)
    assert p.returncode == 0, p.stderr[-3000:]
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def slc_cli(args, cwd=None):
    """``slc ARGS`` run in this process (``slc.run.cli.main``, as the ``slc`` entry point
    runs it) rather than in a fresh interpreter: a ``subprocess.CompletedProcess``
    with the exit status and what the command printed to stdout and stderr. Check
    mode (``--check``) is switched off again afterwards; an exception the command
    does not turn into an exit status propagates (a traceback, as in a subprocess)."""
    import contextlib
    import io
    import os
    import subprocess
    from pathlib import Path

    from slc.core import check
    from slc.run import cli
    args = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    before = os.environ.get(check.ENV)
    code = 0
    try:
        with contextlib.chdir(cwd or Path(__file__).resolve().parents[1]), \
                contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                cli.main(args)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        if before is None:
            os.environ.pop(check.ENV, None)
        else:
            os.environ[check.ENV] = before
    return subprocess.CompletedProcess(["slc", *args], code, out.getvalue(), err.getvalue())


def first_emitter_hit(scene, si, wo):
    """The first surface hit from ``si.p`` along the directions ``wo`` (normalised): (directions,
    its SurfaceInteraction, hit mask, its emitter pointer)."""
    import drjit as dr
    import mitsuba as mi
    wo = dr.normalize(mi.Vector3f(wo))
    si2 = scene.ray_intersect(mi.Ray3f(si.p, wo))
    hit = si2.is_valid()
    return wo, si2, hit, si2.emitter(scene, hit)
