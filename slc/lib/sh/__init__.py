"""Spherical harmonics radiance encodings with YCoCg chrominance compression
(Vardis et al. 2014, "Real-time radiance caching using chrominance
compression"): basis, YCoCg transform, projection and closed-form
irradiance, and the shading from a cached radiance field
(:mod:`slc.lib.sh.shading`), and the projection of light samples into a cached field
(:mod:`slc.lib.sh.update`). Used by the on-surface SH cache (:mod:`slc.methods.sh`), the CRC grid
cache (:mod:`slc.methods.crc`), osc-gi (:mod:`slc.methods.oscgi`) and the adaptive cache's SH pool."""
from slc.lib.sh.basis import A_HAT, basis, clamped_cosine_zonal, n_coeffs, ringing_bound
from slc.lib.sh.project import irradiance, project, radiance
from slc.lib.sh.shading import shade_radiance
from slc.lib.sh.ycocg import ENCODINGS, Encoding, encoding, rgb_to_ycocg, ycocg_to_rgb

__all__ = ["A_HAT", "basis", "clamped_cosine_zonal", "n_coeffs", "ringing_bound", "irradiance", "project",
           "radiance", "shade_radiance", "ENCODINGS", "Encoding", "encoding", "rgb_to_ycocg", "ycocg_to_rgb"]
