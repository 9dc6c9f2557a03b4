"""XML scenes with instances (``shapegroup`` + ``instance``, as exporters write repeated
objects) load with every instance expanded into placed shapes (slc.scene.instances)."""
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import render_frames
from slc import methods
from slc.scene import bsdf_table, checks, scenes, views

# a tetrahedron as an exporter's mesh file (ASCII PLY), read by a relative file name
_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
0 0 0
0.4 0 0
0 0.4 0
0 0 0.4
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""

_XML = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="2.5, 2.0, 3.0" target="0, 0.4, 0" up="0, 1, 0"/></transform>
  </sensor>
  <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.6, 0.6, 0.6"/></bsdf>
  <bsdf type="roughplastic" id="red"><rgb name="diffuse_reflectance" value="0.6, 0.1, 0.1"/><float name="alpha" value="0.2"/></bsdf>
  <shape type="rectangle"><transform name="to_world"><matrix value="3 0 0 0  0 0 1 0  0 -3 0 0  0 0 0 1"/></transform><ref id="grey"/></shape>
  <shape type="shapegroup" id="thing">
    <shape type="cube" id="base"><transform name="to_world"><matrix value="0.2 0 0 0  0 0.1 0 0.1  0 0 0.3 0  0 0 0 1"/></transform><ref id="grey"/></shape>
    <shape type="ply"><string name="filename" value="tetra.ply"/>
      <transform name="to_world"><translate x="-0.1" y="0.2" z="0"/></transform><ref id="red"/></shape>
    <shape type="rectangle"><transform name="to_world"><matrix value="0.1 0 0 0.15  0 0 0.1 0.45  0 -0.2 0 0.1  0 0 0 1"/></transform><ref id="red"/></shape>
  </shape>
  <shape type="instance"><ref id="thing"/></shape>
  <shape type="instance"><ref id="thing"/><transform name="to_world"><matrix value="-0.8 0 0 1.0  0 0.8 0 0  0 0 0.8 -0.9  0 0 0 1"/></transform></shape>
  <shape type="instance"><ref id="thing"/><transform name="to_world"><rotate y="1" angle="40"/><scale x="1.3" y="0.7" z="1.0"/><translate x="-1.0" y="0" z="0.6"/></transform></shape>
  <emitter type="point"><point name="position" x="1" y="2.5" z="1.5"/><rgb name="intensity" value="12, 12, 12"/></emitter>
  <emitter type="spot"><transform name="to_world"><lookat origin="-1.5, 2.2, 1.5" target="0, 0, 0"/></transform>
    <rgb name="intensity" value="20, 20, 20"/><float name="cutoff_angle" value="35"/></emitter>
</scene>
"""


@pytest.fixture(scope="module")
def instanced(tmp_path_factory):
    d = tmp_path_factory.mktemp("instances")
    (d / "tetra.ply").write_text(_PLY)
    (d / "things.xml").write_text(_XML)
    return d / "things.xml"


def _rays(n=48):
    """A fan of rays from the sensor's position over the scene."""
    o = mi.Point3f(2.5, 2.0, 3.0)
    u, v = dr.meshgrid(dr.linspace(mi.Float, -0.55, 0.55, n), dr.linspace(mi.Float, -0.45, 0.45, n))
    fwd = dr.normalize(mi.Vector3f(-2.5, -1.6, -3.0))
    right = dr.normalize(dr.cross(fwd, mi.Vector3f(0, 1, 0)))
    up = dr.cross(right, fwd)
    return mi.Ray3f(mi.Point3f(o.x, o.y, o.z) + 0 * u, dr.normalize(fwd + right * u + up * v))


def test_instances_expand_into_the_same_geometry(instanced):
    """Every instance becomes its group's shapes placed by the instance's transform (a
    mirroring one and a rotated, non-uniformly scaled one among them, a mesh file read by a
    relative name): no instance is left, and rays hit the expanded scene where and as far as
    they hit Mitsuba's instanced scene, with the same normals."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no "unsupported type" shapes left to warn about
        sc = scenes.load(str(instanced))
    kinds = [s.class_name() for s in sc.mi_scene.shapes()]
    assert "Instance" not in kinds and "ShapeGroup" not in kinds
    assert len(kinds) == 1 + 3 * 3, kinds
    assert sorted(k for k in (s.id() for s in sc.mi_scene.shapes()) if k.startswith("base")) == \
        ["base@0", "base@1", "base@2"]

    ref = mi.load_file(str(instanced))          # Mitsuba's own instancing
    assert "Instance" in [s.class_name() for s in ref.shapes()]
    ray = _rays()
    a, b = sc.mi_scene.ray_intersect(ray), ref.ray_intersect(ray)
    ha, hb = np.array(a.is_valid()), np.array(b.is_valid())
    assert ha.sum() > 1000 and np.array_equal(ha, hb)
    np.testing.assert_allclose(np.array(a.t)[ha], np.array(b.t)[hb], rtol=1e-4, atol=1e-5)
    dot = np.abs(np.array(dr.dot(a.n, b.n)))[ha]
    assert dot.min() > 0.999, dot.min()


def test_an_instance_of_no_group_is_a_one_line_error(tmp_path):
    xml = tmp_path / "bad.xml"
    xml.write_text(_XML.replace('<shape type="instance"><ref id="thing"/></shape>',
                                '<shape type="instance" id="lost"><ref id="nothing"/></shape>'))
    with pytest.raises(checks.SceneError) as e:
        scenes.load(str(xml))
    msg = str(e.value)
    assert "\n" not in msg and "instance 'lost' refers to no shape group ('nothing')" in msg, msg


def test_two_sided_lanes_of_a_scene_without_a_bsdf_table():
    """A scene built with instances in Python (``mi.load_dict``) has no BSDF table: the
    two-sided lanes come from the BSDFs' flags."""
    sc = mi.load_dict({
        "type": "scene",
        "group": {"type": "shapegroup",
                  "s": {"type": "rectangle", "bsdf": {"type": "diffuse"}}},
        "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
        "pane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 1]),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
    })
    assert bsdf_table.for_scene(sc) is None
    si = sc.ray_intersect(mi.Ray3f(mi.Point3f([0.0, 0.5], [0.0, 0.5], [3.0, 0.5]), mi.Vector3f(0, 0, -1)))
    assert np.array(si.is_valid()).all()
    two = bsdf_table.two_sided(sc, si.bsdf(), mi.Bool(True))
    assert np.array(two).tolist() == [True, False]     # the twosided pane, then the instance's plane


@pytest.mark.slow
@pytest.mark.parametrize("method", ["slc", "adaptive"])
def test_cache_methods_shade_instanced_objects(instanced, method):
    """The cache methods give entries to the instanced objects (their pixels are lit, as the
    ground truth's) and adaptive renders the scene (its two-sided test read the BSDF flags
    with a wrong signature in scenes without a BSDF table)."""
    sc = scenes.load(str(instanced))
    v = views.single(sc, 0)[0]
    imgs, gbs = render_frames(sc, methods.create(method, sc, seed=0), [v], 2, 48, 27)
    gb, px = gbs[0], imgs[0]
    ids = np.array(dr.reinterpret_array(mi.UInt32, gb.si.shape)).reshape(27, 48)
    floor = np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sc.mi_scene.shapes()[0])))[0]
    obj = np.array(gb.valid).reshape(27, 48) & (ids != floor)
    assert obj.sum() > 30 and np.isfinite(px).all()
    assert (px[obj].sum(-1) > 0).mean() > 0.5, (px[obj].sum(-1) > 0).mean()
