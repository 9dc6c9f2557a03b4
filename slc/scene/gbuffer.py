"""The G-buffer: one primary hit per pixel centre, shared by every method.

Every method, the ground truth included, shades exactly these surface
points, so measured errors are errors of direct illumination alone.

Camera rays are generated here (not by a Mitsuba sensor) from opaque
camera parameters, so a moving camera never recompiles a kernel.

Motion vectors reproject each hit into the previous frame's camera
(camera motion only: a moving object's own motion is not included, which
the temporal reuse of ReSTIR then rejects by its depth/normal tests).

Several viewers: besides one :class:`GBuffer` per viewer, the frame's
G-buffers are also laid out as one array (:class:`Layers`, attached to each
G-buffer by :func:`attach_layers`), as a multi-view renderer's layered
G-buffer (a texture array) would hold them, so that a method can process all
viewers' pixels in one launch without first copying them together in its own
timed stages. The layered copy is made here, with the G-buffer (untimed, as
the G-buffer itself).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from slc.scene.camera import Camera
from slc.scene.scenes import Scene


@dataclass
class GBuffer:
    """Primary hits of one viewer, flattened row-major (index = y * W + x).

    Fields: ``si`` (SurfaceInteraction3f; its ``wi`` is the local direction
    towards the camera), ``valid`` (a surface was hit), ``emitted`` (radiance
    emitted towards the camera by a hit emitter, or the environment seen
    through a miss), ``depth`` (ray distance), ``motion`` (previous pixel
    position minus current, in pixels), ``shape_index``/``prim_index``/
    ``prim_uv`` (a stable triangle id and barycentrics for cache lookups),
    ``footprint`` (world-space width of the pixel on the surface).
    """
    width: int
    height: int
    camera: Camera
    si: mi.SurfaceInteraction3f
    valid: mi.Bool
    emitted: mi.Color3f
    depth: mi.Float
    motion: mi.Vector2f
    shape_index: mi.UInt32
    prim_index: mi.UInt32
    prim_uv: mi.Point2f
    footprint: mi.Float
    viewer: str = ""
    layers: "Layers | None" = field(default=None, repr=False)   # the frame's viewers as one array
    layer: int = 0                                                 # this viewer's index in ``layers``

    @property
    def size(self) -> int:
        return self.width * self.height


@dataclass
class Layers:
    """The G-buffers of one frame's viewers one after another in one array:
    viewer ``v``'s pixel ``i`` is at ``offsets[v] + i``. ``si``, ``valid``,
    ``shape_index``, ``prim_index``, ``prim_uv`` and ``footprint`` as in
    :class:`GBuffer` (so that a cache can map every viewer's pixels to its
    entries in one launch); ``pixel`` is each entry's pixel index within its own
    viewer and ``viewer`` its viewer's index."""
    si: mi.SurfaceInteraction3f
    valid: mi.Bool
    pixel: mi.UInt32
    sizes: tuple
    offsets: tuple
    shape_index: mi.UInt32 = None
    prim_index: mi.UInt32 = None
    prim_uv: mi.Point2f = None
    footprint: mi.Float = None
    viewer: mi.UInt32 = None

    @property
    def size(self) -> int:
        return sum(self.sizes)


def viewer_lanes(n: int, off: int) -> mi.UInt32:
    """The lanes ``off .. off + n - 1`` of a layered array (one viewer's part;
    ``off`` opaque: one kernel whichever viewer)."""
    return dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, off)


def per_viewer(values, sizes, offsets) -> list:
    """Each viewer's part of ``values`` laid out as the layers (unevaluated gathers)."""
    return [dr.gather(type(values), values, viewer_lanes(n, off)) for n, off in zip(sizes, offsets)]


