"""Spherical harmonics radiance encodings with YCoCg chrominance compression
(Vardis et al. 2014, "Real-time radiance caching using chrominance
compression"): basis, YCoCg transform, projection and closed-form
irradiance, and the shading from a cached radiance field
(:mod:`slc.methods.sh.shading`). Used by the CRC grid cache (:mod:`slc.methods.crc`), the
on-surface SH cache (:mod:`slc.methods.sh.method`) and the adaptive cache's SH pool."""
from slc.methods.sh.basis import A_HAT, basis, clamped_cosine_zonal, n_coeffs, ringing_bound
from slc.methods.sh.project import irradiance, project, radiance
from slc.methods.sh.shading import shade_radiance
from slc.methods.sh.ycocg import ENCODINGS, Encoding, encoding, rgb_to_ycocg, ycocg_to_rgb

__all__ = ["A_HAT", "basis", "clamped_cosine_zonal", "n_coeffs", "ringing_bound", "irradiance", "project",
           "radiance", "shade_radiance", "ENCODINGS", "Encoding", "encoding", "rgb_to_ycocg", "ycocg_to_rgb"]
