"""gallery_export: a gallery room written as exporters write it: objects repeated by instances, a mesh file, a rough aluminium floor under a spot, a point and a disk light; static.

Layout (metres, y up): a floor of 8 m x 8 m (x, z in [-4, 4]) with a back wall (z = -4) and a
left wall (x = -4), 4 m high. Everything as an exporter writes it: the floor and walls are
``rectangle`` shapes placed by 4x4 ``matrix`` values (the left wall facing out, ``twosided``
plaster); the floor is a ``roughconductor`` (aluminium, alpha 0.2). A plinth (a ``cube`` of a
diffuse and rough-aluminium ``blendbsdf``) carrying a torus read from a PLY file (glossy red
``roughplastic``) is one ``shapegroup`` placed three times by ``instance`` transforms: one
plain, one mirrored and scaled by 0.8, one turned and scaled by 1.1. A smooth silver sphere
(``conductor``) and a ``thindielectric`` pane stand on the floor. Lights: a ``spot`` (cut-off
25 deg) onto the first plinth, a dim blue ``point`` light by the back wall and a ``disk`` light
of radius 0.25 m at 2.6 m, facing down, placed by a mirroring matrix (emitting from one side).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at 1.4 m/s around
the plinths with view turns up to 30 deg/s at 60 Hz.
"""
import numpy as np

from slc.scene.camera import CameraPath
from slc.scene.scenes import load_xml_text


def _write_torus(path):
    """A torus (major radius 0.35 m, minor 0.12 m, 48 x 24 quads) as an ASCII PLY file."""
    nu, nv, R, r = 48, 24, 0.35, 0.12
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    P = np.stack([(R + r * np.cos(V)) * np.cos(U), r * np.sin(V), (R + r * np.cos(V)) * np.sin(U)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(P)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in P) + "".join(f"3 {p} {q} {s}\n" for p, q, s in F)
    path.write_text(head + body)


XML = """<scene version="3.0.0">
  <bsdf type="twosided" id="plaster"><bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.7, 0.68"/></bsdf></bsdf>
  <bsdf type="roughconductor" id="aluminium"><string name="material" value="Al"/><float name="alpha" value="0.2"/></bsdf>
  <bsdf type="blendbsdf" id="stone">
    <float name="weight" value="0.3"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.45, 0.4"/></bsdf>
    <bsdf type="roughconductor"><string name="material" value="Al"/><float name="alpha" value="0.2"/></bsdf>
  </bsdf>
  <bsdf type="conductor" id="silver"><string name="material" value="Ag"/></bsdf>
  <bsdf type="roughplastic" id="red"><rgb name="diffuse_reflectance" value="0.6, 0.1, 0.08"/><float name="alpha" value="0.05"/></bsdf>
  <bsdf type="thindielectric" id="pane"/>
  <bsdf type="diffuse" id="black"><rgb name="reflectance" value="0, 0, 0"/></bsdf>
  <shape type="rectangle" id="floor"><transform name="to_world"><matrix value="4 0 0 0  0 0 1 0  0 -4 0 0  0 0 0 1"/></transform><ref id="aluminium"/></shape>
  <shape type="rectangle" id="wall_back"><transform name="to_world"><matrix value="4 0 0 0  0 2 0 2  0 0 1 -4  0 0 0 1"/></transform><ref id="plaster"/></shape>
  <shape type="rectangle" id="wall_left"><transform name="to_world"><matrix value="0 0 -1 -4  0 2 0 2  4 0 0 0  0 0 0 1"/></transform><ref id="plaster"/></shape>
  <shape type="shapegroup" id="plinth">
    <shape type="cube" id="plinth_base"><transform name="to_world"><matrix value="0.3 0 0 0  0 0.25 0 0.25  0 0 0.3 0  0 0 0 1"/></transform><ref id="stone"/></shape>
    <shape type="ply" id="plinth_torus"><string name="filename" value="torus.ply"/>
      <transform name="to_world"><matrix value="1 0 0 0  0 0 -1 0.95  0 1 0 0  0 0 0 1"/></transform><ref id="red"/></shape>
  </shape>
  <shape type="instance" id="plinth_a"><ref id="plinth"/><transform name="to_world"><matrix value="1 0 0 -1.2  0 1 0 0  0 0 1 -0.8  0 0 0 1"/></transform></shape>
  <shape type="instance" id="plinth_b"><ref id="plinth"/><transform name="to_world"><matrix value="-0.8 0 0 1.0  0 0.8 0 0  0 0 0.8 -1.4  0 0 0 1"/></transform></shape>
  <shape type="instance" id="plinth_c"><ref id="plinth"/><transform name="to_world"><matrix value="0 0 1.1 0.2  0 1.1 0 0  -1.1 0 0 1.0  0 0 0 1"/></transform></shape>
  <shape type="sphere" id="silver_ball"><point name="center" x="1.6" y="0.4" z="1.2"/><float name="radius" value="0.4"/><ref id="silver"/></shape>
  <shape type="rectangle" id="glass_pane"><transform name="to_world"><matrix value="0.6 0 0 -0.2  0 0.5 0 0.5  0 0 1 0.1  0 0 0 1"/></transform><ref id="pane"/></shape>
  <shape type="disk" id="disk_light">
    <transform name="to_world"><matrix value="-0.25 0 0 0.6  0 0 -0.25 2.6  0 0.25 0 -0.5  0 0 0 1"/></transform><ref id="black"/>
    <emitter type="area"><rgb name="radiance" value="60, 55, 48"/></emitter>
  </shape>
  <emitter type="spot" id="spot">
    <transform name="to_world"><lookat origin="-2.5, 3.0, 2.0" target="-1.2, 0.9, -0.8"/></transform>
    <rgb name="intensity" value="120, 110, 100"/><float name="cutoff_angle" value="25"/><float name="beam_width" value="18"/>
  </emitter>
  <emitter type="point" id="blue_point"><point name="position" x="2.5" y="1.2" z="-2.5"/><rgb name="intensity" value="6, 7, 9"/></emitter>
</scene>
"""


def build(**options):
    c = [0.0, 0.6, -0.4]
    paths = [
        CameraPath([([3.2, 1.7, 3.4], c), ([0.5, 1.6, 3.8], c), ([-2.6, 1.8, 2.6], c), ([-3.0, 1.5, 0.6], c)],
                   fov=55, name="walk"),
        CameraPath([([2.8, 1.2, 0.8], [-1.2, 0.9, -0.8]), ([1.0, 1.4, 2.4], [-1.2, 0.9, -0.8]),
                    ([-0.4, 1.9, 2.8], [1.0, 0.6, -1.4]), ([-2.6, 1.5, 1.8], [1.0, 0.6, -1.4])], fov=55,
                   name="plinths"),
        CameraPath([([3.4, 2.2, -0.5], [0.0, 0.2, 0.2]), ([2.6, 2.4, 2.8], [0.0, 0.2, 0.2]),
                    ([-0.8, 2.2, 3.4], [0.0, 0.2, 0.2])], fov=55, name="high"),
    ]
    return load_xml_text("gallery_export", XML, paths, files={"torus.ply": _write_torus}, exposure=1.0, unit=1.0,
                         description="a gallery as exporters write it: instances, a mesh file, a rough aluminium floor")
