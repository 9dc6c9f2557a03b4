"""street: Bistro-like night street, fully dynamic: two moving emissive spheres, a rotating emissive cube and cars with spinning wheels travel between two rows of facades.

Layout (metres, y up): the street runs along x in [-24, 24]; the roadway is
z in [-4, 4], sidewalks z in [-6.5, -4] and [4, 6.5], facades stand at
|z| = 6.5 with balconies, awnings and window frames. Everything that moves is
a small triangle mesh animated rigidly (``transform(t)``, t in seconds):

* two emissive spheres (radius 0.3 m) drift along the street at 2.5-3.5 m
  height in opposite directions, weaving across it;
* an emissive cube (0.5 m) tumbles about a tilted axis while travelling;
* three cars drive along their lanes (wrapping around at the ends of the
  street) and their wheels spin at the matching angular speed (~800 deg/s);
  each wheel (tyre + hub) carries a metal spoke cross so the rotation is visible.

The only lights are the three moving ones (night scene).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import math

import numpy as np
import trimesh

from slc.scene.builder import (SceneBuilder, about, box_mesh, diffuse, merge_meshes, principled, rotate,
                               rough_conductor, translate)
from slc.scene.camera import CameraPath

HALF_LEN = 24.0
ROAD_Z, WALK_Z = 4.0, 6.5
WHEEL_R = 0.34
SPHERE_RADIANCE = (260.0, 200.0, 120.0)
SPHERE2_RADIANCE = (120.0, 170.0, 260.0)
CUBE_RADIANCE = (220.0, 90.0, 60.0)


def _sphere_path(x0, speed, z_amp, z_freq, y0, phase):
    def T(t):
        x = x0 + 14.0 * math.sin(speed * t + phase)
        z = z_amp * math.sin(z_freq * t + phase)
        y = y0 + 0.3 * math.sin(2.0 * t + phase)
        return translate([x - x0, y - y0, z])
    return T


def _facades(side, rng):
    """One row of facades along x at z = side * WALK_Z (side = +1 or -1)."""
    parts, frames, awnings = [], [], []
    x = -HALF_LEN
    z_face = side * WALK_Z
    while x < HALF_LEN - 1e-6:
        w = float(min(rng.uniform(5.0, 8.0), HALF_LEN - x))
        h = float(rng.uniform(8.0, 14.0))
        setback = float(rng.uniform(0.0, 0.4))
        zf = z_face + side * setback
        parts.append(box_mesh([x, 0.0, min(zf, zf + side * 4.0)], [x + w, h, max(zf, zf + side * 4.0)]))
        # window frames / pilasters (protruding 0.12 m) and floor cornices
        for fx in np.arange(x + 0.9, x + w - 0.6, 1.8):
            for fy in np.arange(3.4, h - 1.5, 3.0):
                frames.append(box_mesh([fx - 0.55, fy, min(zf, zf - side * 0.12)],
                                   [fx + 0.55, fy + 1.6, max(zf, zf - side * 0.12)]))
        for fy in np.arange(3.0, h - 0.5, 3.0):
            frames.append(box_mesh([x, fy - 0.15, min(zf, zf - side * 0.25)], [x + w, fy, max(zf, zf - side * 0.25)]))
        # a balcony on the first floor and an awning over the ground floor on some buildings
        if rng.uniform() < 0.6:
            bx = x + 0.2 * w
            frames.append(box_mesh([bx, 3.1, min(zf, zf - side * 1.0)], [bx + 0.6 * w, 3.25, max(zf, zf - side * 1.0)]))
        if rng.uniform() < 0.7:
            ax = x + 0.5
            a0, a1 = zf, zf - side * 1.6
            V = np.array([[ax, 2.9, a0], [ax + w - 1.0, 2.9, a0], [ax + w - 1.0, 2.4, a1], [ax, 2.4, a1]])
            awnings.append(trimesh.Trimesh(V, [[0, 1, 2], [0, 2, 3]], process=False))
        x += w
    return parts, frames, awnings


def _car_body(length, width, height):
    body = box_mesh([-length / 2, 0.25, -width / 2], [length / 2, 0.25 + 0.55 * height, width / 2])
    cabin = box_mesh([-0.3 * length, 0.25 + 0.55 * height, -0.45 * width], [0.2 * length, 0.25 + height, 0.45 * width])
    return merge_meshes([body, cabin])


def _wheel():
    """A tyre centred at the origin, axis along z, and its hub: a spoke cross
    standing out of both faces (separate mesh, bright metal, so the spin shows)."""
    tyre = trimesh.creation.cylinder(radius=WHEEL_R, height=0.22, sections=12)
    hub = merge_meshes([box_mesh([-0.8 * WHEEL_R, -0.05, -0.13], [0.8 * WHEEL_R, 0.05, 0.13]),
                  box_mesh([-0.05, -0.8 * WHEEL_R, -0.13], [0.05, 0.8 * WHEEL_R, 0.13])])
    return tyre, hub


# the options a scene name may carry (``street:exposure=...``); scenes.load refuses others
OPTIONS = ('exposure',)


def build(**options):
    b = SceneBuilder("street")
    rng = np.random.default_rng(7)
    asphalt = principled([0.08, 0.08, 0.09], roughness=0.3, specular=0.5)
    curb = diffuse([0.45, 0.44, 0.42])
    wall_cols = [diffuse([0.62, 0.50, 0.38]), diffuse([0.55, 0.57, 0.60]), principled([0.70, 0.62, 0.50], 0.3)]
    frame_mat = diffuse([0.85, 0.83, 0.78])
    glass = rough_conductor(0.05, rgb=[0.5, 0.55, 0.6])
    awning_mat = {"type": "twosided", "bsdf": diffuse([0.55, 0.1, 0.08])}
    metal = rough_conductor(0.12, "Al")
    black = diffuse([0.0, 0.0, 0.0])
    tyre_mat = diffuse([0.06, 0.06, 0.06])
    hub_mat = rough_conductor(0.15, "Al")

    # ground: glossy wet-looking asphalt, raised sidewalks
    b.add_quad([0, 0, 0], [HALF_LEN, 0, 0], [0, 0, -ROAD_Z], bsdf=asphalt, name="road")
    b.add_trimesh(merge_meshes([box_mesh([-HALF_LEN, 0, ROAD_Z], [HALF_LEN, 0.15, WALK_Z + 0.5]),
                          box_mesh([-HALF_LEN, 0, -WALK_Z - 0.5], [HALF_LEN, 0.15, -ROAD_Z])]),
                  bsdf=curb, name="sidewalks")
    # facades: blocks by colour, frames, dark glossy windows, awnings
    blocks = [[], [], []]
    frames, awnings = [], []
    for side in (-1, 1):
        parts, fr, aw = _facades(side, rng)
        for i, p in enumerate(parts):
            blocks[int(rng.integers(0, 3))].append(p)
        frames += fr
        awnings += aw
    for i, blk in enumerate(blocks):
        if blk:
            b.add_trimesh(merge_meshes(blk), bsdf=wall_cols[i], name=f"facades{i}")
    b.add_trimesh(merge_meshes(frames), bsdf=frame_mat, name="frames")
    b.add_trimesh(merge_meshes(awnings), bsdf=awning_mat, name="awnings")
    # lamp posts (unlit, glossy metal) and cafe tables on the sidewalks
    props = []
    for x in np.arange(-20.0, 21.0, 8.0):
        for side in (-1, 1):
            z = side * (ROAD_Z + 0.5)
            props.append(trimesh.creation.cylinder(radius=0.07, segment=[[x, 0.15, z], [x, 4.2, z]], sections=8))
            props.append(box_mesh([x - 0.2, 4.2, z - 0.2], [x + 0.2, 4.5, z + 0.2]))
    for x in (-14.0, -12.0, 5.0, 7.0, 16.0):
        for side in (-1, 1):
            z = side * 5.6
            props.append(trimesh.creation.cylinder(radius=0.04, segment=[[x, 0.15, z], [x, 0.85, z]], sections=6))
            props.append(trimesh.creation.cylinder(radius=0.38, segment=[[x, 0.85, z], [x, 0.9, z]], sections=16))
    b.add_trimesh(merge_meshes(props), bsdf=metal, name="street_props")

    # cars: body + wheels, driving along +x (z < 0 lane) or -x (z > 0 lane), wrapping around
    period_len = 2 * HALF_LEN - 6.0
    cars = [(-10.0, -2.0, 6.0, [0.7, 0.05, 0.05]), (4.0, 2.0, -5.0, [0.1, 0.2, 0.6]),
            (15.0, -2.0, 4.0, [0.85, 0.85, 0.8])]
    for ci, (x0, zc, v, col) in enumerate(cars):
        L, Wd, Hh = 4.0, 1.8, 1.4

        def car_x(t, x0=x0, v=v):
            return (x0 + v * t + HALF_LEN - 3.0) % period_len - (HALF_LEN - 3.0)

        def body_T(t, zc=zc, v=v, car_x=car_x):
            return translate([car_x(t), 0.0, zc]) @ rotate([0, 1, 0], 0.0 if v > 0 else 180.0)

        body = _car_body(L, Wd, Hh)
        b.add_trimesh(body, bsdf=principled(col, roughness=0.12, metallic=0.6), name=f"car{ci}", transform=body_T)
        b.add_trimesh(box_mesh([-0.28 * L, 0.25 + 0.6 * Hh, -0.455 * Wd], [0.18 * L, 0.2 + Hh, 0.455 * Wd]),
                      bsdf=glass, name=f"car{ci}_glass", transform=body_T)
        for wx in (-0.32 * L, 0.32 * L):
            for wz in (-0.5 * Wd - 0.06, 0.5 * Wd + 0.06):
                tyre, hub = _wheel()
                omega = math.degrees(v / WHEEL_R)  # deg/s; rolling without slipping

                def wheel_T(t, wx=wx, wz=wz, omega=omega, body_T=body_T):
                    # spin about the wheel's own axis (z), then place it on the moving car
                    return body_T(t) @ translate([wx, WHEEL_R, wz]) @ rotate([0, 0, 1], -abs(omega) * t)

                b.add_trimesh(tyre, bsdf=tyre_mat, name=f"car{ci}_tyre", transform=wheel_T)
                b.add_trimesh(hub, bsdf=hub_mat, name=f"car{ci}_hub", transform=wheel_T)

    # lights: two moving emissive spheres and one tumbling emissive cube
    s1 = _sphere_path(0.0, 0.55, 2.5, 1.3, 3.0, 0.0)
    b.add_sphere([0, 3.0, 0], 0.3, subdivisions=2, bsdf=black, emission=SPHERE_RADIANCE, name="orb_warm",
                 transform=s1)
    s2 = _sphere_path(0.0, -0.45, 2.0, 1.7, 2.5, 2.0)
    b.add_sphere([0, 2.5, 0], 0.3, subdivisions=2, bsdf=black, emission=SPHERE2_RADIANCE, name="orb_cool",
                 transform=s2)

    def cube_T(t):
        x = -16.0 + 32.0 * (0.5 - 0.5 * math.cos(0.35 * t + 0.6))
        return translate([x, 0.6 * math.sin(1.5 * t), 0.8 * math.cos(0.9 * t)]) @ \
            about([0, 2.2, 0], rotate([1, 1, 0.3], 140.0 * t))
    b.add_box([-0.25, 1.95, -0.25], [0.25, 2.45, 0.25], bsdf=black, emission=CUBE_RADIANCE, name="cube_light",
              transform=cube_T)

    paths = [
        CameraPath([([-18.0, 1.7, -5.2], [0.0, 2.0, 0.0]), ([-12.0, 1.7, -5.0], [2.0, 2.5, 2.0]),
                    ([-6.0, 1.8, -5.4], [6.0, 2.0, 3.0]), ([0.0, 1.7, -5.0], [10.0, 2.0, 0.0]),
                    ([5.0, 1.7, -5.3], [15.0, 3.0, 2.0])], fov=60, name="sidewalk"),
        CameraPath([([12.0, 5.0, 0.0], [0.0, 1.0, 0.0]), ([8.0, 4.0, 2.5], [-4.0, 1.5, -3.0]),
                    ([3.0, 3.5, 1.0], [-8.0, 2.0, 4.0]), ([-2.0, 4.5, -1.5], [-12.0, 1.0, 0.0])],
                   fov=55, name="street_fly"),
        CameraPath([([-3.0, 1.6, 5.5], [3.0, 2.0, -6.0]), ([0.0, 1.6, 5.4], [-6.0, 3.0, -6.0]),
                    ([3.0, 1.7, 5.6], [4.0, 1.0, 0.0]), ([6.0, 1.6, 5.3], [-4.0, 2.0, -3.0])],
                   fov=65, name="cafe"),
        CameraPath([([-20.0, 9.0, 0.0], [-6.0, 0.0, 0.0]), ([-10.0, 8.0, -2.0], [2.0, 0.0, 1.0]),
                    ([0.0, 7.5, 2.0], [12.0, 0.0, -1.0]), ([10.0, 8.5, 0.0], [20.0, 1.0, 0.0])],
                   fov=60, name="overhead"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 2.0)), unit=1.0,
                   meeting_center=[0.0, 1.5, 0.0], description=__doc__.strip().splitlines()[0])
