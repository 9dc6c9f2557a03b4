"""atrium: Sponza-like court (24 m x 16 m) with two floors of colonnades, three small round lamps in the lower hallways and one large light at the top centre; static.

Layout (metres, y up): outer walls enclose x in [-12, 12], z in [-8, 8] up to
y = 14. The open court is x in [-8.4, 8.4], z in [-3.6, 3.6]; around it run
the lower hallways (floor y = 0, slab above at y = 5.0-5.4) and the upper
galleries (slab above at y = 10.0-10.4), both open to the court through
colonnades of round columns with lintels/arches. The top light is a 8 m x 4 m
quad at y = 13.6 facing down; the three lamps are emissive icospheres
(radius 0.15 m) hanging in the hallways.

Unit: one scene unit is one metre (``unit=1.0``); the camera paths walk at
1.4 m/s with view turns up to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import numpy as np
import trimesh

from slc.scene.builder import SceneBuilder, box_mesh, diffuse, merge_meshes, principled, rough_conductor
from slc.scene.camera import CameraPath

W_X, W_Z, H = 12.0, 8.0, 14.0          # outer half extents and wall height
C_X, C_Z = 8.4, 3.6                    # court half extents (column line)
FLOORS = [(0.0, 5.0), (5.4, 10.0)]     # (floor level, ceiling level) of the two storeys
SLAB = 0.4
LAMP_RADIUS = 0.15
LAMP_RADIANCE = (400.0, 300.0, 180.0)
LAMPS = [(-6.0, 2.6, 5.8), (2.0, 2.6, -5.8), (10.0, 2.6, 2.0)]
TOP_Y, TOP_HALF = 13.6, (4.0, 2.0)
TOP_RADIANCE = (10.0, 9.5, 9.0)


def _cyl(x, z, y0, y1, r, sections=16):
    return trimesh.creation.cylinder(radius=r, segment=np.array([[x, y0, z], [x, y1, z]]), sections=sections)


def _column_positions():
    """Column centres on the rectangle |x| = C_X, |z| = C_Z (4.2 m spacing along x, 3.6 m along z)."""
    pts = set()
    for x in np.linspace(-C_X, C_X, 5):
        pts.add((round(float(x), 3), C_Z))
        pts.add((round(float(x), 3), -C_Z))
    for z in np.linspace(-C_Z, C_Z, 3):
        pts.add((C_X, round(float(z), 3)))
        pts.add((-C_X, round(float(z), 3)))
    return sorted(pts)


def _arches(y_spring, y_top, depth=0.5, r=0.32):
    """Box 'arches' between neighbouring columns: a lintel with stepped haunches."""
    parts = []
    cols = _column_positions()
    for (x0, z0) in cols:
        for (x1, z1) in cols:
            if (x1, z1) <= (x0, z0):
                continue
            if not ((abs(z0 - z1) < 1e-6 and abs(abs(z0) - C_Z) < 1e-6 and abs(abs(x1 - x0) - 4.2) < 1e-3) or
                    (abs(x0 - x1) < 1e-6 and abs(abs(x0) - C_X) < 1e-6 and abs(abs(z1 - z0) - 3.6) < 1e-3)):
                continue
            a, b = np.array([x0, z0]), np.array([x1, z1])
            along = (b - a) / np.linalg.norm(b - a)
            perp = np.array([-along[1], along[0]]) * depth / 2
            span = np.linalg.norm(b - a)
            # lintel over the whole span plus two haunch steps near each column
            for (s0, s1, h0) in [(0.0, span, y_top - 0.5), (0.0, 0.7, y_spring + 0.4), (span - 0.7, span, y_spring + 0.4),
                                 (0.0, 0.35, y_spring), (span - 0.35, span, y_spring)]:
                p0, p1 = a + along * s0, a + along * s1
                lo = np.minimum(p0, p1) - np.abs(perp)
                hi = np.maximum(p0, p1) + np.abs(perp)
                parts.append(box_mesh([lo[0], h0, lo[1]], [hi[0], y_top, hi[1]]))
    return parts


def _ring_slab(y0, y1, inner_x, inner_z):
    """A slab covering the outer rectangle minus the court opening."""
    return [
        box_mesh([-W_X, y0, inner_z], [W_X, y1, W_Z]),
        box_mesh([-W_X, y0, -W_Z], [W_X, y1, -inner_z]),
        box_mesh([-W_X, y0, -inner_z], [-inner_x, y1, inner_z]),
        box_mesh([inner_x, y0, -inner_z], [W_X, y1, inner_z]),
    ]


# the options a scene name may carry (``atrium:exposure=...``); scenes.load refuses others
OPTIONS = ('exposure',)


def build(**options):
    b = SceneBuilder("atrium")
    stone = diffuse([0.62, 0.56, 0.47])
    wall = diffuse([0.70, 0.64, 0.55])
    slab = diffuse([0.55, 0.52, 0.48])
    marble = principled([0.80, 0.78, 0.74], roughness=0.15, specular=0.6)
    floor_glossy = principled([0.45, 0.36, 0.28], roughness=0.22, specular=0.5)
    bronze = rough_conductor(0.12, "Cu")
    dark = diffuse([0.0, 0.0, 0.0])

    # floor: a glossy court paving and diffuse hallway floors
    b.add_quad([0, 0, 0], [C_X, 0, 0], [0, 0, -C_Z], bsdf=floor_glossy, name="court_floor")
    b.add_trimesh(merge_meshes(_ring_slab(-0.2, 0.0, C_X, C_Z)), bsdf=stone, name="hall_floor")
    # outer walls (inner faces visible) with a few pilasters
    walls = [box_mesh([-W_X - 0.5, 0, -W_Z - 0.5], [W_X + 0.5, H, -W_Z]),
             box_mesh([-W_X - 0.5, 0, W_Z], [W_X + 0.5, H, W_Z + 0.5]),
             box_mesh([-W_X - 0.5, 0, -W_Z], [-W_X, H, W_Z]),
             box_mesh([W_X, 0, -W_Z], [W_X + 0.5, H, W_Z])]
    for x in np.linspace(-C_X, C_X, 5):
        for s in (-1, 1):
            walls.append(box_mesh([x - 0.4, 0, s * W_Z - (0.3 if s > 0 else 0.0)],
                              [x + 0.4, FLOORS[1][1], s * W_Z + (0.3 if s < 0 else 0.0)]))
    b.add_trimesh(merge_meshes(walls), bsdf=wall, name="walls")
    # slabs between storeys, parapets on the gallery and the roof cornice
    slabs = _ring_slab(FLOORS[0][1], FLOORS[1][0], C_X - 0.3, C_Z - 0.3)
    slabs += _ring_slab(FLOORS[1][1], FLOORS[1][1] + SLAB, C_X - 0.3, C_Z - 0.3)
    b.add_trimesh(merge_meshes(slabs), bsdf=slab, name="slabs")
    parapet = []
    for s in (-1, 1):
        parapet.append(box_mesh([-C_X, FLOORS[1][0], s * C_Z - 0.12], [C_X, FLOORS[1][0] + 1.0, s * C_Z + 0.12]))
        parapet.append(box_mesh([s * C_X - 0.12, FLOORS[1][0], -C_Z], [s * C_X + 0.12, FLOORS[1][0] + 1.0, C_Z]))
    b.add_trimesh(merge_meshes(parapet), bsdf=marble, name="parapet")
    # railing on top of the parapet: glossy metal
    rail = []
    for s in (-1, 1):
        rail.append(box_mesh([-C_X, FLOORS[1][0] + 1.0, s * C_Z - 0.06], [C_X, FLOORS[1][0] + 1.1, s * C_Z + 0.06]))
        rail.append(box_mesh([s * C_X - 0.06, FLOORS[1][0] + 1.0, -C_Z], [s * C_X + 0.06, FLOORS[1][0] + 1.1, C_Z]))
    b.add_trimesh(merge_meshes(rail), bsdf=bronze, name="rail")

    # colonnades: lower columns (glossy marble), upper columns (diffuse stone), with bases and capitals
    lower, upper, caps = [], [], []
    for (x, z) in _column_positions():
        lower.append(_cyl(x, z, 0.3, 3.7, 0.32, sections=20))
        caps += [box_mesh([x - 0.45, 0.0, z - 0.45], [x + 0.45, 0.3, z + 0.45]),
                 box_mesh([x - 0.45, 3.7, z - 0.45], [x + 0.45, 3.95, z + 0.45])]
        upper.append(_cyl(x, z, FLOORS[1][0], 8.8, 0.24, sections=16))
        caps.append(box_mesh([x - 0.35, 8.8, z - 0.35], [x + 0.35, 9.0, z + 0.35]))
    b.add_trimesh(merge_meshes(lower), bsdf=marble, name="columns_lower")
    b.add_trimesh(merge_meshes(upper), bsdf=stone, name="columns_upper")
    b.add_trimesh(merge_meshes(caps), bsdf=stone, name="capitals")
    b.add_trimesh(merge_meshes(_arches(3.95, FLOORS[0][1]) + _arches(9.0, FLOORS[1][1])), bsdf=wall, name="arches")
    # a bronze fountain basin in the middle of the court
    basin = trimesh.creation.annulus(r_min=1.1, r_max=1.4, height=0.6, sections=32)
    basin.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    basin.apply_translation([0, 0.3, 0])
    b.add_trimesh(basin, bsdf=bronze, name="basin")
    b.add_trimesh(_cyl(0, 0, 0.0, 1.6, 0.25, sections=24), bsdf=marble, name="fountain")

    # lights
    for i, c in enumerate(LAMPS):
        b.add_sphere(c, LAMP_RADIUS, subdivisions=2, bsdf=dark, emission=LAMP_RADIANCE, name=f"lamp{i}")
        b.add_cylinder([c[0], c[1] + LAMP_RADIUS, c[2]], [c[0], FLOORS[0][1], c[2]], 0.015, sections=6,
                       bsdf=bronze, name=f"chain{i}")
    hx, hz = TOP_HALF
    # cross(u, v) = cross(x, z) = -y: the top light faces down into the court
    b.add_quad([0, TOP_Y, 0], [hx, 0, 0], [0, 0, hz], bsdf=dark, emission=TOP_RADIANCE, name="top_light")

    paths = [
        CameraPath([([-7.0, 1.7, 0.5], [3.0, 3.0, -2.0]), ([-3.0, 1.8, -2.0], [4.0, 4.0, 3.5]),
                    ([2.0, 1.9, -2.2], [6.0, 2.0, 5.8]), ([6.0, 1.8, 0.0], [-4.0, 7.0, 0.0]),
                    ([4.0, 2.2, 2.5], [-8.0, 3.0, 0.0])], fov=60, name="court"),
        CameraPath([([-10.5, 1.7, 6.2], [-2.0, 2.2, 5.0]), ([-7.0, 1.7, 5.5], [2.0, 2.0, 4.0]),
                    ([-2.0, 1.8, 6.0], [6.0, 2.0, 3.0]), ([3.0, 1.6, 5.6], [10.0, 2.5, 2.0]),
                    ([8.0, 1.7, 6.0], [9.5, 2.0, -4.0])], fov=65, name="hallway"),
        CameraPath([([10.0, 7.2, -4.6], [0.0, 4.0, 3.6]), ([5.0, 7.3, -4.4], [-4.0, 1.0, 1.0]),
                    ([0.0, 7.1, -4.6], [-6.0, 7.0, 5.0]), ([-5.0, 7.3, -4.5], [2.0, 7.5, 4.5]),
                    ([-10.0, 7.2, -5.0], [0.0, 3.0, 3.0])], fov=60, name="gallery"),
        CameraPath([([0.0, 12.0, 2.5], [0.0, 0.0, 0.0]), ([-5.0, 9.0, 2.0], [2.0, 1.0, -5.5]),
                    ([-6.5, 4.0, 0.0], [4.0, 2.0, 5.5]), ([-2.0, 1.2, 2.0], [6.0, 3.0, -5.0])],
                   fov=55, name="descent"),
    ]
    return b.build(paths, exposure=float(options.get("exposure", 1.5)), unit=1.0,
                   meeting_center=[0.0, 1.6, 0.0], description=__doc__.strip().splitlines()[0])
