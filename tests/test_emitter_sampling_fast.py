"""The fast paths of light sampling and shading: the emitter table's packed
rows and selected segments (slc.scene.emitter_sampling) and the BSDF evaluation
without the virtual call for diffuse BSDFs (slc.scene.lights.SurfaceBSDF). Each is
checked against the plain path it replaces, bit for bit, or against closed
forms (the triangle areas)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from slc.scene import emitter_sampling, emitter_table, lights, scenes, views
from slc.methods import FrameContext
from slc.methods.rt.method import RandomLightSampling
from slc.scene.gbuffer import frame_gbuffers

from test_emitter_sampling import _mixed_scene, _shading_point


def _arr(x):
    return np.array(x)


def test_rows_hold_the_triangles_and_their_area_distribution():
    """Each mesh triangle's row holds its corner p0 and edges, P(e)/A_e, its
    emitter; the alias cells of a mesh reproduce P(t|e) = A_t / A_e exactly."""
    sc = _mixed_scene(point=False, env=False)
    t = emitter_sampling.EmitterSampler(sc)
    rows = _arr(t._rows).reshape(-1, emitter_table.ROW)
    seg = _arr(t._seg).reshape(-1, 2)
    assert rows.shape[0] == t.size
    ems = list(sc.emitters())
    checked = 0
    for k, i in enumerate(t.subset):
        sh = t._shapes.get(i)
        if sh is None or not sh.is_mesh() or sh.class_name() == "Rectangle":
            continue
        o, c = int(seg[k, 0]), int(seg[k, 1])
        V = _arr(sh.vertex_positions_buffer()).reshape(-1, 3).astype(np.float64)
        F = _arr(sh.faces_buffer()).reshape(-1, 3)
        if c != len(F):
            continue   # a mesh the table sees as a sphere/rectangle
        p0, e0, e1 = V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
        r = rows[o:o + c]
        assert np.allclose(r[:, emitter_table.ROW_P0:emitter_table.ROW_P0 + 3], p0, atol=1e-6)
        assert np.allclose(r[:, emitter_table.ROW_E0:emitter_table.ROW_E0 + 3], e0, atol=1e-6)
        assert np.allclose(r[:, emitter_table.ROW_E1:emitter_table.ROW_E1 + 3], e1, atol=1e-6)
        assert (r[:, emitter_table.ROW_EM] == i).all()
        area = 0.5 * np.linalg.norm(np.cross(e0, e1), axis=1)
        assert np.allclose(r[:, emitter_table.ROW_PA] * area.sum(), t.pmf[i], rtol=1e-5)
        # probability of each entry implied by the alias cells: (q_j + sum of (1 - q) of cells aliasing to it) / c
        cells = _arr(t._cells).reshape(-1, 2)[o:o + c]
        q, alias = cells[:, 0].astype(np.float64), cells[:, 1].astype(int)
        p = q.copy()
        np.add.at(p, alias, 1.0 - q)
        assert np.allclose(p / c, area / area.sum(), atol=1e-6)
        assert ems[i].get_shape() is not None
        checked += 1
    assert checked == 2   # the icosphere and the cube


@pytest.mark.slow
def test_selected_segments_equal_gathered_segments(monkeypatch):
    """Up to SEG_SELECT_MAX emitters, the segment is picked by selects over
    kernel parameters; above, gathered: both give the same samples, bit for bit."""
    sc = _mixed_scene()
    n = 1 << 14
    si = _shading_point(n)
    rng = mi.PCG32(n)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    for choice in ("uniform", "power"):
        a = emitter_sampling.EmitterSampler(sc, choice=choice)
        assert a._seg_params is not None and len(a._seg_params) == len(sc.emitters()) > 1
        monkeypatch.setattr(emitter_table, "SEG_SELECT_MAX", 0)
        b = emitter_sampling.EmitterSampler(sc, choice=choice)
        monkeypatch.undo()
        assert b._seg_params is None
        ra, rb = a.sample(si, u, mi.Bool(True)), b.sample(si, u, mi.Bool(True))
        assert _arr(ra[2]).mean() > 0.3
        for x, y in ((ra[0].p, rb[0].p), (ra[0].pdf, rb[0].pdf), (ra[1], rb[1]), (ra[2], rb[2]), (ra[3], rb[3])):
            assert np.array_equal(_arr(x), _arr(y))


def _bsdf_scene():
    """A floor of five strips with different BSDFs (diffuse, textured diffuse,
    rough conductor, principled, two-sided diffuse) under a rectangle light."""
    def strip(x, bsdf):
        return {"type": "rectangle", "bsdf": bsdf,
                "to_world": mi.ScalarTransform4f().translate([x, 0, 0]).rotate([1, 0, 0], -90).scale([0.2, 1, 1])}
    bsdfs = [{"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.3]}},
             {"type": "diffuse", "reflectance": {"type": "checkerboard",
                                                 "to_uv": mi.ScalarTransform4f().scale([7, 5, 1])}},
             {"type": "roughconductor", "alpha": 0.3},
             {"type": "principled", "base_color": {"type": "rgb", "value": [0.2, 0.6, 0.4]}, "roughness": 0.4},
             {"type": "twosided", "bsdf": {"type": "diffuse"}}]
    d = {"type": "scene",
         "light": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 2, 0]).rotate([1, 0, 0], 90),
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [3.0, 3.0, 3.0]}}}}
    for k, b in enumerate(bsdfs):
        d[f"s{k}"] = strip(-0.8 + 0.4 * k, b)
    return mi.load_dict(d)


def _floor_points(sc, n, seed=1):
    """Surface interactions on the floor strips, seen from random directions above and below."""
    rng = mi.PCG32(n, initseq=seed)
    x = -1.0 + 2.0 * rng.next_float32()
    z = -0.95 + 1.9 * rng.next_float32()
    d = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    target = mi.Point3f(x, 0.0, z)
    si = sc.ray_intersect(mi.Ray3f(target - 3.0 * d, d))
    return si, si.is_valid()


@pytest.mark.parametrize("all_diffuse", [False, True])
def test_surface_bsdf_equals_bsdf_eval_bitwise(all_diffuse):
    """SurfaceBSDF.eval equals bsdf.eval for every BSDF kind, directions in
    both hemispheres, masked lanes included; in an all-diffuse scene the
    virtual call is not traced at all (``others`` False)."""
    sc = _bsdf_scene()
    if all_diffuse:   # a textured and a plain diffuse surface, nothing else
        sc = mi.load_dict({"type": "scene",
                           "a": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {
                               "type": "checkerboard"}}, "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)},
                           "b": {"type": "disk", "bsdf": {"type": "diffuse"},
                                 "to_world": mi.ScalarTransform4f().translate([0, 0.5, 0]).rotate([1, 0, 0], 90)}})
    n = 1 << 14
    si, valid = _floor_points(sc, n)
    assert _arr(valid).mean() > 0.5
    ctx = mi.BSDFContext()
    sb = lights.SurfaceBSDF(sc, si, valid, ctx)
    assert sb.kd is not None and sb.others == (not all_diffuse)
    diff = _arr(sb.diffuse)
    assert diff[_arr(valid)].any() and (all_diffuse or not diff[_arr(valid)].all())
    rng = mi.PCG32(n, initseq=7)
    for _ in range(3):
        wo = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
        active = valid & (rng.next_float32() < 0.8)
        ref = _arr(mi.Color3f(si.bsdf().eval(ctx, si, wo, active)))
        got = _arr(sb.eval(wo, active))
        assert np.array_equal(got, ref)
        assert (ref[:, _arr(active)] > 0).any()


def test_surface_bsdf_keeps_the_virtual_call_for_other_contexts():
    """A context that is not plain radiance transport over all components
    (e.g. adjoint transport) evaluates every lane through bsdf.eval."""
    sc = _bsdf_scene()
    si, valid = _floor_points(sc, 4096)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    sb = lights.SurfaceBSDF(sc, si, valid, ctx)
    assert sb.kd is None
    wo = mi.Vector3f(0.3, 0.2, 0.9)
    assert np.array_equal(_arr(sb.eval(wo, valid)), _arr(mi.Color3f(si.bsdf().eval(ctx, si, wo, valid))))


def test_rt_with_surface_bsdf_equals_plain_eval():
    """RT-N's shading (SurfaceBSDF) equals the same loop with bsdf.eval, bit for bit, on atrium."""
    s = scenes.load("atrium")
    gb = frame_gbuffers(s, views.single(s), 0, 48, 27)[0]
    m = RandomLightSampling(s, n=4)
    got = _arr(m.shade(FrameContext(0), None, 0, gb))
    sc, si, active = s.mi_scene, gb.si, gb.valid
    sampler = lights.rng(gb.size, m.seed_for(0, 0), stream=1)
    bsdf, ctx = si.bsdf(), mi.BSDFContext()
    L = mi.Color3f(0.0)
    for _ in range(4):   # the same samples, unrolled, with the virtual call
        u = mi.Point2f(sampler.next_float32(), sampler.next_float32())
        L += lights.direct_sample(sc, si, bsdf, u, active, ctx)
    ref = _arr(L / 4.0)
    assert ref.max() > 0
    assert np.array_equal(got, ref)


