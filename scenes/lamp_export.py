"""lamp_export: a living room written as exporters write it: a tiny, very bright light inside a lamp shade, a ceiling panel, walls placed by matrices facing out; static.

Layout (metres, y up): a 6 m x 5 m room, 2.8 m high (x in [-3, 3], z in [-2.5, 2.5]).
Everything as an exporter writes it: walls and ceiling are ``rectangle`` shapes placed by
4x4 ``matrix`` values with non-uniform scales, their normals pointing out of the room,
with ``twosided`` materials; the floor is a ``twosided`` rough plastic. A side table (a
``cube`` placed by a matrix) carries a lamp: an open ``cylinder`` shade (two-sided diffuse)
around a bulb of two 5 cm ``rectangle`` lights back to back (a two-sided emitter: one faces
up, one down) of radiance 2500, so that the lamp's light leaves the fixture only through
the shade's two openings, onto the ceiling and the table. A second light, a 0.8 m x 0.5 m
ceiling panel (a ``rectangle`` placed by a matrix, facing down), lights the room's other
half. A sofa (``cube``, ``principled``), a rough conductor sphere and a one-sided diffuse
box (placed by a mirroring matrix) stand on the floor.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at 1.4 m/s through
the room with view turns up to 30 deg/s at 60 Hz.
"""
import numpy as np

from slc.scene.camera import CameraPath
from slc.scene.scenes import load_xml_text, xml_matrix


def _place(x, y, z, sx, sy, sz, axis=None, deg=0.0, mirror=False):
    """T(x, y, z) R(axis, deg) S(sx, sy, sz) as an exporter writes it (one matrix)."""
    S = np.diag([(-sx if mirror else sx), sy, sz, 1.0])
    R = np.eye(4)
    if axis is not None:
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        t = np.radians(deg)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        R[:3, :3] = np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return xml_matrix(T @ R @ S)


# rectangles face +z before their matrix; walls turned to face out of the room
WALLS = {
    "floor": _place(0, 0, 0, 3.0, 2.5, 1.0, [1, 0, 0], -90),             # faces up
    "ceiling": _place(0, 2.8, 0, 3.0, 2.5, 1.0, [1, 0, 0], -90),         # faces up (out of the room)
    "wall_n": _place(0, 1.4, -2.5, 3.0, 1.4, 1.0, [0, 1, 0], 180),       # faces -z (out)
    "wall_s": _place(0, 1.4, 2.5, 3.0, 1.4, 1.0),                        # faces +z (out)
    "wall_w": _place(-3.0, 1.4, 0, 2.5, 1.4, 1.0, [0, 1, 0], -90),       # faces -x (out)
    "wall_e": _place(3.0, 1.4, 0, 2.5, 1.4, 1.0, [0, 1, 0], 90),         # faces +x (out)
}
LAMP = np.array([-1.6, 0.0, -1.7])      # the side table's centre on the floor
BULB_Y = 0.62 + 0.42                    # inside the shade (0.90 to 1.20 m)

