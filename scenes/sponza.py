"""sponza: the Sponza atrium (../shared/scenes/sponza) with the paper's lights: three small round lamps in the lower hallways and one large light at the top centre.

The geometry and textured materials come from ``sponza.xml`` (loaded with
``mi.load_file``; Mitsuba upgrades its old XML version on load and merges
meshes that share a material). The file's own light, one tiny analytic
sphere high above the atrium (not a triangle mesh), is dropped. Every mesh
is copied into a fresh ``mi.Mesh`` with a unique id (the merged meshes have
none) and the four lights are added as emissive triangle meshes, then the
scene is assembled with ``mi.load_dict``.

Coordinates (metres-ish, y up): the court spans x in [-11.7, 11.7] and
z in [-3.3, 3.3] between the colonnades; the lower hallways are the strips
|z| in [3.6, 7.2] under the first-floor slab (y ~ 6); the walls reach
y ~ 15.6 and the atrium is open to the sky.

Unit: one scene unit is taken as one metre (``unit=1.0``; the model's own
scale, give or take); the camera paths walk at 1.4 m/s with view turns up
to 30 deg/s at 60 Hz (``slc.scene.camera.CameraPath``).
"""
import numpy as np

from slc.scene.builder import diffuse
from slc.scene.camera import CameraPath
from slc.scene.checks import SceneError
from slc.scene.scenes import SHARED_DIR, Scene

SPONZA_XML = SHARED_DIR / "scenes" / "sponza" / "sponza.xml"

# three small round lamps (icospheres) in the lower hallways
LAMP_RADIUS = 0.2
LAMP_RADIANCE = (300.0, 230.0, 150.0)
LAMPS = [(-7.5, 2.2, 5.2), (1.0, 2.2, -5.2), (8.5, 2.2, 5.2)]
# one large light at the top centre, facing down
TOP_Y = 15.0
TOP_HALF = (4.0, 1.5)          # half extents along x and z
TOP_RADIANCE = (14.0, 13.0, 12.0)


