"""two_rooms: two closed 2 m x 2.4 m x 3 m rooms side by side behind a 10 cm wall; room A has a ceiling light, room B none (all its light would be a leak); a light-leaking check for GI caches.

Layout (metres, y up): room A spans x in [-1.9, 0.1], room B x in [0.2, 2.2], both y in [0, 2.4],
z in [-1.5, 1.5]; the wall between them is the box x in [0.1, 0.2]. The wall is deliberately
off the 10 cm / 30 cm grid lines: a 30 cm world cell [0, 0.3) straddles it. Every room has its
own floor, ceiling and walls (quads facing into the room) unless ``shared_floor=1``: then one
floor quad runs under both rooms (the hard case for caches keyed by surface: the floor on both
sides of the wall is one shape). A rough-metal block stands in room A. Path 0 ("lit") walks
around room A looking at the wall, path 1 ("dark") around room B, path 2 ("lit_floor") around
room A looking at its floor.

Unit: one scene unit is one metre (``unit=1.0``).
"""
from slc.scene.builder import SceneBuilder, diffuse, rough_conductor
from slc.scene.camera import CameraPath

ROOM_A = (-1.9, 0.1)
ROOM_B = (0.2, 2.2)
HEIGHT, HALF_Z = 2.4, 1.5
LIGHT_RADIANCE = (15.0, 14.0, 12.0)


def _room(b, x0, x1, white, wall, shared_floor):
    cx, hx = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    if not shared_floor:
        b.add_quad([cx, 0, 0], [hx, 0, 0], [0, 0, -HALF_Z], bsdf=white, name="floor")
    b.add_quad([cx, HEIGHT, 0], [hx, 0, 0], [0, 0, HALF_Z], bsdf=white, name="ceiling")
    b.add_quad([cx, HEIGHT / 2, -HALF_Z], [hx, 0, 0], [0, HEIGHT / 2, 0], bsdf=wall, name="back")
    b.add_quad([cx, HEIGHT / 2, HALF_Z], [0, HEIGHT / 2, 0], [hx, 0, 0], bsdf=wall, name="front")
    b.add_quad([x0, HEIGHT / 2, 0], [0, HEIGHT / 2, 0], [0, 0, HALF_Z], bsdf=white, name="left")
    b.add_quad([x1, HEIGHT / 2, 0], [0, 0, HALF_Z], [0, HEIGHT / 2, 0], bsdf=white, name="right")


# the options a scene name may carry (``two_rooms:shared_floor=...``); scenes.load refuses others
OPTIONS = ('shared_floor',)


def build(**options):
    shared = str(options.get("shared_floor", "0")).lower() in ("1", "true", "yes")
    b = SceneBuilder("two_rooms" + ("_shared_floor" if shared else ""))
    white, warm = diffuse([0.7, 0.7, 0.7]), diffuse([0.7, 0.5, 0.3])
    _room(b, *ROOM_A, white, warm, shared)
    _room(b, *ROOM_B, white, warm, shared)
    if shared:
        b.add_quad([0.15, 0, 0], [2.05, 0, 0], [0, 0, -HALF_Z], bsdf=white, name="floor")
    b.add_box([ROOM_A[1], 0.0, -HALF_Z], [ROOM_B[0], HEIGHT, HALF_Z], bsdf=white, name="wall")
    b.add_quad([-0.9, HEIGHT - 0.02, 0], [0.3, 0, 0], [0, 0, 0.3], bsdf=diffuse([0, 0, 0]),
               emission=LIGHT_RADIANCE, name="light")
    b.add_box([-1.4, 0.0, -1.2], [-1.0, 0.8, -0.8], bsdf=rough_conductor(0.2, "Al"), name="metal_block")
    # walks of 7 m around each room (5 s at walking speed), looking at the wall between the rooms
    loop_a = [[-1.6, 1.3, 1.2], [-0.3, 1.2, 1.2], [-0.3, 1.4, -1.0], [-1.6, 1.2, -1.0], [-1.6, 1.3, 1.2]]
    loop_b = [[2.0 - (x + 1.9), y, z] for x, y, z in loop_a]
    paths = [
        CameraPath([(o, [0.1, 0.7, 0.0]) for o in loop_a], fov=70, name="lit"),
        CameraPath([(o, [0.2, 0.7, 0.0]) for o in loop_b], fov=70, name="dark"),
        CameraPath([(o, [-0.9, 0.0, 0.0]) for o in loop_a], fov=70, name="lit_floor"),
    ]
    return b.build(paths, exposure=1.0, unit=1.0, meeting_center=[0.15, 1.2, 0.0], description=__doc__.strip())
