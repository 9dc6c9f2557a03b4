"""Small scenes and loops shared by the tests."""
import numpy as np

from slc import gbuffer
from slc.methods import FrameContext
from slc.scenes import CameraPath, SceneBuilder, diffuse
from slc.timing import NullTimer


def plane_under_rect_light(half=0.25, height=1.0, radiance=10.0, albedo=0.5, plane_half=2.0,
                           name="plane_light", bsdf=None, light_transform=None):
    """A horizontal plane y = 0 (facing up) under a rectangular light of size
    2*half x 2*half at ``height`` facing down; camera looking down at it."""
    b = SceneBuilder(name)
    b.add_quad([0, 0, 0], [plane_half, 0, 0], [0, 0, -plane_half],
               bsdf=bsdf if bsdf is not None else diffuse([albedo] * 3), name="plane")
    b.add_quad([0, height, 0], [half, 0, 0], [0, 0, half], bsdf=diffuse([0, 0, 0]),
               emission=[radiance] * 3, name="light", transform=light_transform)
    cam = CameraPath([([0.0, 0.8 * height, 1.2], [0.0, 0.0, 0.0])], frames=64, fov=60)
    return b.build([cam, cam, cam])


def rect_irradiance(px, pz, x1, x2, z1, z2, h, L):
    """Closed-form irradiance at (px, 0, pz) from a uniform Lambertian
    rectangle [x1,x2] x [z1,z2] at height h, parallel to the plane."""
    def G(X, Z):
        A, B = X / h, Z / h
        return 0.5 * (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
                      + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B)))
    return L * (G(x2 - px, z2 - pz) - G(x1 - px, z2 - pz) - G(x2 - px, z1 - pz) + G(x1 - px, z1 - pz))


def render_frames(scene, method, viewers, frames, width, height, seed=0, start=0):
    """Run ``frames`` frames; return the composed images of the last frame."""
    from slc.pipeline import gbuffers_for
    out = None
    for f in range(start, start + frames):
        gbs = gbuffers_for(scene, viewers, f, width, height)
        d = method.render(FrameContext(f), gbs, NullTimer())
        out = [gbuffer.to_image(gb, gbuffer.compose(gb, x)) for gb, x in zip(gbs, d)]
    return out, gbs