XML = f"""<scene version="3.0.0">
  <bsdf type="twosided" id="plaster"><bsdf type="diffuse"><rgb name="reflectance" value="0.78, 0.74, 0.68"/></bsdf></bsdf>
  <bsdf type="twosided" id="wood"><bsdf type="roughplastic">
    <rgb name="diffuse_reflectance" value="0.35, 0.22, 0.12"/><float name="alpha" value="0.15"/></bsdf></bsdf>
  <bsdf type="twosided" id="shade"><bsdf type="diffuse"><rgb name="reflectance" value="0.85, 0.8, 0.62"/></bsdf></bsdf>
  <bsdf type="twosided" id="table"><bsdf type="diffuse"><rgb name="reflectance" value="0.45, 0.3, 0.2"/></bsdf></bsdf>
  <bsdf type="twosided" id="black"><bsdf type="diffuse"><rgb name="reflectance" value="0, 0, 0"/></bsdf></bsdf>
  <bsdf type="principled" id="fabric"><rgb name="base_color" value="0.2, 0.3, 0.5"/><float name="roughness" value="0.8"/></bsdf>
  <bsdf type="roughconductor" id="chrome"><string name="material" value="Cr"/><float name="alpha" value="0.1"/></bsdf>
  <bsdf type="diffuse" id="paper"><rgb name="reflectance" value="0.7, 0.65, 0.5"/></bsdf>
{"".join(f'''  <shape type="rectangle" id="{k}"><transform name="to_world"><matrix value="{v}"/></transform><ref id="{'wood' if k == 'floor' else 'plaster'}"/></shape>
''' for k, v in WALLS.items())}  <shape type="cube" id="side_table"><transform name="to_world"><matrix value="{_place(LAMP[0], 0.31, LAMP[2], 0.3, 0.31, 0.3)}"/></transform><ref id="table"/></shape>
  <shape type="cylinder" id="lamp_shade">
    <point name="p0" x="{LAMP[0]}" y="0.90" z="{LAMP[2]}"/><point name="p1" x="{LAMP[0]}" y="1.20" z="{LAMP[2]}"/>
    <float name="radius" value="0.17"/><ref id="shade"/>
  </shape>
  <shape type="cylinder" id="lamp_stand">
    <point name="p0" x="{LAMP[0]}" y="0.62" z="{LAMP[2]}"/><point name="p1" x="{LAMP[0]}" y="1.0" z="{LAMP[2]}"/>
    <float name="radius" value="0.012"/><ref id="chrome"/>
  </shape>
  <shape type="rectangle" id="bulb_down">
    <transform name="to_world"><matrix value="{_place(LAMP[0], BULB_Y - 0.005, LAMP[2], 0.025, 0.025, 1.0, [1, 0, 0], 90)}"/></transform><ref id="black"/>
    <emitter type="area"><rgb name="radiance" value="2500, 2100, 1500"/></emitter>
  </shape>
  <shape type="rectangle" id="bulb_up">
    <transform name="to_world"><matrix value="{_place(LAMP[0], BULB_Y + 0.005, LAMP[2], 0.025, 0.025, 1.0, [1, 0, 0], -90)}"/></transform><ref id="black"/>
    <emitter type="area"><rgb name="radiance" value="2500, 2100, 1500"/></emitter>
  </shape>
  <shape type="rectangle" id="ceiling_panel">
    <transform name="to_world"><matrix value="{_place(1.2, 2.78, 0.6, 0.4, 0.25, 3.0, [1, 0, 0], 90)}"/></transform><ref id="black"/>
    <emitter type="area"><rgb name="radiance" value="24, 24, 25"/></emitter>
  </shape>
  <shape type="cube" id="sofa"><transform name="to_world"><matrix value="{_place(1.0, 0.35, -1.9, 1.0, 0.35, 0.45)}"/></transform><ref id="fabric"/></shape>
  <shape type="sphere" id="ball"><point name="center" x="0.4" y="0.3" z="0.9"/><float name="radius" value="0.3"/><ref id="chrome"/></shape>
  <shape type="cube" id="box"><transform name="to_world"><matrix value="{_place(-1.4, 0.2, 1.2, 0.25, 0.2, 0.35, [0, 1, 0], 25, mirror=True)}"/></transform><ref id="paper"/></shape>
</scene>
"""


def build(**options):
    lamp = [LAMP[0], 0.9, LAMP[2]]
    paths = [
        CameraPath([([2.2, 1.6, 2.0], lamp), ([0.5, 1.5, 2.2], lamp), ([-2.3, 1.7, 1.8], [0.5, 0.8, -1.5]),
                    ([1.5, 1.4, 1.0], [-2.0, 1.5, -2.0])], fov=60, name="walk"),
        CameraPath([([-2.5, 1.2, 2.0], [1.0, 1.0, -1.5]), ([2.4, 1.7, -0.5], [-1.5, 1.0, -1.0]),
                    ([0.0, 1.6, 2.2], [0.0, 2.2, -1.0])], fov=60, name="around"),
        CameraPath([([0.2, 1.1, 1.5], lamp), ([-0.6, 1.4, 0.2], lamp), ([1.8, 1.8, 0.5], [1.0, 0.3, -1.8]),
                    ([2.0, 1.2, 2.2], lamp)], fov=60, name="close"),
    ]
    return load_xml_text("lamp_export", XML, paths, exposure=2.0, unit=1.0,
                         description="a living room as exporters write it: a bright light inside a lamp shade")