def test_one_bsdf_table_per_scene():
    """The diffuse flags of SurfaceBSDF and the cone shading's BSDF kinds come from one
    table, built once per scene (cached, dropped by ``forget``): smooth diffuse BSDFs are
    flagged whatever their reflectance, only the constant one is KIND_DIFFUSE."""
    from slc.scene import bsdf_table
    from slc.lib.cones.shading import bsdf_table as cone_table
    sc = _bsdf_scene()
    t = bsdf_table.for_scene(sc)
    assert cone_table(sc) is t and bsdf_table.for_scene(sc) is t
    ids = [int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(s.bsdf()))[0]) for s in sc.shapes()
           if s.bsdf() is not None]
    diffuse, kind = _arr(t.diffuse), _arr(t.kind)
    strips = [s.id() for s in sc.shapes()]
    by_id = dict(zip(strips, ids))
    assert diffuse[by_id["s0"]] and diffuse[by_id["s1"]] and not diffuse[by_id["s2"]]
    assert kind[by_id["s0"]] == bsdf_table.KIND_DIFFUSE and kind[by_id["s1"]] == bsdf_table.KIND_NOT_PRINCIPLED
    assert kind[by_id["s3"]] == bsdf_table.KIND_PRINCIPLED and not t.all_diffuse
    bsdf_table.forget(id(sc))
    assert bsdf_table.for_scene(sc) is not t
