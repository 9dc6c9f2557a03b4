"""Spherical harmonics radiance encodings with YCoCg chrominance compression
(Vardis et al. 2014, "Real-time radiance caching using chrominance
compression"): basis, YCoCg transform, projection and closed-form
irradiance, and the shading from a cached radiance field
(:mod:`slc.sh.shading`). Used by the CRC grid cache (:mod:`slc.crc`), the
on-surface SH cache (:mod:`slc.sh.method`) and the adaptive cache's SH pool."""
from .basis import A_HAT, basis, clamped_cosine_zonal, n_coeffs, ringing_bound
from .project import irradiance, project, radiance
from .shading import shade_radiance
from .ycocg import ENCODINGS, Encoding, encoding, rgb_to_ycocg, ycocg_to_rgb

__all__ = ["A_HAT", "basis", "clamped_cosine_zonal", "n_coeffs", "ringing_bound", "irradiance", "project",
           "radiance", "shade_radiance", "ENCODINGS", "Encoding", "encoding", "rgb_to_ycocg", "ycocg_to_rgb"]