def _copy_mesh(mi, src, sid):
    """A fresh mi.Mesh with id ``sid`` holding ``src``'s buffers and BSDF."""
    p = mi.traverse(src)
    V = np.array(p["vertex_positions"], np.float32)
    F = np.array(p["faces"], np.uint32)
    has_n = "vertex_normals" in p and len(p["vertex_normals"]) == len(V)
    has_uv = "vertex_texcoords" in p and len(p["vertex_texcoords"]) == 2 * (len(V) // 3)
    props = mi.Properties()
    props["bsdf"] = src.bsdf()
    m = mi.Mesh(sid, len(V) // 3, len(F) // 3, props, has_vertex_normals=has_n,
                has_vertex_texcoords=has_uv)
    q = mi.traverse(m)
    q["vertex_positions"] = mi.Float(V)
    q["faces"] = mi.UInt32(F)
    if has_n:
        q["vertex_normals"] = mi.Float(np.array(p["vertex_normals"], np.float32))
    if has_uv:
        q["vertex_texcoords"] = mi.Float(np.array(p["vertex_texcoords"], np.float32))
    q.update()
    return m


def _emissive_mesh(mi, sid, V, F, radiance, normals=None):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(diffuse([0.0, 0.0, 0.0]))
    props["emitter"] = mi.load_dict({"type": "area", "radiance": {
        "type": "rgb", "value": list(map(float, radiance))}})
    m = mi.Mesh(sid, len(V), len(F), props, has_vertex_normals=normals is not None,
                has_vertex_texcoords=False)
    q = mi.traverse(m)
    q["vertex_positions"] = mi.Float(np.asarray(V, np.float32).ravel())
    q["faces"] = mi.UInt32(np.asarray(F, np.uint32).ravel())
    if normals is not None:
        q["vertex_normals"] = mi.Float(np.asarray(normals, np.float32).ravel())
    q.update()
    return m


def _camera_paths():
    return [
        # walk down the court along x, looking ahead and up at the arcades
        CameraPath([([-10.0, 1.8, 0.5], [0.0, 4.0, 0.0]), ([-5.0, 2.2, -1.0], [4.0, 3.0, 3.5]),
                    ([0.0, 2.0, 0.8], [8.0, 3.0, -3.5]), ([5.0, 2.4, -0.5], [11.0, 5.0, 0.0]),
                    ([9.0, 2.0, 0.3], [0.0, 8.0, 0.0])], fov=60, name="court_walk"),
        # along the +z lower hallway past two of the lamps
        CameraPath([([-11.0, 1.7, 5.4], [-5.0, 1.8, 4.6]), ([-5.0, 1.7, 5.6], [2.0, 2.0, 4.0]),
                    ([1.0, 1.8, 5.0], [8.5, 2.0, 5.0]), ([6.0, 1.7, 5.6], [12.0, 1.5, 3.5]),
                    ([10.5, 1.8, 5.0], [0.0, 3.0, 0.0])], fov=65, name="hallway"),
        # a high view from the first-floor gallery level across the court
        CameraPath([([9.0, 9.0, 2.0], [0.0, 2.0, -2.0]), ([4.0, 10.0, 2.5], [-6.0, 2.0, 0.0]),
                    ([-2.0, 9.5, 2.0], [-9.0, 3.0, -5.0]), ([-7.0, 8.5, -1.5], [3.0, 1.5, -5.0]),
                    ([-9.0, 7.0, 0.0], [4.0, 6.0, 5.5])], fov=60, name="gallery"),
        # low orbit around the centre of the court looking at the hallways
        CameraPath([([2.5, 1.2, 1.5], [-4.0, 2.0, 5.5]), ([-2.5, 1.4, 1.8], [-8.0, 2.5, -5.0]),
                    ([-3.0, 1.3, -1.0], [6.0, 2.0, -5.5]), ([2.0, 1.5, -2.0], [8.5, 2.5, 5.0]),
                    ([3.5, 1.2, 0.0], [-2.0, 12.0, 0.0])], fov=55, name="court_orbit"),
    ]


# the options a scene name may carry (``sponza:exposure=...``); scenes.load refuses others
OPTIONS = ('exposure',)


def build(**options):
    if not SPONZA_XML.exists():
        raise SceneError("sponza needs ../shared/scenes/sponza/sponza.xml, which is not present")
    import mitsuba as mi
    import trimesh

    try:
        src = mi.load_file(str(SPONZA_XML))
    except Exception as e:  # Mitsuba raises RuntimeError with a long message
        msg = str(e).strip().splitlines()
        raise SceneError(f"cannot load {SPONZA_XML}: {msg[-1] if msg else type(e).__name__}") from None

    d = {"type": "scene", "integrator": {"type": "direct"}}
    n = 0
    # Mitsuba's loader (merging meshes of one material) returns the shapes in an
    # order that changes from run to run; the cache layout and its keys follow the
    # shape order, so the shapes are numbered in a fixed order here.
    def order(s):
        b = s.bbox()
        return (s.id(), s.bsdf().id() if s.bsdf() is not None else "", s.face_count() if s.is_mesh() else 0,
                s.vertex_count() if s.is_mesh() else 0, tuple(b.min), tuple(b.max))

    for s in sorted(src.shapes(), key=order):
        if s.is_emitter() or not s.is_mesh():
            continue  # the file's tiny analytic sphere light
        n += 1
        base = s.id() or (s.bsdf().id() if s.bsdf() is not None else "") or "mesh"
        sid = f"sponza_{n:02d}_{base}".replace(".", "_")
        d[sid] = _copy_mesh(mi, s, sid)

    for i, c in enumerate(LAMPS):
        tm = trimesh.creation.icosphere(subdivisions=2, radius=LAMP_RADIUS)
        tm.apply_translation(np.asarray(c, float))
        V = np.asarray(tm.vertices)
        N = (V - np.asarray(c, float)) / LAMP_RADIUS
        sid = f"lamp_{i}"
        d[sid] = _emissive_mesh(mi, sid, V, np.asarray(tm.faces), LAMP_RADIANCE, normals=N)

    hx, hz = TOP_HALF
    V = np.array([[-hx, TOP_Y, -hz], [hx, TOP_Y, -hz], [hx, TOP_Y, hz], [-hx, TOP_Y, hz]])
    # winding chosen so that the geometric normal points down (-y), into the atrium
    F = np.array([[0, 1, 2], [0, 2, 3]])
    assert np.cross(V[1] - V[0], V[2] - V[0])[1] < 0
    d["top_light"] = _emissive_mesh(mi, "top_light", V, F, TOP_RADIANCE)

    sc = mi.load_dict(d)
    exposure = float(options.get("exposure", 1.5))
    return Scene("sponza", sc, _camera_paths(), exposure=exposure, unit=1.0,
                 description=__doc__.strip().splitlines()[0], meeting_center=[0.0, 2.0, 0.0])
