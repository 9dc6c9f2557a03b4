"""The emitter table (slc.scene.emitter_sampling) against Mitsuba's own
``scene.sample_emitter_direction``: chi-square tests of the sampled
directions, the weights' expectation, delta lights, moving lights, and RT-N
with the table against the (Mitsuba-sampled) ground truth."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.scene import emitter_sampling, gbuffer, lights, scenes, views

from slc.reference import groundtruth

from slc import methods
from slc.scene.gbuffer import frame_gbuffers

from helpers import first_emitter_hit, plane_under_rect_light

pytestmark = pytest.mark.slow      # chi-square tests of every emitter type (the fast subset: test_emitter_sampling_fast.py)


ORIGIN = [0.1, 0.05, -0.1]   # the shading point (floating: nothing but emitters around it)


def _icosphere(center, radius, radiance, smooth):
    import trimesh
    tm = trimesh.creation.icosphere(subdivisions=1, radius=radius)
    V = np.asarray(tm.vertices, np.float32) + np.asarray(center, np.float32)
    F = np.asarray(tm.faces, np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse"})
    props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": radiance}})
    m = mi.Mesh("ico", len(V), len(F), props, has_vertex_normals=smooth, has_vertex_texcoords=False)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(V.ravel())
    p["faces"] = mi.UInt32(F.ravel())
    if smooth:
        N = (V - np.asarray(center, np.float32)) / radius
        p["vertex_normals"] = mi.Float(N.astype(np.float32).ravel())
    p.update()
    return m


def _mixed_scene(point=True, smooth=True, env=True):
    """Rectangle above, analytic sphere at +x, emissive icosphere mesh at -x,
    emissive cube below, a constant environment (sampled by Mitsuba inside
    the table) and a point light; no other geometry."""
    d = {"type": "scene",
         "rect": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(0.5),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [4.0, 3.0, 2.0]}}},
         "sph": {"type": "sphere", "center": [2.0, 0.5, 0.0], "radius": 0.4,
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 2.0, 6.0]}}},
         "ico": _icosphere([-2.0, 0.3, 0.5], 0.5, [2.0, 2.0, 2.0], smooth),
         "cube": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.0, -2.0, 1.5]).scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6.0, 1.0, 1.0]}}}}
    if env:
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.05, 0.08]}}
    if point:
        d["pt"] = {"type": "point", "position": [0.0, 1.0, 2.0], "intensity": {"type": "rgb", "value": [3.0, 3.0, 3.0]}}
    return mi.load_dict(d)


def _shading_point(n):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(*ORIGIN)
    si.n = mi.Normal3f(0, 1, 0)
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    return si


def _pdf_of_direction(scene, table):
    """Directional density of ``table`` at ORIGIN: the emitter point first hit
    along the direction plus the environment behind everything."""
    env = [i for i, e in enumerate(scene.emitters()) if e.is_environment()]

    def pdf(wo):
        n = dr.width(wo)
        si = _shading_point(n)
        wo, si2, hit, em = first_emitter_hit(scene, si, wo)
        p = dr.select(hit & (em != None), table.pdf_hit(scene, si, si2, hit), 0.0)  # noqa: E711
        for i in env:
            ds = dr.zeros(mi.DirectionSample3f, n)
            ds.d, ds.dist, ds.p = wo, dr.inf, si.p + wo
            p += table.pdf(si, ds, mi.Bool(True), index=mi.UInt32(i))
        return p
    return pdf


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    """A chi-square test that fails writes ``chi2_data.py`` into the working folder:
    run it in a temporary one."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _chi2(scene, sample_dir, pdf, seed=3):
    """Pearson's test over the sphere of directions. The densities are
    discontinuous at every emitter's silhouette, where the trapezoid rule of
    the pdf tabulation is only O(1/ires) accurate: coarse cells (31 x 62),
    64 x 64 integration points per cell and 300k samples keep that error
    below the statistical one (a 10% error in one emitter's density is
    still rejected: test_chi2_rejects_a_wrong_density)."""
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample_dir, pdf_func=pdf,
                                 sample_dim=2, sample_count=300_000, res=31, ires=64, seed=seed)
    ok = test.run(significance_level=0.01)
    return ok, test.messages


