"""village: Viking-village-like night scene on rolling terrain: huts with pitched roofs, a large moon-like light high in the sky and small torches on poles; static (option sun=1: by day, lit by one sun alone).

Layout (metres, y up): a 64 x 64 grid of terrain over x, z in [-30, 30]
(smooth height field, a shallow bowl with low hills at the rim, the village
square near the origin is almost flat); seven huts (log walls as boxes, gabled
roofs as prisms, one glossy-roofed longhouse); a palisade and a few barrels.
The moon is an emissive icosphere of radius 10 m about 120 m away, 35 degrees
above the horizon; the torches are emissive spheres of radius 0.08 m on
2.2 m poles. ``village:sun=1`` lights the same village by day, by one sun
alone (the CRC paper's outdoor scenes): a directional light from the moon's
direction (35 degrees above the horizon), warm white, irradiance
``SUN_IRRADIANCE`` on a surface facing it; no moon, no torch lights (their
poles stay), no sky, so shadows hold indirect light only; exposure 1.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import math

import numpy as np
import trimesh

from slc.scene.builder import SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor
from slc.scene.camera import CameraPath

EXTENT, GRID = 30.0, 64
MOON_DIR = np.array([-0.55, 0.57, -0.61])
MOON_DIST, MOON_RADIUS = 120.0, 10.0
MOON_RADIANCE = (90.0, 100.0, 125.0)
TORCH_RADIUS = 0.08
TORCH_RADIANCE = (700.0, 380.0, 120.0)
SUN_IRRADIANCE = (7.0, 6.5, 5.7)       # W/m^2 (option sun=1)


def height(x, z):
    """Smooth terrain height: flat-ish centre, a bowl rim and gentle waves."""
    r = np.sqrt(x * x + z * z)
    rim = 3.5 * (1.0 / (1.0 + np.exp(-(r - 20.0) / 3.0)))
    waves = 0.45 * np.sin(0.21 * x + 0.7) * np.cos(0.17 * z - 0.4) + 0.25 * np.sin(0.37 * z + 0.33 * x)
    return rim + waves * np.clip(r / 8.0, 0.0, 1.0)


def _terrain():
    xs = np.linspace(-EXTENT, EXTENT, GRID + 1)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X, height(X, Z), Z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(GRID), np.arange(GRID), indexing="ij")
    a = (i * (GRID + 1) + j).ravel()
    b_, c, d = a + (GRID + 1), a + (GRID + 2), a + 1
    # (x, z) grid with +x along i and +z along j: the winding a, d, c gives +y normals
    F = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b_], 1)])
    return V, F


def _place(tm, x, z, yaw_deg, y):
    M = trimesh.transformations.rotation_matrix(math.radians(yaw_deg), [0, 1, 0])
    M[:3, 3] = [x, y, z]
    tm.apply_transform(M)
    return tm


def _hut_walls(L, W, H):
    return box_mesh([-L / 2, -0.5, -W / 2], [L / 2, H, W / 2])


def _hut_roof(L, W, H, ridge, overhang=0.5):
    """Gabled roof: a triangular prism along x (closed mesh)."""
    hl, hw = L / 2 + overhang, W / 2 + overhang
    y0, y1 = H - 0.15, H + ridge
    V = np.array([[-hl, y0, -hw], [-hl, y0, hw], [-hl, y1, 0.0],
                  [hl, y0, -hw], [hl, y0, hw], [hl, y1, 0.0]])
    F = np.array([[0, 2, 1], [3, 4, 5],               # gables
                  [0, 3, 5], [0, 5, 2],               # -z slope
                  [1, 2, 5], [1, 5, 4],               # +z slope
                  [0, 1, 4], [0, 4, 3]])              # underside
    tm = trimesh.Trimesh(V, F, process=False)
    tm.fix_normals()
    return tm


HUTS = [  # x, z, yaw, length, width, wall height, ridge
    (-10.0, -6.0, 20.0, 7.0, 4.5, 2.3, 2.3),
    (8.0, -9.0, -15.0, 6.0, 4.5, 2.2, 2.0),
    (12.0, 3.0, 80.0, 6.5, 4.5, 2.3, 2.2),
    (-1.0, 12.0, 5.0, 11.0, 5.5, 2.8, 3.0),   # longhouse (glossy slate roof)
    (-12.0, 7.0, 60.0, 5.5, 4.0, 2.0, 1.9),
    (-2.0, -14.0, -5.0, 6.5, 4.5, 2.3, 2.3),
    (10.0, 10.5, 40.0, 5.0, 4.0, 2.1, 2.0),
]
TORCHES = [(-3.0, -2.0), (3.0, 1.0), (-4.0, 4.0), (4.0, -4.0), (1.0, 7.0), (-7.0, 0.0), (7.0, -1.0)]


# the options a scene name may carry (``village:sun=...``); scenes.load refuses others
OPTIONS = ('sun', 'exposure')


def build(**options):
    sun = str(options.get("sun", "0")).lower()
    if sun not in ("0", "1", "false", "true", "no", "yes"):
        raise ValueError(f"sun must be 0 or 1, got '{sun}'")
    sun = sun in ("1", "true", "yes")
    b = SceneBuilder("village_sun" if sun else "village")
    grass = diffuse([0.22, 0.28, 0.14])
    wood = diffuse([0.40, 0.27, 0.16])
    thatch = principled([0.35, 0.30, 0.22], roughness=0.3, specular=0.4)
    slate = principled([0.25, 0.27, 0.30], roughness=0.12, specular=0.7)
    iron = rough_conductor(0.2, rgb=[0.53, 0.51, 0.49])
    dark = diffuse([0.0, 0.0, 0.0])

    V, F = _terrain()
    b.add_mesh(V, F, bsdf=grass, name="terrain", smooth=True)

    walls, roofs, glossy_roof = [], [], []
    for k, (x, z, yaw, L, W, H, ridge) in enumerate(HUTS):
        y = float(height(np.array(x), np.array(z)))
        walls.append(_place(_hut_walls(L, W, H), x, z, yaw, y))
        # a door frame (dark inset) on the front
        walls.append(_place(box_mesh([-0.6, -0.2, W / 2], [0.6, 1.9, W / 2 + 0.08]), x, z, yaw, y))
        roof = _place(_hut_roof(L, W, H, ridge), x, z, yaw, y)
        (glossy_roof if k == 3 else roofs).append(roof)
    b.add_trimesh(merge_meshes(walls), bsdf=wood, name="hut_walls")
    b.add_trimesh(merge_meshes(roofs), bsdf=thatch, name="hut_roofs")
    b.add_trimesh(merge_meshes(glossy_roof), bsdf=slate, name="longhouse_roof")

    # palisade: posts on an arc around the village
    posts = []
    for a in np.linspace(math.radians(100), math.radians(350), 60):
        x, z = 18.0 * math.cos(a), 18.0 * math.sin(a)
        y = float(height(np.array(x), np.array(z)))
        posts.append(trimesh.creation.cylinder(radius=0.18, segment=[[x, y - 0.5, z], [x, y + 3.0, z]], sections=6))
    b.add_trimesh(merge_meshes(posts), bsdf=wood, name="palisade")

    # barrels with iron hoops (glossy) near the huts
    barrels, hoops = [], []
    for (x, z) in [(-3.5, -1.5), (-3.0, -2.3), (5.0, 2.5), (1.0, 6.0)]:
        y = float(height(np.array(x), np.array(z)))
        barrels.append(trimesh.creation.cylinder(radius=0.35, segment=[[x, y, z], [x, y + 0.9, z]], sections=14))
        for hy in (0.15, 0.75):
            hoops.append(trimesh.creation.cylinder(radius=0.37, segment=[[x, y + hy, z], [x, y + hy + 0.06, z]],
                                                   sections=14))
    b.add_trimesh(merge_meshes(barrels), bsdf=wood, name="barrels")
    b.add_trimesh(merge_meshes(hoops), bsdf=iron, name="hoops")

    # torches: poles (diffuse wood) with tiny emissive spheres on top
    poles = []
    for i, (x, z) in enumerate(TORCHES):
        y = float(height(np.array(x), np.array(z)))
        poles.append(trimesh.creation.cylinder(radius=0.04, segment=[[x, y - 0.3, z], [x, y + 2.1, z]], sections=6))
        poles.append(trimesh.creation.cylinder(radius=0.07, segment=[[x, y + 2.0, z], [x, y + 2.12, z]],
                                               sections=8))
        if not sun:
            b.add_sphere([x, y + 2.2, z], TORCH_RADIUS, subdivisions=1, bsdf=dark, emission=TORCH_RADIANCE,
                         name=f"torch{i}")
    b.add_trimesh(merge_meshes(poles), bsdf=iron, name="torch_poles")

    # the moon: far, large, high in the sky (lights the whole village from one side); or the sun from there
    d = MOON_DIR / np.linalg.norm(MOON_DIR)
    if sun:
        b.add_directional_light(-d, SUN_IRRADIANCE, name="sun")
    else:
        b.add_sphere(d * MOON_DIST, MOON_RADIUS, subdivisions=3, bsdf=dark, emission=MOON_RADIANCE, name="moon")

    paths = [
        CameraPath([([-3.0, 1.8, -5.0], [10.0, 2.0, 6.0]), ([2.0, 1.8, -5.0], [0.0, 2.5, 12.0]),
                    ([5.0, 1.8, 0.0], [-10.0, 2.0, 5.0]), ([2.0, 1.8, 5.0], [-8.0, 2.0, -6.0]),
                    ([-4.0, 1.8, 2.0], [8.0, 1.5, -9.0])], fov=60, name="square"),
        CameraPath([([-18.8, 9.0, -6.8], [0.0, 1.0, 0.0]), ([-14.0, 9.0, -14.0], [2.0, 1.0, 2.0]),
                    ([-6.0, 8.5, -18.5], [3.0, 1.0, 4.0]), ([3.0, 8.0, -19.5], [-1.0, 1.0, 6.0])],
                   fov=55, name="crane"),
        CameraPath([([-15.0, 3.2, 0.0], [0.0, 2.0, 2.0]), ([-9.0, 2.2, 1.0], [4.0, 2.0, -4.0]),
                    ([-3.0, 1.8, 6.5], [8.0, 2.0, 9.0]), ([4.0, 1.8, 6.0], [12.0, 2.5, 3.0]),
                    ([7.0, 1.9, 0.0], [8.0, 2.0, -9.0])], fov=65, name="lanes"),
        CameraPath([([6.0, 2.6, 6.0], [-20.0, 14.0, -20.0]), ([4.0, 2.5, 5.0], [-8.0, 1.0, -4.0]),
                    ([0.0, 2.4, 4.0], [-2.0, 1.0, -14.0])], fov=60, name="moonward"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 1.0 if sun else 3.0)), unit=1.0,
                   meeting_center=[0.0, 1.5, 0.0], description=__doc__.strip().splitlines()[0])
