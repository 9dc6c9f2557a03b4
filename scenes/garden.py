"""garden: San-Miguel-like courtyard with an arcade of pillars, dense thin foliage (thousands of leaf quads), several lamps and a sunset environment map; static.

Layout (metres, y up): a 20 m x 20 m paved courtyard (x, z in [-10, 10])
closed by 4.5 m walls; an arcade (pillars, lintel and a roof slab) runs along
the north (z < 0) and west (x < 0) sides; four trees (trunks + leaf canopies)
and eight bushes, ~5700 leaves in all, each a small two-sided quad (random
orientation, deterministic numpy RNG, merged into a few meshes); café tables
with glossy tops; lamps: small emissive spheres hanging in the arcade and on
posts, and two emissive lantern boxes. The sky is
``../shared/envmaps/venice_sunset_1k.hdr`` when present, otherwise a constant
dusk-blue environment.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import numpy as np
import trimesh

from slc.scene.builder import SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor
from slc.scene.camera import CameraPath
from slc.scene.scenes import SHARED_DIR

HALF, WALL_H = 10.0, 4.5
ARCADE_D, ARCADE_H = 3.0, 3.6            # arcade depth and ceiling height
ENVMAP = SHARED_DIR / "envmaps" / "venice_sunset_1k.hdr"
ENV_SCALE = 0.6
ENV_CONSTANT = (0.08, 0.10, 0.16)
LAMP_RADIUS = 0.12
LAMP_RADIANCE = (320.0, 250.0, 160.0)
LANTERN_RADIANCE = (90.0, 60.0, 30.0)


def _leaves(rng, center, radii, n, size=(0.09, 0.05)):
    """``n`` leaf quads with centres in an ellipsoid, random orientations."""
    c = np.asarray(center, float)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.0, 1.0, size=(n, 1)) ** (1 / 3)
    # denser at the canopy surface
    r = 0.55 + 0.45 * r
    P = c + d * r * np.asarray(radii, float)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(u, rng.normal(size=(n, 3)))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    s = rng.uniform(0.7, 1.3, size=(n, 1))
    a, b = u * size[0] * s, w * size[1] * s
    V = np.stack([P - a - b, P + a - b, P + a + b, P - a + b], axis=1).reshape(-1, 3)
    base = 4 * np.arange(n)[:, None]
    F = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0)
    return V, F


def _concat(meshes):
    Vs, Fs, off = [], [], 0
    for V, F in meshes:
        Vs.append(V)
        Fs.append(F + off)
        off += len(V)
    return np.concatenate(Vs), np.concatenate(Fs)


# the options a scene name may carry (``garden:exposure=...``); scenes.load refuses others
OPTIONS = ('exposure',)


def build(**options):
    b = SceneBuilder("garden")
    rng = np.random.default_rng(1234)
    plaster = diffuse([0.78, 0.70, 0.58])
    stone = diffuse([0.60, 0.57, 0.52])
    tiles = principled([0.55, 0.32, 0.22], roughness=0.25, specular=0.5)
    bark = diffuse([0.28, 0.20, 0.13])
    leaf_a = {"type": "twosided", "bsdf": diffuse([0.13, 0.32, 0.08])}
    leaf_b = {"type": "twosided", "bsdf": diffuse([0.22, 0.40, 0.10])}
    tabletop = principled([0.85, 0.85, 0.82], roughness=0.08, specular=0.7)
    iron = rough_conductor(0.2, rgb=[0.35, 0.35, 0.35])
    dark = diffuse([0.0, 0.0, 0.0])

    # floor: glossy terracotta tiles in the courtyard, stone under the arcade
    b.add_quad([0, 0, 0], [HALF, 0, 0], [0, 0, -HALF], bsdf=tiles, name="floor")
    # walls (outer) and arcade: pillars, lintels, roof slab
    walls = [box_mesh([-HALF - 0.4, 0, -HALF - 0.4], [HALF + 0.4, WALL_H, -HALF]),
             box_mesh([-HALF - 0.4, 0, HALF], [HALF + 0.4, WALL_H, HALF + 0.4]),
             box_mesh([-HALF - 0.4, 0, -HALF], [-HALF, WALL_H, HALF]),
             box_mesh([HALF, 0, -HALF], [HALF + 0.4, WALL_H, HALF])]
    b.add_trimesh(merge_meshes(walls), bsdf=plaster, name="walls")
    pillars, arcade = [], []
    edge = -HALF + ARCADE_D
    for x in np.linspace(edge, HALF - 1.0, 6):           # north arcade along x
        pillars.append(box_mesh([x - 0.22, 0, edge - 0.22], [x + 0.22, ARCADE_H, edge + 0.22]))
    for z in np.linspace(edge + 3.0, HALF - 1.0, 4):     # west arcade along z
        pillars.append(box_mesh([edge - 0.22, 0, z - 0.22], [edge + 0.22, ARCADE_H, z + 0.22]))
    arcade.append(box_mesh([edge - 0.3, ARCADE_H, -HALF], [HALF, ARCADE_H + 0.5, edge + 0.3]))
    arcade.append(box_mesh([-HALF, ARCADE_H, edge + 0.3], [edge + 0.3, ARCADE_H + 0.5, HALF]))
    b.add_trimesh(merge_meshes(pillars), bsdf=stone, name="pillars")
    b.add_trimesh(merge_meshes(arcade), bsdf=plaster, name="arcade_roof")
    # a low stone planter ring and a fountain in the middle
    fountain = trimesh.creation.annulus(r_min=1.3, r_max=1.6, height=0.5, sections=32)
    fountain.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    fountain.apply_translation([2.0, 0.25, 2.0])
    b.add_trimesh(merge_meshes([fountain, trimesh.creation.cylinder(radius=0.2, segment=[[2, 0, 2], [2, 1.3, 2]],
                                                              sections=16)]), bsdf=stone, name="fountain")

    # trees and bushes: trunks + thousands of leaves
    trees = [(5.5, -4.0, 3.2), (-3.0, 6.0, 3.6), (6.5, 6.5, 2.8), (-1.0, -1.5, 3.0)]
    trunks, leaves_a, leaves_b = [], [], []
    for (x, z, h) in trees:
        trunks.append(trimesh.creation.cylinder(radius=0.14, segment=[[x, 0, z], [x, h, z]], sections=10))
        for k in range(3):  # a few branches
            ang = rng.uniform(0, 2 * np.pi)
            tip = [x + 0.9 * np.cos(ang), h - 0.2 + 0.4 * k, z + 0.9 * np.sin(ang)]
            trunks.append(trimesh.creation.cylinder(radius=0.05, segment=[[x, h - 0.8, z], tip], sections=6))
        leaves_a.append(_leaves(rng, [x, h + 0.4, z], [1.5, 1.0, 1.5], 900))
    bushes = [(8.5, -8.0), (3.0, -8.5), (8.8, 0.5), (8.5, 8.5), (3.5, 8.8), (-8.5, 8.5), (-8.0, -1.0), (-4.0, -8.3)]
    for (x, z) in bushes:
        leaves_b.append(_leaves(rng, [x, 0.55, z], [0.8, 0.55, 0.8], 260, size=(0.07, 0.04)))
    b.add_trimesh(merge_meshes(trunks), bsdf=bark, name="trunks")
    b.add_mesh(*_concat(leaves_a), bsdf=leaf_a, name="leaves_trees")
    b.add_mesh(*_concat(leaves_b), bsdf=leaf_b, name="leaves_bushes")

    # café tables: iron legs, glossy tops
    legs, tops = [], []
    for (x, z) in [(-4.0, -5.5), (-1.0, -6.0), (2.5, -5.5), (-6.0, 1.0), (-6.0, 4.0)]:
        legs.append(trimesh.creation.cylinder(radius=0.04, segment=[[x, 0, z], [x, 0.72, z]], sections=8))
        tops.append(trimesh.creation.cylinder(radius=0.4, segment=[[x, 0.72, z], [x, 0.76, z]], sections=20))
    b.add_trimesh(merge_meshes(legs), bsdf=iron, name="table_legs")
    b.add_trimesh(merge_meshes(tops), bsdf=tabletop, name="table_tops")

    # lamps: spheres hanging in the arcade and on posts, two lanterns
    posts = []
    for i, x in enumerate((-5.0, 0.0, 5.0)):
        c = [x, ARCADE_H - 0.6, -HALF + ARCADE_D / 2]
        b.add_sphere(c, LAMP_RADIUS, subdivisions=2, bsdf=dark, emission=LAMP_RADIANCE, name=f"arcade_lamp{i}")
        posts.append(trimesh.creation.cylinder(radius=0.01, segment=[[c[0], c[1] + LAMP_RADIUS, c[2]],
                                                                       [c[0], ARCADE_H, c[2]]], sections=4))
    for i, (x, z) in enumerate([(-HALF + ARCADE_D / 2, 3.0), (4.5, 4.0)]):
        c = [x, 2.6 if i == 0 else 2.2, z]
        b.add_sphere(c, LAMP_RADIUS, subdivisions=2, bsdf=dark, emission=LAMP_RADIANCE, name=f"post_lamp{i}")
        if i == 1:
            posts.append(trimesh.creation.cylinder(radius=0.05, segment=[[x, 0, z], [x, c[1] - LAMP_RADIUS, z]],
                                                   sections=8))
        else:
            posts.append(trimesh.creation.cylinder(radius=0.01, segment=[[x, c[1] + LAMP_RADIUS, z],
                                                                           [x, ARCADE_H, z]], sections=4))
    b.add_trimesh(merge_meshes(posts), bsdf=iron, name="lamp_posts")
    for i, (x, z) in enumerate([(9.4, -3.0), (-2.0, 9.4)]):
        b.add_box([x - 0.15, 1.8, z - 0.15], [x + 0.15, 2.2, z + 0.15], bsdf=dark, emission=LANTERN_RADIANCE,
                  name=f"lantern{i}")

    if ENVMAP.exists():
        b.add_envmap(ENVMAP, scale=ENV_SCALE)
    else:
        b.add_envmap(rgb=ENV_CONSTANT)

    paths = [
        CameraPath([([-7.5, 1.7, -8.5], [4.0, 1.5, 2.0]), ([-3.0, 1.7, -8.8], [6.0, 2.0, -3.0]),
                    ([2.0, 1.6, -8.5], [-3.0, 2.0, 6.0]), ([7.0, 1.8, -8.6], [0.0, 1.0, 0.0])],
                   fov=60, name="arcade_walk"),
        CameraPath([([0.0, 1.6, 6.5], [6.0, 3.0, -4.0]), ([-5.0, 1.7, 3.0], [5.5, 3.0, -4.0]),
                    ([-4.5, 1.7, -2.5], [6.5, 2.0, 6.5]), ([1.0, 1.6, -3.5], [-3.0, 2.5, 6.0])],
                   fov=60, name="courtyard"),
        CameraPath([([8.5, 6.0, 8.5], [-2.0, 0.5, -2.0]), ([0.0, 7.0, 9.0], [0.0, 0.5, -4.0]),
                    ([-8.0, 6.5, 8.0], [3.0, 1.0, -3.0]), ([-8.0, 6.0, -1.0], [6.0, 1.0, 0.0])],
                   fov=55, name="above"),
        CameraPath([([4.0, 0.9, -2.0], [5.5, 3.5, -4.0]), ([3.5, 1.0, 0.0], [-1.0, 3.0, -1.5]),
                    ([5.0, 1.1, 2.0], [8.5, 0.5, 8.5]), ([6.0, 1.2, -0.5], [8.5, 0.5, -8.0])],
                   fov=70, name="foliage"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 1.0)), unit=1.0,
                   meeting_center=[2.0, 1.2, 2.0], description=__doc__.strip().splitlines()[0])
