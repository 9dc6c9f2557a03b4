"""box_export: a Cornell box written as exporters write it (Bitterli's Mitsuba XML): rectangles and cubes placed by matrices, walls facing out, a mirrored cube, a rectangle light by a matrix; static.

Layout (metres, y up): the box spans x, z in [-1, 1] and y in [0, 2], open towards +z.
As in B. Bitterli's "Cornell box" for Mitsuba: every wall is a ``rectangle`` placed by a
4x4 ``matrix``, with a ``twosided`` diffuse material, and the walls' and ceiling's normals
point out of the box (the light reaches their back sides); the floor faces up. The two
boxes are ``cube`` shapes placed by matrices: the short one with a mirroring matrix
(negative determinant: its triangles' winding, and so their geometric normals, are
reversed, its shading normals are not) and a one-sided diffuse material, the tall one
``principled``. The light is a 0.47 m x 0.38 m ``rectangle`` 2 cm below the ceiling,
facing down, placed by a matrix with a non-uniform scale, of radiance (17, 12, 4).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at 1.4 m/s in
front of the box's opening, with view turns up to 30 deg/s at 60 Hz.
"""
import numpy as np

from slc.scene.camera import CameraPath
from slc.scene.scenes import load_xml_text, xml_matrix

FLOOR = "-4.37114e-8 1 4.37114e-8 0 0 -8.74228e-8 2 0 1 4.37114e-8 1.91069e-15 0 0 0 0 1"
CEILING = "-1 7.64274e-15 -1.74846e-7 0 -8.74228e-8 8.74228e-8 2 2 0 1 -8.74228e-8 0 0 0 0 1"
BACK = "1.91069e-15 1 1.31134e-7 0 1 3.82137e-15 -8.74228e-8 1 -4.37114e-8 1.31134e-7 -2 -1 0 0 0 1"
RIGHT = "4.37114e-8 -1.74846e-7 2 1 1 3.82137e-15 -8.74228e-8 1 3.82137e-15 1 2.18557e-7 0 0 0 0 1"
LEFT = "-4.37114e-8 8.74228e-8 -2 -1 1 3.82137e-15 -8.74228e-8 1 0 -1 -4.37114e-8 0 0 0 0 1"
SHORT = "0.0851643 0.289542 1.31134e-8 0.328631 3.72265e-9 1.26563e-8 -0.3 0.3 -0.284951 0.0865363 5.73206e-16 " \
        "0.374592 0 0 0 1"
TALL = "0.286776 0.098229 -2.29282e-15 -0.335439 1.76858e-8 -5.16329e-8 -0.6 0.6 -0.0997984 0.282266 -2.62268e-8 " \
       "-0.291415 0 0 0 1"
LIGHT = "0.235 -1.66103e-8 -7.80685e-9 -0.005 -2.05444e-8 3.90343e-9 -0.0893 1.98 2.05444e-8 0.19 8.30516e-9 " \
        "-0.03 0 0 0 1"


def _mirrored(value: str) -> str:
    """The matrix ``value`` with its local x axis reversed (a cube looks the same, its winding does not)."""
    M = np.array(value.split(), float).reshape(4, 4)
    return xml_matrix(M @ np.diag([-1.0, 1.0, 1.0, 1.0]))


XML = f"""<scene version="3.0.0">
  <bsdf type="twosided" id="LeftWall"><bsdf type="diffuse"><rgb name="reflectance" value="0.63, 0.065, 0.05"/></bsdf></bsdf>
  <bsdf type="twosided" id="RightWall"><bsdf type="diffuse"><rgb name="reflectance" value="0.14, 0.45, 0.091"/></bsdf></bsdf>
  <bsdf type="twosided" id="Floor"><bsdf type="diffuse"><rgb name="reflectance" value="0.725, 0.71, 0.68"/></bsdf></bsdf>
  <bsdf type="twosided" id="Light"><bsdf type="diffuse"><rgb name="reflectance" value="0, 0, 0"/></bsdf></bsdf>
  <bsdf type="diffuse" id="ShortBox"><rgb name="reflectance" value="0.725, 0.71, 0.68"/></bsdf>
  <bsdf type="principled" id="TallBox">
    <rgb name="base_color" value="0.8, 0.7, 0.55"/><float name="roughness" value="0.3"/><float name="specular" value="0.5"/>
  </bsdf>
  <shape type="rectangle" id="floor"><transform name="to_world"><matrix value="{FLOOR}"/></transform><ref id="Floor"/></shape>
  <shape type="rectangle" id="ceiling"><transform name="to_world"><matrix value="{CEILING}"/></transform><ref id="Floor"/></shape>
  <shape type="rectangle" id="back"><transform name="to_world"><matrix value="{BACK}"/></transform><ref id="Floor"/></shape>
  <shape type="rectangle" id="right"><transform name="to_world"><matrix value="{RIGHT}"/></transform><ref id="RightWall"/></shape>
  <shape type="rectangle" id="left"><transform name="to_world"><matrix value="{LEFT}"/></transform><ref id="LeftWall"/></shape>
  <shape type="cube" id="short_box"><transform name="to_world"><matrix value="{_mirrored(SHORT)}"/></transform><ref id="ShortBox"/></shape>
  <shape type="cube" id="tall_box"><transform name="to_world"><matrix value="{TALL}"/></transform><ref id="TallBox"/></shape>
  <shape type="rectangle" id="light">
    <transform name="to_world"><matrix value="{LIGHT}"/></transform><ref id="Light"/>
    <emitter type="area"><rgb name="radiance" value="17, 12, 4"/></emitter>
  </shape>
</scene>
"""


def build(**options):
    look = [0.0, 0.9, 0.0]
    paths = [
        CameraPath([([-1.6, 1.0, 4.4], look), ([1.6, 1.1, 3.6], look), ([-1.2, 0.8, 2.8], look)],
                   fov=40, name="sweep"),
        CameraPath([([0.0, 1.0, 5.2], look), ([0.4, 1.3, 2.6], [0.0, 0.7, -0.5]), ([-1.8, 1.2, 3.4], look),
                    ([1.2, 0.9, 4.8], look)], fov=40, name="approach"),
        CameraPath([([1.9, 0.6, 3.0], [-0.2, 0.6, 0.0]), ([-1.9, 1.5, 3.2], [0.3, 0.8, 0.0]),
                    ([0.8, 1.0, 4.6], look)], fov=40, name="cross"),
    ]
    return load_xml_text("box_export", XML, paths, exposure=1.0, unit=1.0,
                         description="Cornell box as exporters write it (Bitterli's XML)")
