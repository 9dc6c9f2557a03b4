"""spheres: a dark room with four spherical lights (radii 0.03-1 m, radiances 1-1e4) over glossy plates (rough metal and plastic); static.

Layout (metres, y up): a room x in [-5, 5], z in [-4, 7], 4.5 m high, with
dark diffuse walls (albedo 0.04-0.06). Four spherical area lights hang in a
row 3 m above the floor near the back wall; their radii span 30x (0.03, 0.1,
0.3, 1 m) and their radiances four orders of magnitude (1e4, 1e3, 1e2, 1),
so the small lights are the brightest (as in Veach's multiple-importance
test scene). Below them four plates tilted towards the camera side reflect
the lights: rough aluminium (GGX alpha 0.01, 0.04, 0.12) and a rough
plastic (principled, roughness 0.3). The lights are flat-shaded triangle
meshes (icospheres), so the emitter's area density is exact.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import numpy as np

from slc.scene.builder import SceneBuilder, diffuse, principled, rough_conductor
from slc.scene.camera import CameraPath

HX, Z0, Z1, HH = 5.0, -4.0, 7.0, 4.5
# (centre, radius, RGB radiance) of the four lights: radii 0.03-1 m, radiances 1-1e4
LIGHTS = (
    ((-2.6, 3.0, -2.2), 1.0, (1.0, 0.9, 0.8)),
    ((-0.6, 3.0, -2.2), 0.3, (100.0, 95.0, 85.0)),
    ((0.9, 3.0, -2.2), 0.1, (1000.0, 1000.0, 1100.0)),
    ((2.3, 3.0, -2.2), 0.03, (10000.0, 9000.0, 8000.0)),
)
# (centre z, height y, tilt towards +z in degrees, BSDF) of the plates (4 m wide, 0.9 m deep)
PLATES = (
    (-0.9, 0.9, 25.0, rough_conductor(0.01, "Al")),
    (0.1, 0.7, 16.0, rough_conductor(0.04, "Al")),
    (1.1, 0.5, 10.0, rough_conductor(0.12, "Al")),
    (2.1, 0.3, 4.0, principled([0.15, 0.2, 0.3], roughness=0.3, specular=0.6)),
)


def add_room(b: SceneBuilder) -> None:
    """The room, its plates and its lights (everything but the camera paths)."""
    wall, floor = diffuse([0.06, 0.055, 0.05]), diffuse([0.04, 0.04, 0.04])
    b.add_quad([0, 0, 0.5 * (Z0 + Z1)], [HX, 0, 0], [0, 0, -0.5 * (Z1 - Z0)], bsdf=floor, name="floor")
    b.add_quad([0, HH, 0.5 * (Z0 + Z1)], [HX, 0, 0], [0, 0, 0.5 * (Z1 - Z0)], bsdf=wall, name="ceiling")
    b.add_quad([0, 0.5 * HH, Z0], [HX, 0, 0], [0, 0.5 * HH, 0], bsdf=wall, name="back")
    b.add_quad([0, 0.5 * HH, Z1], [0, 0.5 * HH, 0], [HX, 0, 0], bsdf=wall, name="front")
    b.add_quad([-HX, 0.5 * HH, 0.5 * (Z0 + Z1)], [0, 0.5 * HH, 0], [0, 0, 0.5 * (Z1 - Z0)], bsdf=wall, name="left")
    b.add_quad([HX, 0.5 * HH, 0.5 * (Z0 + Z1)], [0, 0, 0.5 * (Z1 - Z0)], [0, 0.5 * HH, 0], bsdf=wall, name="right")
    for z, y, tilt, bsdf in PLATES:
        t = np.radians(tilt)
        # u along x, v up the slope (towards -z); cross(u, v) faces up and towards +z
        b.add_quad([0, y, z], [2.0, 0, 0], [0, 0.45 * np.sin(t), -0.45 * np.cos(t)], bsdf=bsdf, name="plate")
    for c, r, L in LIGHTS:
        b.add_sphere(c, r, subdivisions=3, smooth=False, bsdf=diffuse([0, 0, 0]), emission=L, name="light")


def build(**options):
    b = SceneBuilder("spheres")
    add_room(b)
    paths = [
        CameraPath([([-3.0, 1.8, 5.5], [0.0, 1.0, -0.5]), ([0.0, 2.0, 5.8], [0.0, 1.2, -1.0]),
                    ([3.0, 1.8, 5.5], [0.0, 1.0, -0.5])], fov=50, name="front"),
        CameraPath([([3.5, 2.6, 4.5], [-0.5, 0.8, -1.0]), ([0.5, 2.4, 3.5], [0.0, 1.0, -1.5]),
                    ([-3.5, 2.6, 4.5], [0.5, 0.8, -1.0])], fov=55, name="high"),
        CameraPath([([-4.0, 1.2, 2.5], [1.0, 1.0, -1.5]), ([-1.0, 1.1, 4.0], [0.5, 1.2, -1.5]),
                    ([2.5, 1.3, 4.5], [-0.5, 1.0, -1.5]), ([4.0, 1.2, 2.5], [-1.0, 1.0, -1.5])], fov=60, name="low"),
    ]
    return b.build(paths, exposure=1.0, unit=1.0, meeting_center=[0.0, 1.2, -0.8],
                   description=__doc__.strip().splitlines()[0])
