"""skylit: an open courtyard lit only by an environment map (option env=venice|studio|spots|constant); static.

Layout (metres, y up): a 20 m x 20 m paved yard with low walls, an arcade of
pillars under a roofed walkway on one side, boxes and glossy spheres; no
roof over the yard, so every point sees part of the sky. The environment:

- ``venice`` (default) / ``studio``: the HDR maps in ``../shared/envmaps/``
  (a sunset with a strong sun; an interior studio with soft rectangular
  lights); a missing file is a one-line error naming it;
- ``spots``: a map made in code, hard for cones (the paper's Fig. 18): 48
  small bright discs (1.5-4 degrees, 200-800x the sky) scattered over a dim
  blue sky;
- ``constant``: a uniform sky (closed forms for tests).

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import math

import numpy as np

from slc.scene.builder import SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor
from slc.scene.camera import CameraPath
from slc.scene.checks import SceneError
from slc.scene.scenes import ENVMAPS_DIR

ENVMAPS = {"venice": "venice_sunset_1k.hdr", "studio": "studio_small_03_1k.hdr"}


def spots_map(width=512, height=256, n=48, seed=5) -> np.ndarray:
    """A dim sky with ``n`` small bright discs (lat-long, Mitsuba's envmap layout)."""
    rng = np.random.default_rng(seed)
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta, phi = np.meshgrid(v * math.pi, u * 2 * math.pi, indexing="ij")
    d = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    sky = np.where(d[..., 1:2] > 0, np.array([0.05, 0.08, 0.14]) * (0.4 + 0.6 * d[..., 1:2]),
                   np.array([0.02, 0.02, 0.02]))
    img = sky.astype(np.float64)
    for _ in range(n):
        ct = rng.uniform(0.05, 0.95)                     # upper hemisphere (y up)
        ph = rng.uniform(0, 2 * math.pi)
        st = math.sqrt(1 - ct * ct)
        c = np.array([st * math.cos(ph), ct, st * math.sin(ph)])
        r = math.radians(rng.uniform(1.5, 4.0))
        col = rng.uniform(0.6, 1.0, 3) * rng.uniform(200, 800) * 0.05
        img[(d @ c) > math.cos(r)] = col
    return img.astype(np.float32)


# the options a scene name may carry (``skylit:env=...``); scenes.load refuses others
OPTIONS = ('env', 'exposure')


def build(**options):
    env = str(options.get("env", "venice"))
    b = SceneBuilder("skylit")
    paving = principled([0.55, 0.5, 0.45], roughness=0.35, specular=0.5)
    plaster = diffuse([0.7, 0.66, 0.6])
    stone = diffuse([0.5, 0.48, 0.44])
    red = diffuse([0.6, 0.2, 0.15])
    chrome = rough_conductor(0.08, "Al")
    b.add_quad([0, 0, 0], [10, 0, 0], [0, 0, -10], bsdf=paving, name="yard")
    walls = [box_mesh([-10, 0, -10.3], [10, 1.2, -10]), box_mesh([-10, 0, 10], [10, 1.2, 10.3]),
             box_mesh([10, 0, -10], [10.3, 1.2, 10])]
    b.add_trimesh(merge_meshes(walls), bsdf=plaster, name="walls")
    # a roofed arcade along x = -10
    arcade = [box_mesh([-10.3, 0, -10], [-10, 4.5, 10]), box_mesh([-10.3, 4.2, -10], [-6.5, 4.5, 10])]
    arcade += [box_mesh([-7.0, 0, z - 0.3], [-6.4, 4.2, z + 0.3]) for z in np.linspace(-9, 9, 7)]
    b.add_trimesh(merge_meshes(arcade), bsdf=stone, name="arcade")
    boxes = [box_mesh([x - 0.6, 0, z - 0.6], [x + 0.6, h, z + 0.6])
             for x, z, h in ((-2, -4, 1.2), (3, -6, 2.0), (5, 3, 1.0), (-3, 5, 1.6), (0.5, 0.5, 0.8))]
    b.add_trimesh(merge_meshes(boxes), bsdf=red, name="boxes")
    for x, z in ((1.5, -2.0), (-4.0, 1.5), (6.0, -1.0)):
        b.add_sphere([x, 0.7, z], 0.7, subdivisions=3, bsdf=chrome, name="sphere")
    if env in ENVMAPS:
        path = ENVMAPS_DIR / ENVMAPS[env]
        if not path.exists():
            raise SceneError(f"environment map not found: {path} (skylit:env=spots or env=constant need no file)")
        b.add_envmap(path, scale=1.0)
    elif env == "spots":
        b.add_envmap(bitmap=spots_map())
    elif env == "constant":
        b.add_envmap(rgb=[0.8, 0.85, 1.0])
    else:
        raise ValueError(f"env must be one of venice, studio, spots, constant (got '{env}')")
    paths = [
        CameraPath([([8.0, 1.7, 8.0], [0.0, 0.8, 0.0]), ([2.0, 1.8, 8.5], [-4.0, 1.0, -2.0]),
                    ([-5.0, 1.7, 7.0], [2.0, 0.8, -6.0])], fov=60, name="stroll"),
        CameraPath([([-8.5, 2.0, -8.0], [2.0, 0.5, 2.0]), ([-8.5, 2.0, 0.0], [4.0, 0.5, -3.0]),
                    ([-8.5, 2.0, 8.0], [3.0, 0.8, 0.0])], fov=60, name="arcade"),
        CameraPath([([0.0, 8.0, 9.0], [0.0, 0.0, 0.0]), ([6.0, 7.5, 6.0], [-1.0, 0.0, -1.0])], fov=55,
                   name="above"),
    ]
    exposure = {"venice": 1.0, "studio": 0.5, "spots": 0.6, "constant": 1.0}[env]
    return b.build(paths, exposure=float(options.get("exposure", exposure)), unit=1.0,
                   meeting_center=[0.0, 1.0, 0.0], description=__doc__.strip().splitlines()[0])
