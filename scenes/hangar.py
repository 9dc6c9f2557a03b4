"""hangar: large hall lit by 12 small moving emissive spheres circling at different heights and speeds, with stacks of crates (some glossy) on a glossy floor; dynamic (option lights=N).

Layout (metres, y up): the hall spans x in [-20, 20], z in [-12, 12], walls
9 m high with ribbed steel columns and a roof with trusses. Crates (boxes,
0.8-2 m) stand in stacks; a third of them are glossy metal. The twelve lights
are emissive icospheres (radius 0.12 m, 80 triangles each) moving on
horizontal circles/ellipses around three centres, each at its own height
(0.8-6 m), speed (0.35-1.6 rad/s), direction and colour, plus a small
vertical bob. ``hangar:lights=N`` builds the same hall with N lights (the
first N of one deterministic sequence of orbits; their radiance scaled by
12/N so that the total power stays that of the twelve), for the many-lights
experiment (the paper's Fig. 17).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import math

import numpy as np
import trimesh

from slc.scene.builder import (SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor,
                               translate)
from slc.scene.camera import CameraPath

HX, HZ, HH = 20.0, 12.0, 9.0
LIGHT_RADIUS = 0.12
N_LIGHTS = 12


def _orbit(center, rx, rz, y, omega, phase, bob):
    c = np.asarray(center, float)

    def T(t):
        a = omega * t + phase
        p = c + np.array([rx * math.cos(a), y + bob * math.sin(2.3 * omega * t + phase), rz * math.sin(a)])
        return translate(p)
    return T


# the options a scene name may carry (``hangar:lights=...``); scenes.load refuses others
OPTIONS = ('lights', 'exposure')


def build(**options):
    b = SceneBuilder("hangar")
    rng = np.random.default_rng(99)
    floor = principled([0.35, 0.36, 0.38], roughness=0.18, specular=0.6)
    wall = diffuse([0.55, 0.56, 0.58])
    steel = rough_conductor(0.25, rgb=[0.55, 0.56, 0.58])
    wood = diffuse([0.55, 0.40, 0.22])
    green = diffuse([0.20, 0.32, 0.18])
    glossy_crate = rough_conductor(0.1, "Al")
    painted = principled([0.7, 0.45, 0.1], roughness=0.2, metallic=0.3)
    dark = diffuse([0.0, 0.0, 0.0])

    # the hall: floor (faces up), walls and roof as boxes
    b.add_quad([0, 0, 0], [HX, 0, 0], [0, 0, -HZ], bsdf=floor, name="floor")
    shell = [box_mesh([-HX - 0.5, 0, -HZ - 0.5], [HX + 0.5, HH, -HZ]), box_mesh([-HX - 0.5, 0, HZ], [HX + 0.5, HH, HZ + 0.5]),
             box_mesh([-HX - 0.5, 0, -HZ], [-HX, HH, HZ]), box_mesh([HX, 0, -HZ], [HX + 0.5, HH, HZ]),
             box_mesh([-HX - 0.5, HH, -HZ - 0.5], [HX + 0.5, HH + 0.4, HZ + 0.5])]
    b.add_trimesh(merge_meshes(shell), bsdf=wall, name="shell")
    # steel columns along the long walls and roof trusses across the hall
    frame = []
    for x in np.linspace(-HX + 2, HX - 2, 7):
        for s in (-1, 1):
            z = s * (HZ - 0.3)
            frame.append(box_mesh([x - 0.25, 0, z - 0.3], [x + 0.25, HH, z + 0.3]))
        frame.append(box_mesh([x - 0.15, HH - 0.9, -HZ], [x + 0.15, HH - 0.6, HZ]))
        for zz in np.linspace(-HZ + 2, HZ - 2, 6):
            frame.append(trimesh.creation.cylinder(radius=0.05, segment=[[x, HH - 0.9, zz], [x, HH, zz + 1.5]],
                                                   sections=6))
    b.add_trimesh(merge_meshes(frame), bsdf=steel, name="steel_frame")

    # crates in stacks: wood, painted, glossy aluminium
    groups = {"wood": [], "green": [], "glossy": [], "painted": []}
    stacks = [(-14.0, -7.0), (-9.0, 6.5), (-3.0, -8.0), (4.0, 7.0), (9.0, -6.0), (14.5, 5.0), (16.0, -8.5),
              (-16.0, 8.5), (0.5, 0.5)]
    kinds = list(groups)
    for (sx, sz) in stacks:
        y = 0.0
        for level in range(int(rng.integers(1, 4))):
            sz_ = float(rng.uniform(0.9, 2.0))
            ox, oz = rng.uniform(-0.3, 0.3, size=2)
            box = box_mesh([sx + ox - sz_ / 2, y, sz + oz - sz_ / 2], [sx + ox + sz_ / 2, y + sz_, sz + oz + sz_ / 2])
            ang = rng.uniform(-20, 20)
            box.apply_transform(trimesh.transformations.rotation_matrix(math.radians(ang), [0, 1, 0],
                                                                        [sx + ox, 0, sz + oz]))
            groups[kinds[int(rng.integers(0, 4))]].append(box)
            y += sz_
        # a few loose crates beside the stack
        for _ in range(2):
            s = float(rng.uniform(0.6, 1.0))
            cx, cz = sx + rng.uniform(-2.2, 2.2), sz + rng.uniform(-2.2, 2.2)
            groups[kinds[int(rng.integers(0, 4))]].append(box_mesh([cx - s / 2, 0, cz - s / 2], [cx + s / 2, s, cz + s / 2]))
    mats = {"wood": wood, "green": green, "glossy": glossy_crate, "painted": painted}
    for k, parts in groups.items():
        if parts:
            b.add_trimesh(merge_meshes(parts), bsdf=mats[k], name=f"crates_{k}")

    # small moving lights around three centres (12 by default); their orbits come from a
    # generator of their own, so the first N lights are the same for every N
    n_lights = int(options.get("lights", N_LIGHTS))
    if not 1 <= n_lights <= 256:
        raise ValueError(f"lights must be 1-256, got {n_lights}")
    lrng = np.random.default_rng(7)
    centres = [(-10.0, 0.0, 0.0), (0.0, 0.0, 0.0), (10.0, 0.0, 0.0)]
    palette = [(1.0, 0.85, 0.6), (0.6, 0.8, 1.0), (1.0, 0.5, 0.4), (0.7, 1.0, 0.6)]
    for i in range(n_lights):
        c = centres[i % 3]
        rx = float(lrng.uniform(3.0, 7.5))
        rz = float(lrng.uniform(3.0, 8.5))
        y = float(0.8 + 5.2 * ((i * 0.618034) % 1.0))
        omega = float(lrng.uniform(0.35, 1.6)) * (1 if i % 2 == 0 else -1)
        phase = float(lrng.uniform(0, 2 * np.pi))
        radiance = 250.0 * (N_LIGHTS / n_lights) * np.asarray(palette[i % 4])
        b.add_sphere([0, 0, 0], LIGHT_RADIUS, subdivisions=1, bsdf=dark, emission=radiance, name=f"light{i:02d}",
                     transform=_orbit(c, rx, rz, y, omega, phase, 0.4))

    paths = [
        CameraPath([([-18.0, 1.8, -10.0], [0.0, 1.5, 0.0]), ([-12.0, 2.0, -10.5], [0.0, 2.0, 4.0]),
                    ([-5.0, 1.8, -10.8], [8.0, 1.0, 4.0]), ([2.0, 2.0, -10.5], [14.0, 2.0, 0.0])],
                   fov=60, name="aisle"),
        CameraPath([([17.0, 7.5, 10.0], [0.0, 0.5, 0.0]), ([8.0, 7.8, 10.5], [-6.0, 0.5, -3.0]),
                    ([-4.0, 7.5, 10.0], [-12.0, 0.5, -4.0]), ([-16.0, 7.0, 9.0], [0.0, 1.0, -4.0])],
                   fov=60, name="gantry"),
        CameraPath([([-6.0, 1.5, 2.0], [4.0, 1.5, -3.0]), ([-2.5, 1.6, 3.5], [6.0, 2.5, 6.5]),
                    ([5.5, 1.7, 2.5], [14.0, 2.0, -2.0]), ([9.5, 1.6, 0.5], [0.5, 1.0, 0.5])],
                   fov=65, name="floor_walk"),
        CameraPath([([18.5, 3.0, -10.5], [-4.0, 2.0, 4.0]), ([18.0, 4.5, -2.0], [-10.0, 1.0, 0.0]),
                    ([18.5, 3.5, 6.0], [-4.0, 3.0, -6.0])], fov=55, name="end_wall"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 2.5)), unit=1.0,
                   meeting_center=[0.0, 1.5, 0.0], description=__doc__.strip().splitlines()[0])
