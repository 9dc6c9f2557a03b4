"""lamps: a long gallery lit only by point and spot lights (32 by default: wall lamps, ceiling spots), with pillars, benches and glossy statues; static (option lights=N).

Layout (metres, y up): the gallery spans x in [-16, 16], z in [-5, 5], 6 m
high, with two rows of pillars, benches and a few glossy pedestals. Lights
are delta lights only: every second one a point light on a wall bracket at
2.5 m, the others spot lights under the ceiling aimed at the floor and the
pedestals (cut-off 35 degrees). ``lamps:lights=N`` (1-256) spreads N lights
along the gallery with the same total power. This is the case the Surface
Light Cones paper names as overkill for cones ("a simple visibility/occlusion
caching approach may work significantly better").

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import numpy as np

from slc.scene.builder import SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor
from slc.scene.camera import CameraPath

HX, HZ, HH = 16.0, 5.0, 6.0
N_LIGHTS = 32


# the options a scene name may carry (``lamps:lights=...``); scenes.load refuses others
OPTIONS = ('lights', 'exposure')


def build(**options):
    n = int(options.get("lights", N_LIGHTS))
    if not 1 <= n <= 256:
        raise ValueError(f"lights must be 1-256, got {n}")
    b = SceneBuilder("lamps")
    floor = principled([0.45, 0.42, 0.38], roughness=0.3, specular=0.5)
    wall = diffuse([0.62, 0.6, 0.56])
    stone = diffuse([0.5, 0.48, 0.45])
    wood = diffuse([0.45, 0.3, 0.18])
    metal = rough_conductor(0.12, "Au")
    b.add_quad([0, 0, 0], [HX, 0, 0], [0, 0, -HZ], bsdf=floor, name="floor")
    shell = [box_mesh([-HX - 0.4, 0, -HZ - 0.4], [HX + 0.4, HH, -HZ]), box_mesh([-HX - 0.4, 0, HZ], [HX + 0.4, HH, HZ + 0.4]),
             box_mesh([-HX - 0.4, 0, -HZ], [-HX, HH, HZ]), box_mesh([HX, 0, -HZ], [HX + 0.4, HH, HZ]),
             box_mesh([-HX - 0.4, HH, -HZ - 0.4], [HX + 0.4, HH + 0.3, HZ + 0.4])]
    b.add_trimesh(merge_meshes(shell), bsdf=wall, name="shell")
    xs = np.linspace(-HX + 3, HX - 3, 7)
    pillars = [box_mesh([x - 0.35, 0, s * 2.6 - 0.35], [x + 0.35, HH, s * 2.6 + 0.35]) for x in xs for s in (-1, 1)]
    b.add_trimesh(merge_meshes(pillars), bsdf=stone, name="pillars")
    benches = [box_mesh([x - 1.0, 0.4, -0.4], [x + 1.0, 0.5, 0.4]) for x in xs[::2]]
    benches += [box_mesh([x - 0.9, 0, -0.3], [x - 0.7, 0.4, 0.3]) for x in xs[::2]]
    benches += [box_mesh([x + 0.7, 0, -0.3], [x + 0.9, 0.4, 0.3]) for x in xs[::2]]
    b.add_trimesh(merge_meshes(benches), bsdf=wood, name="benches")
    for k, x in enumerate(xs[1::2]):
        b.add_box([x - 0.4, 0, -0.4], [x + 0.4, 1.0, 0.4], bsdf=stone, name="pedestal")
        b.add_sphere([x, 1.45, 0.0], 0.45, subdivisions=3, bsdf=metal, name="statue")
    # delta lights along the gallery, alternating wall points and ceiling spots
    total = 40.0 * N_LIGHTS
    for i in range(n):
        x = -HX + 1.0 + (2 * HX - 2.0) * (i + 0.5) / n
        warm = np.array([1.0, 0.8, 0.55]) if i % 3 else np.array([0.75, 0.85, 1.0])
        I = total / n * warm
        if i % 2 == 0:
            z = -HZ + 0.35 if (i // 2) % 2 == 0 else HZ - 0.35
            b.add_point_light([x, 2.5, z], I, name="wall_lamp")
        else:
            z = -1.5 if (i // 2) % 2 == 0 else 1.5
            b.add_spot_light([x, HH - 0.2, z], [x, 0.0, 0.3 * z], 2.0 * I, cutoff_deg=35.0, name="ceiling_spot")
    paths = [
        CameraPath([([-14.0, 1.7, 0.0], [0.0, 1.2, 0.0]), ([-6.0, 1.7, 1.2], [6.0, 1.0, -1.0]),
                    ([3.0, 1.8, -1.0], [14.0, 1.5, 0.5])], fov=60, name="walk"),
        CameraPath([([14.0, 4.5, 4.0], [0.0, 0.5, -1.0]), ([0.0, 4.8, 4.2], [-10.0, 0.5, -2.0]),
                    ([-13.0, 4.5, 3.5], [0.0, 1.0, -1.0])], fov=60, name="balcony"),
        CameraPath([([-3.0, 1.2, -4.0], [1.0, 1.2, 3.0]), ([0.0, 1.3, -4.2], [4.0, 1.0, 2.0]),
                    ([3.0, 1.2, -4.0], [-1.0, 1.4, 3.0])], fov=65, name="side"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 0.3)), unit=1.0, meeting_center=[0.0, 1.5, 0.0],
                   description=__doc__.strip().splitlines()[0])
