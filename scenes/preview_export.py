"""preview_export: the usual material-preview set-up written as exporters write it: smooth plastic, glass and metal objects on a checkered plane under an environment map with a sun; static.

Layout (metres, y up): a 12 m x 12 m ``rectangle`` floor (placed by a matrix) with a
``checkerboard`` diffuse texture; on it a smooth ``plastic`` sphere, a smooth ``plastic``
``cube`` placed by a mirroring matrix (negative determinant: its geometric normals point
into it, its shading normals out), a smooth ``dielectric`` sphere, a ``principled`` metal
sphere and a ``roughconductor`` cube. The only light is an ``envmap``: a sky made in code
(deterministic), blue towards the zenith, a warm haze at the horizon, a dim ground, and a sun
of 1.5 degrees' radius 30 degrees above the horizon holding about 60% of the map's power
(written to a temporary EXR file that the XML names, as an exporter's file would be).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at 1.4 m/s around
the objects with view turns up to 30 deg/s at 60 Hz.
"""
import math

import numpy as np

from slc.scene.camera import CameraPath
from slc.scene.scenes import load_xml_text, xml_matrix

SUN_ELEVATION, SUN_AZIMUTH, SUN_RADIUS = 30.0, 135.0, 1.5        # degrees
SUN_RADIANCE = (9000.0, 8000.0, 6500.0)


def sky_map(width=512, height=256) -> np.ndarray:
    """The environment (lat-long, Mitsuba's envmap layout, y up): sky, haze, ground, sun."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta, phi = np.meshgrid(v * math.pi, u * 2 * math.pi, indexing="ij")
    d = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    up = d[..., 1:2]
    zenith, haze, ground = np.array([0.25, 0.45, 1.0]), np.array([1.1, 0.95, 0.8]), np.array([0.12, 0.1, 0.08])
    t = np.clip(up, 0.0, 1.0) ** 0.4
    img = np.where(up > 0.0, haze * (1 - t) + zenith * t, ground)
    e, a = math.radians(SUN_ELEVATION), math.radians(SUN_AZIMUTH)
    sun = np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])
    img[(d @ sun) > math.cos(math.radians(SUN_RADIUS))] = SUN_RADIANCE
    return img.astype(np.float32)


def _write_sky(path):
    import mitsuba as mi
    mi.Bitmap(sky_map()).write(str(path))


def _m(x, y, z, s, mirror=False, turn=0.0):
    c, s_ = math.cos(math.radians(turn)), math.sin(math.radians(turn))
    R = np.array([[c, 0, s_, 0], [0, 1, 0, 0], [-s_, 0, c, 0], [0, 0, 0, 1]])
    S = np.diag([(-s[0] if mirror else s[0]), s[1], s[2], 1.0])
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return xml_matrix(T @ R @ S)


XML = f"""<scene version="3.0.0">
  <emitter type="envmap" id="sky"><string name="filename" value="sky.exr"/></emitter>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><matrix value="{xml_matrix([[6, 0, 0, 0], [0, 0, 6, 0], [0, -6, 0, 0], [0, 0, 0, 1]])}"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.08"/><rgb name="color1" value="0.6"/>
      <transform name="to_uv"><scale x="16" y="16"/></transform></texture></bsdf>
  </shape>
  <shape type="sphere" id="plastic_ball"><point name="center" x="-0.9" y="0.6" z="0.0"/><float name="radius" value="0.6"/>
    <bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.6, 0.08, 0.06"/></bsdf></shape>
  <shape type="cube" id="plastic_cube"><transform name="to_world"><matrix value="{_m(0.7, 0.45, -0.2, (0.45, 0.45, 0.45), True, 20)}"/></transform>
    <bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.08, 0.15, 0.6"/><float name="int_ior" value="1.5"/></bsdf></shape>
  <shape type="sphere" id="glass_ball"><point name="center" x="0.2" y="0.35" z="1.1"/><float name="radius" value="0.35"/>
    <bsdf type="dielectric"/></shape>
  <shape type="sphere" id="gold_ball"><point name="center" x="-2.1" y="0.4" z="1.0"/><float name="radius" value="0.4"/>
    <bsdf type="principled"><rgb name="base_color" value="0.95, 0.7, 0.3"/><float name="metallic" value="1.0"/>
      <float name="roughness" value="0.25"/></bsdf></shape>
  <shape type="cube" id="steel_cube"><transform name="to_world"><matrix value="{_m(2.0, 0.3, 1.0, (0.3, 0.3, 0.3), False, -30)}"/></transform>
    <bsdf type="roughconductor"><string name="material" value="Al"/><float name="alpha" value="0.2"/></bsdf></shape>
</scene>
"""


def build(**options):
    c = [0.0, 0.4, 0.3]
    paths = [
        CameraPath([([0.0, 1.8, 6.8], c), ([4.6, 1.6, 5.2], c), ([6.8, 2.0, 1.2], c), ([5.6, 1.4, -3.8], c)],
                   fov=40, name="orbit"),
        CameraPath([([-4.5, 1.2, 2.5], c), ([-1.5, 2.5, 4.5], c), ([2.5, 1.0, 4.0], [0.5, 0.4, 0.0])],
                   fov=40, name="high"),
        CameraPath([([1.5, 0.9, 3.2], [-0.9, 0.6, 0.0]), ([-2.5, 1.0, 3.0], [0.7, 0.45, -0.2]),
                    ([-3.5, 1.6, -1.5], c), ([0.5, 2.0, -4.0], c)], fov=40, name="low"),
    ]
    return load_xml_text("preview_export", XML, paths, files={"sky.exr": _write_sky}, exposure=0.6, unit=1.0,
                         description="material preview as exporters write it: plastic under an environment map")