def _lay_out(gbuffers: list) -> Layers:
    sizes = tuple(gb.size for gb in gbuffers)
    offsets = tuple(sum(sizes[:v]) for v in range(len(sizes)))
    total = sum(sizes)
    lay = Layers(dr.empty(mi.SurfaceInteraction3f, total), dr.empty(mi.Bool, total), dr.empty(mi.UInt32, total),
                 sizes, offsets, dr.empty(mi.UInt32, total), dr.empty(mi.UInt32, total),
                 dr.empty(mi.Point2f, total), dr.empty(mi.Float, total), dr.empty(mi.UInt32, total))
    for v, (gb, n, off) in enumerate(zip(gbuffers, sizes, offsets)):
        at = viewer_lanes(n, off)
        dr.scatter(lay.si, gb.si, at)
        dr.scatter(lay.valid, mi.Bool(gb.valid), at)
        dr.scatter(lay.pixel, dr.arange(mi.UInt32, n), at)
        dr.scatter(lay.shape_index, mi.UInt32(gb.shape_index), at)
        dr.scatter(lay.prim_index, mi.UInt32(gb.prim_index), at)
        dr.scatter(lay.prim_uv, mi.Point2f(gb.prim_uv), at)
        dr.scatter(lay.footprint, mi.Float(gb.footprint), at)
        dr.scatter(lay.viewer, dr.opaque(mi.UInt32, v), at)
    dr.eval(lay.si, lay.valid, lay.pixel, lay.shape_index, lay.prim_index, lay.prim_uv, lay.footprint, lay.viewer)
    return lay


def attach_layers(gbuffers: list) -> Layers | None:
    """Lay the G-buffers ``gbuffers`` (one frame, several viewers) out as one
    :class:`Layers` and attach it to each (``gb.layers``, ``gb.layer``); the
    per-viewer G-buffers are unchanged. Nothing for fewer than two viewers."""
    if len(gbuffers) < 2:
        return None
    lay = _lay_out(gbuffers)
    for v, gb in enumerate(gbuffers):
        gb.layers, gb.layer = lay, v
    return lay


def layered(gbuffers: list) -> Layers:
    """The frame's viewers as one :class:`Layers`: the attached one when every
    G-buffer carries it (no copy); one G-buffer's own arrays (no copy; ``viewer``
    0); else laid out here (a copy, for callers that did not attach layers)."""
    if len(gbuffers) == 1:
        gb = gbuffers[0]
        return Layers(gb.si, mi.Bool(gb.valid), None, (gb.size,), (0,), mi.UInt32(gb.shape_index),
                      mi.UInt32(gb.prim_index), mi.Point2f(gb.prim_uv), mi.Float(gb.footprint),
                      dr.zeros(mi.UInt32, gb.size))
    lay = gbuffers[0].layers if gbuffers else None
    if lay is not None and lay.viewer is not None and len(lay.sizes) == len(gbuffers) and \
            all(gb.layers is lay and gb.layer == v for v, gb in enumerate(gbuffers)):
        return lay
    return _lay_out(gbuffers)


def _opaque_camera(cam: Camera, width: int, height: int):
    f, r, u = cam.basis()
    th = math.tan(math.radians(cam.fov) / 2)
    aspect = width / height
    vals = dict(o=cam.origin, f=f, r=r * th * aspect, u=u * th)
    out = {}
    for k, v in vals.items():
        out[k] = mi.Vector3f(*[dr.opaque(mi.Float, float(x)) for x in v])
    return out