def test_table_kinds():
    sc = _mixed_scene()
    t = emitter_sampling.EmitterSampler(sc, choice="power")
    kinds = t.describe()["emitters"]
    assert kinds == {"rectangle": 1, "sphere": 1, "mesh": 2, "mitsuba": 1, "point": 1}, kinds
    pm = np.array(list(t.pmf.values()))
    assert abs(pm.sum() - 1.0) < 1e-9 and (pm > 0).all()
    # power choice: the environment keeps its uniform share
    env = [i for i, e in enumerate(sc.emitters()) if e.is_environment()][0]
    assert abs(t.pmf[env] - 1.0 / len(pm)) < 1e-12


@pytest.mark.parametrize("choice", ["power", "uniform"])
@pytest.mark.usefixtures("in_tmp")
def test_chi2_table_samples_follow_table_pdf(choice):
    """Directions sampled by the table (all continuous emitters; the point
    light excluded by ``subset``) follow the table's own ``pdf``."""
    sc = _mixed_scene(point=True, smooth=True)
    cont = [i for i, e in enumerate(sc.emitters()) if e.class_name() != "PointLight"]
    t = emitter_sampling.EmitterSampler(sc, choice=choice, subset=cont)

    def sample_dir(u):
        n = dr.width(u)
        ds, w, ok, _ = t.sample(_shading_point(n), mi.Point2f(u), mi.Bool(True))
        return ds.d, dr.select(ok, 1.0, 0.0)

    ok, msg = _chi2(sc, sample_dir, _pdf_of_direction(sc, t))
    assert ok, msg


@pytest.mark.usefixtures("in_tmp")
def test_chi2_rejects_a_wrong_density():
    """The test has the power to see a 10% error in the sphere's density."""
    sc = _mixed_scene(point=False, smooth=True)
    t = emitter_sampling.EmitterSampler(sc)
    right = _pdf_of_direction(sc, t)

    def sample_dir(u):
        ds, w, ok, _ = t.sample(_shading_point(dr.width(u)), mi.Point2f(u), mi.Bool(True))
        return ds.d, dr.select(ok, 1.0, 0.0)

    def wrong(wo):
        return right(wo) * dr.select(wo.x > 0.8 * dr.norm(wo), 1.1, 1.0)

    ok, msg = _chi2(sc, sample_dir, wrong)
    assert not ok, msg


@pytest.mark.usefixtures("in_tmp")
def test_chi2_mitsuba_samples_follow_table_pdf():
    """The other way round: directions from Mitsuba's
    ``scene.sample_emitter_direction`` follow the table's pdf with the
    uniform emitter choice (flat-shaded meshes, whose one-sidedness is
    the geometric normal for both)."""
    sc = _mixed_scene(point=False, smooth=False)
    t = emitter_sampling.EmitterSampler(sc, choice="uniform")

    def sample_dir(u):
        n = dr.width(u)
        ds, w = sc.sample_emitter_direction(_shading_point(n), mi.Point2f(u), False, mi.Bool(True))
        return ds.d, dr.select((ds.pdf > 0.0) & (dr.max(mi.Color3f(w)) > 0.0), 1.0, 0.0)

    ok, msg = _chi2(sc, sample_dir, _pdf_of_direction(sc, t))
    assert ok, msg


def test_pdf_matches_mitsuba_for_uniform_choice():
    """For flat emitters the table's density with the uniform choice is
    Mitsuba's ``pdf_emitter_direction``."""
    sc = _mixed_scene(point=False, smooth=False, env=False)
    t = emitter_sampling.EmitterSampler(sc, choice="uniform")
    n = 1 << 16
    rng = mi.PCG32(n)
    si = _shading_point(n)
    ds, w, ok, _ = t.sample(si, mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Bool(True))
    ours = np.array(t.pdf(si, ds, ok))
    ref = np.array(sc.pdf_emitter_direction(si, ds, ok))
    okn = np.array(ok)
    assert okn.mean() > 0.3
    assert np.allclose(ours[okn], ref[okn], rtol=2e-3), np.max(np.abs(ours[okn] / ref[okn] - 1))


