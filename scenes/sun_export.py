"""sun_export: a courtyard lit by one directional light only (hard shadows), written as exporters write it: cubes placed by matrices, one mirrored, a pergola of thin beams; static.

Layout (metres, y up): a 16 m x 16 m ground ``rectangle`` (one-sided diffuse) placed by a
matrix; ``cube`` blocks placed by matrices with non-uniform scales (one by a mirroring
matrix), a pergola of 12 thin beams on four posts whose shadows are stripes a few
centimetres wide, a ``roughconductor`` sphere and a ``principled`` block. The only light
is a ``directional`` emitter (irradiance (3.0, 2.8, 2.5), 35 degrees above the horizon):
every shadow edge is hard, and one shadow ray per pixel is exact.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at 1.4 m/s through
the courtyard with view turns up to 30 deg/s at 60 Hz.
"""
import math

import numpy as np

from slc.scene.camera import CameraPath
from slc.scene.scenes import load_xml_text, xml_matrix


def _box(x, y, z, sx, sy, sz, turn=0.0, mirror=False):
    """A ``cube`` (the [-1, 1]^3 box) scaled to half-extents (sx, sy, sz), turned about y."""
    c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
    R = np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return xml_matrix(T @ R @ np.diag([(-sx if mirror else sx), sy, sz, 1.0]))


def _cube(name, M, bsdf):
    return f'  <shape type="cube" id="{name}"><transform name="to_world"><matrix value="{M}"/></transform>' \
           f'<ref id="{bsdf}"/></shape>\n'


def _shapes() -> str:
    out = [_cube("block_a", _box(-3.0, 1.0, -2.0, 1.0, 1.0, 1.5, 15), "stone"),
           _cube("block_b", _box(2.5, 0.6, -3.5, 1.5, 0.6, 0.6, -30, mirror=True), "stone"),
           _cube("plinth", _box(3.0, 0.4, 2.0, 0.8, 0.4, 0.8, 40), "marble")]
    for i, (x, z) in enumerate(((-1.5, 0.5), (1.5, 0.5), (-1.5, 3.5), (1.5, 3.5))):
        out.append(_cube(f"post{i}", _box(x, 1.2, z, 0.08, 1.2, 0.08), "wood"))
    for i in range(12):
        out.append(_cube(f"beam{i}", _box(0.0, 2.45, 0.5 + 0.27 * i, 1.7, 0.05, 0.04), "wood"))
    return "".join(out)


XML = f"""<scene version="3.0.0">
  <emitter type="directional"><vector name="direction" x="-0.45" y="-0.57" z="-0.69"/>
    <rgb name="irradiance" value="3.0, 2.8, 2.5"/></emitter>
  <bsdf type="diffuse" id="ground"><rgb name="reflectance" value="0.45, 0.42, 0.38"/></bsdf>
  <bsdf type="twosided" id="stone"><bsdf type="diffuse"><rgb name="reflectance" value="0.62, 0.55, 0.48"/></bsdf></bsdf>
  <bsdf type="twosided" id="wood"><bsdf type="diffuse"><rgb name="reflectance" value="0.4, 0.26, 0.15"/></bsdf></bsdf>
  <bsdf type="principled" id="marble"><rgb name="base_color" value="0.85, 0.85, 0.82"/><float name="roughness" value="0.2"/></bsdf>
  <shape type="rectangle" id="ground_plane">
    <transform name="to_world"><matrix value="{xml_matrix([[8, 0, 0, 0], [0, 0, 8, 0], [0, -8, 0, 0], [0, 0, 0, 1]])}"/></transform>
    <ref id="ground"/>
  </shape>
{_shapes()}  <shape type="sphere" id="ball"><point name="center" x="-0.5" y="0.7" z="-4.0"/><float name="radius" value="0.7"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.15"/></bsdf></shape>
</scene>
"""


def build(**options):
    c = [0.0, 0.8, 0.5]
    paths = [
        CameraPath([([6.0, 2.5, 6.5], c), ([0.0, 3.0, 7.5], c), ([-6.0, 2.2, 5.0], c)], fov=50, name="arc"),
        CameraPath([([-1.0, 1.7, 6.5], [0.0, 1.0, 1.5]), ([0.0, 1.7, 2.0], [0.0, 0.5, -3.0]),
                    ([3.5, 2.0, -1.0], [-1.0, 0.5, 1.5])], fov=55, name="through"),
        CameraPath([([-6.5, 3.5, -5.0], c), ([-6.0, 2.0, 2.5], c), ([-2.0, 4.0, 6.5], [0.0, 0.0, 0.0])],
                   fov=50, name="side"),
    ]
    return load_xml_text("sun_export", XML, paths, exposure=1.0, unit=1.0,
                         description="a courtyard under one directional light, as exporters write it")
