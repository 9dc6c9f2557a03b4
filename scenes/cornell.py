"""cornell: a Cornell box (2 m) with a square ceiling light, one glossy and one diffuse block; sanity scene with an analytic check.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""

from slc.scene.builder import SceneBuilder, classic_cornell, cornell_walls, diffuse, rough_conductor
from slc.scene.camera import CameraPath

LIGHT_HALF = 0.25       # the ceiling light is a 0.5 m x 0.5 m square
LIGHT_HEIGHT = 1.98     # just below the ceiling (y = 2)
LIGHT_RADIANCE = (12.0, 11.0, 9.0)


def build(variant="glossy", **options):
    """``variant``: ``glossy`` (this scene) or ``classic`` (the classic all-Lambertian box with
    a small warm light, seen from far: :func:`slc.scene.builder.classic_cornell`), e.g.
    ``slc run single-viewer --scene cornell:variant=classic``."""
    if variant == "classic":
        return classic_cornell()
    if variant != "glossy":
        raise ValueError(f"variant must be 'glossy' or 'classic', not '{variant}'")
    b = SceneBuilder("cornell")
    cornell_walls(b)      # walls of the box [-1, 1] x [0, 2] x [-1, 1], open at +z (the camera side)
    b.add_box([-0.65, 0, -0.6], [-0.05, 1.2, 0.0], bsdf=rough_conductor(0.15, "Al"), name="tall_block")
    b.add_box([0.1, 0, 0.05], [0.7, 0.6, 0.65], bsdf=diffuse([0.7, 0.7, 0.6]), name="short_block")
    # the light faces down: cross(u, v) = cross(x, z) = -y
    b.add_quad([0, LIGHT_HEIGHT, 0], [LIGHT_HALF, 0, 0], [0, 0, LIGHT_HALF], bsdf=diffuse([0, 0, 0]),
               emission=LIGHT_RADIANCE, name="light")
    # walking speed (1.4 m/s, turns up to 30 deg/s) in a 2 m box: the paths sweep back and forth for 4+ s
    paths = [
        CameraPath([([0, 1, 3.4], [0, 1, 0]), ([0.5, 1.2, 3.0], [0, 0.9, 0]), ([-0.4, 1.1, 3.2], [0, 1, 0]),
                    ([0.6, 0.9, 3.6], [0, 1, 0]), ([-0.6, 1.3, 3.0], [0, 0.9, 0]), ([0.0, 1.0, 3.8], [0, 1, 0]),
                    ([0.5, 1.1, 3.1], [0, 1, 0])], fov=45, name="front"),
        CameraPath([([0.7, 1.6, 0.9], [-0.3, 0.3, -0.5]), ([-0.7, 1.5, 0.8], [0.3, 0.3, -0.4]),
                    ([0.0, 1.7, 0.7], [0, 0, -0.6]), ([0.6, 1.6, 0.6], [-0.2, 0.3, -0.5]),
                    ([-0.5, 1.7, 0.9], [0.3, 0.2, -0.6])], fov=55, name="above"),
        CameraPath([([-0.8, 0.4, 0.9], [0.5, 0.8, -0.8]), ([0.8, 0.5, 0.9], [-0.5, 0.9, -0.8]),
                    ([0.0, 0.3, 0.95], [0.0, 1.2, -1.0]), ([0.7, 0.4, 0.9], [-0.4, 0.9, -0.8]),
                    ([-0.6, 0.5, 0.85], [0.4, 1.0, -0.8])], fov=60, name="low"),
    ]
    return b.build(paths, exposure=1.0, unit=1.0, meeting_center=[0, 0.8, -0.2],
                   description=__doc__.strip())