def _estimate(sample, n, seed):
    """Mean and standard error of luminance(w) * max(cos, 0) at ORIGIN."""
    rng = mi.PCG32(n, initseq=seed)
    si = _shading_point(n)
    ds, w, ok = sample(si, mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Bool(True))
    cos = dr.maximum(dr.dot(ds.d, mi.Vector3f(0.3, 0.8, 0.2) / math.sqrt(0.77)), 0.0)
    v = np.array(dr.select(ok, mi.luminance(mi.Color3f(w)) * cos, 0.0))
    return v.mean(), v.std() / math.sqrt(n)


@pytest.mark.parametrize("choice", ["power", "uniform"])
def test_weights_match_mitsuba_in_expectation(choice):
    """Irradiance-like estimates (all kinds, point light included) agree
    with Mitsuba's within 4 standard errors."""
    sc = _mixed_scene(point=True, smooth=False)
    t = emitter_sampling.EmitterSampler(sc, choice=choice)
    n = 1 << 21
    a, sa = _estimate(lambda si, u, m: t.sample(si, u, m)[:3], n, 1)
    b, sb = _estimate(lambda si, u, m: lights.sample_light_reference(sc, si, u, m), n, 2)
    assert abs(a - b) < 4.0 * math.hypot(sa, sb), (a, sa, b, sb)


def test_point_light_is_a_delta_with_its_choice_probability():
    sc = _mixed_scene(point=True)
    t = emitter_sampling.EmitterSampler(sc)
    k = [i for i, e in enumerate(sc.emitters()) if e.class_name() == "PointLight"][0]
    n = 1 << 18
    rng = mi.PCG32(n)
    si = _shading_point(n)
    ds, w, ok, em = t.sample(si, mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Bool(True))
    is_pt = np.array(em) == k
    assert (np.array(ds.delta) == is_pt).all()
    P = t.pmf[k]
    frac = is_pt.mean()
    assert abs(frac - P) < 5.0 * math.sqrt(P * (1 - P) / n), (frac, P)
    d2 = float(np.sum((np.array([0.0, 1.0, 2.0]) - np.array(ORIGIN)) ** 2))
    wr = np.array(w)[:, is_pt] if np.array(w).shape[0] == 3 else np.array(w)[is_pt].T
    assert np.allclose(wr[0], 3.0 / d2 / P, rtol=1e-5)
    assert np.allclose(np.array(ds.pdf)[is_pt], P)
    assert (np.array(t.pdf(si, ds, ok))[is_pt] == 0.0).all()