def camera_rays(cam: Camera, width: int, height: int) -> mi.Ray3f:
    """One ray per pixel centre."""
    c = _opaque_camera(cam, width, height)
    idx = dr.arange(mi.UInt32, width * height)
    x = mi.Float(idx % width) + 0.5
    y = mi.Float(idx // width) + 0.5
    sx = 2.0 * x / width - 1.0
    sy = 1.0 - 2.0 * y / height
    d = dr.normalize(c["f"] + sx * c["r"] + sy * c["u"])
    return mi.Ray3f(mi.Point3f(c["o"]), d)


def project(cam: Camera, width: int, height: int, p: mi.Point3f):
    """Pixel coordinates (continuous, pixel centres at +0.5) of world points,
    and a mask of points in front of the camera."""
    c = _opaque_camera(cam, width, height)
    v = p - c["o"]
    z = dr.dot(v, c["f"])
    front = z > 1e-6
    zs = dr.select(front, z, 1.0)
    sx = dr.dot(v, c["r"]) / (zs * dr.squared_norm(c["r"]))
    sy = dr.dot(v, c["u"]) / (zs * dr.squared_norm(c["u"]))
    x = (sx + 1.0) * 0.5 * width
    y = (1.0 - sy) * 0.5 * height
    return mi.Vector2f(x, y), front


def render_gbuffer(scene: Scene, cam: Camera, width: int, height: int,
                   prev_cam: Camera | None = None, viewer: str = "") -> GBuffer:
    sc = scene.mi_scene
    ray = camera_rays(cam, width, height)
    pi = sc.ray_intersect_preliminary(ray, coherent=True)
    si = pi.compute_surface_interaction(ray)
    valid = si.is_valid()
    emitted = mi.Color3f(si.emitter(sc).eval(si))
    depth = dr.select(valid, si.t, 0.0)
    idx = dr.arange(mi.UInt32, width * height)
    cur = mi.Vector2f(mi.Float(idx % width) + 0.5, mi.Float(idx // width) + 0.5)
    if prev_cam is not None:
        prev, front = project(prev_cam, width, height, si.p)
        motion = dr.select(valid & front, prev - cur, mi.Vector2f(0.0))
    else:
        motion = mi.Vector2f(0.0)
    th = math.tan(math.radians(cam.fov) / 2)
    cos_n = dr.abs(dr.dot(si.n, -ray.d))
    footprint = dr.select(valid, si.t * (2.0 * th / height) / dr.maximum(cos_n, 0.05), 0.0)
    gb = GBuffer(width, height, cam, si, valid, emitted, depth, motion,
                 dr.select(valid, pi.shape_index, 0), dr.select(valid, pi.prim_index, 0),
                 mi.Point2f(pi.prim_uv), footprint, viewer)
    dr.eval(gb.si, gb.valid, gb.emitted, gb.depth, gb.motion, gb.shape_index, gb.prim_index,
            gb.prim_uv, gb.footprint)
    return gb


def frame_gbuffers(scene: Scene, viewers, frame: int, width: int, height: int) -> list:
    """The G-buffers of frame ``frame``: the scene posed at the frame
    (:meth:`Scene.set_frame`), one G-buffer per viewer (anything with ``camera(frame)`` and
    ``name``: a rig's viewer, a render node's viewer poses), its motion vectors towards the
    viewer's camera at the previous frame; with several viewers also laid out as one array
    (:func:`attach_layers`), as part of G-buffer generation. Every frame of the pipeline, of
    the render nodes and of their evaluation is built here."""
    scene.set_frame(frame)
    out = [render_gbuffer(scene, v.camera(frame), width, height, v.camera(frame - 1) if frame > 0 else None, v.name)
           for v in viewers]
    attach_layers(out)
    return out


def to_image(gb: GBuffer, value: mi.Color3f) -> np.ndarray:
    """(H, W, 3) float32 numpy image of a per-pixel colour."""
    a = np.array(value, dtype=np.float32)
    if a.ndim == 2 and a.shape[0] == 3:
        a = a.T
    # C order: a strided view would make numpy reductions (metrics) sum in another order than
    # the same image read back from the ground-truth cache (1-ulp differences between runs)
    return np.ascontiguousarray(a.reshape(gb.height, gb.width, 3))


def compose(gb: GBuffer, direct: mi.Color3f) -> mi.Color3f:
    """Final image value: emitted radiance seen directly plus direct light at
    valid hits. Raw: nothing is clamped and NaN/Inf are kept, so that they
    surface (check mode, :mod:`slc.core.check`, stops at them); clamping happens
    in the display tone map only (:func:`slc.core.io.tonemap`)."""
    return gb.emitted + dr.select(gb.valid, direct, 0.0)