def test_moving_light_is_followed():
    """An animated emissive mesh: samples lie on its current position."""
    sc = plane_under_rect_light(light_transform=lambda t: np.array(
        [[1, 0, 0, 0.5 * t], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float))
    n = 4096
    si = _shading_point(n)
    u = mi.Point2f(mi.PCG32(n).next_float32(), mi.PCG32(n, initseq=5).next_float32())
    for t_ in (0.0, 1.0, 2.0):
        sc.set_time(t_)
        t = emitter_sampling.for_scene(sc.mi_scene)
        ds, w, ok, _ = t.sample(si, u, mi.Bool(True))
        x = np.array(ds.p.x)[np.array(ok)]
        assert x.size > 0 and x.min() >= 0.5 * t_ - 0.25 - 1e-4 and x.max() <= 0.5 * t_ + 0.25 + 1e-4, (t_, x.min(), x.max())
    assert emitter_sampling.for_scene(sc.mi_scene) is t   # one sampler per scene, refreshed in place


def test_switch_selects_the_sampler():
    sc = _mixed_scene()
    n = 64
    si = _shading_point(n)
    u = mi.Point2f(dr.linspace(mi.Float, 0.01, 0.99, n), dr.linspace(mi.Float, 0.3, 0.7, n))
    with lights.emitter_sampling_as("mitsuba"):
        assert lights.sampler(sc) is None
        ds_m, _, _ = lights.sample_light(sc, si, u, mi.Bool(True))
    with lights.emitter_sampling_as("table"):
        assert lights.sampler(sc) is not None
        ds_t, _, _ = lights.sample_light(sc, si, u, mi.Bool(True))
    ds_r, _, _ = lights.sample_light_reference(sc, si, u, mi.Bool(True))
    assert np.array_equal(np.array(ds_m.p), np.array(ds_r.p))
    assert not np.array_equal(np.array(ds_t.p), np.array(ds_r.p))
    with pytest.raises(ValueError):
        lights.set_emitter_sampling("bogus")


@pytest.mark.parametrize("name,choice", [("cornell", "uniform"), ("atrium", "uniform"), ("atrium", "power")])
def test_rt_with_table_matches_ground_truth_mean(name, choice, monkeypatch):
    """RT-N with the table against the 2048-sample ground truth (Mitsuba's
    sampling, MIS): image means agree within 2%."""
    monkeypatch.setattr(emitter_sampling, "DEFAULT_CHOICE", choice)
    s = scenes.load(name)
    assert emitter_sampling.for_scene(s.mi_scene).choice == choice
    gb = frame_gbuffers(s, views.single(s), 0, 64, 36)[0]
    gt = groundtruth.ground_truth(s, gb, 0, "single")
    with lights.emitter_sampling_as("table"):
        assert lights.sampler(s.mi_scene) is not None
        m = methods.create("rt256", s, seed=1)
        img = gbuffer.to_image(gb, gbuffer.compose(gb, m.shade(methods.FrameContext(0), None, 0, gb)))
    assert np.isfinite(img).all()
    valid = np.array(gb.valid).reshape(36, 64)
    a, b = img[valid].mean(), gt[valid].mean()
    assert b > 1e-3, "scene is black"
    assert abs(a - b) / b < 0.02, (name, a, b)


def test_bench_rays_reports_both_samplers():
    """`slc bench rays` measures Mitsuba's sampler and the table side by side
    (a smoke test: no timing is asserted)."""
    from slc.run import bench
    r = bench.bench_rays("cornell", 16, 9, n=2, repeats=1)
    assert set(r["samplers"]) == {"mitsuba", "table"}
    for x in r["samplers"].values():
        assert x["raw_ms"] > 0 and x["ours_ms"] > 0 and x["sample_ms"] > 0
    assert r["samplers"]["table"]["table"]["entries"] == 2   # cornell: one quad light, two triangles
    assert r["samplers"]["mitsuba"]["table"]["entries"] == 0
    lines = bench.report_lines(r)
    assert sum("ratio ours/raw" in ln for ln in lines) == 2


@pytest.mark.parametrize("mode", ["table", "mitsuba"])
def test_light_pdf_matches_the_sampler_in_use(mode):
    """lights.light_pdf / light_pdf_hit give ds.pdf of the sampler in use
    (flat emitters, where Mitsuba's pdf is the density of its samples)."""
    sc = _mixed_scene(point=False, smooth=False, env=False)
    emitter_sampling.for_scene(sc)
    n = 1 << 14
    rng = mi.PCG32(n)
    si = _shading_point(n)
    with lights.emitter_sampling_as(mode):
        ds, w, ok = lights.sample_light(sc, si, mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Bool(True))
        p = np.array(lights.light_pdf(sc, si, ds, ok))
        si2 = sc.ray_intersect(mi.Ray3f(si.p, ds.d), ok)   # a point in free space: no offset needed
        same = ok & si2.is_valid() & (dr.norm(si2.p - ds.p) < 1e-3)   # the ray found the sampled point
        ph = np.array(lights.light_pdf_hit(sc, si, si2, same))
    okn, samen = np.array(ok), np.array(same)
    ref = np.array(ds.pdf)
    assert okn.mean() > 0.3 and samen.sum() > 0.95 * okn.sum()
    assert np.allclose(p[okn], ref[okn], rtol=2e-3)
    assert np.allclose(ph[samen], ref[samen], rtol=2e-3)


def test_table_is_not_built_inside_a_symbolic_loop():
    """Building reads the scene on the host: inside a symbolic loop it
    fails with a clear message instead of silently falling back."""
    sc = _mixed_scene()   # a new scene: no table yet (the cache is not cleared: other tests' scenes keep theirs)

    def body(i):
        emitter_sampling.for_scene(sc)
        return (i + 1,)

    with pytest.raises(RuntimeError) as e:
        dr.while_loop((mi.UInt32(0),), lambda i: i < 2, body)
    chain, x = [], e.value
    while x is not None:
        chain.append(str(x))
        x = x.__cause__ or x.__context__
    assert any("inside a symbolic loop" in m for m in chain), chain
