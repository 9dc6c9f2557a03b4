"""The CRC paper's image comparisons: CIE Lab RMSE (:func:`slc.metrics.lab_rmse`)
and the percentage of perceptibly different pixels.

pdiff here: the percentage of pixels whose CIE76 colour difference
(linear sRGB with the scene exposure, clipped to [0, 1], -> XYZ -> Lab, D65)
exceeds 2.3, the just-noticeable difference of Sharma's Digital Color
Imaging Handbook. (The paper used Yee's PerceptualDiff; this is a simpler,
stated threshold.)
"""
from __future__ import annotations

import numpy as np

JND_CIE76 = 2.3


def _lab(img, exposure):
    import colour
    rgb = np.clip(np.asarray(img, np.float64) * exposure, 0.0, 1.0)
    xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    return colour.XYZ_to_Lab(xyz)


def delta_e76(reference_hdr, test_hdr, exposure: float = 1.0) -> np.ndarray:
    import colour
    return colour.delta_E(_lab(reference_hdr, exposure), _lab(test_hdr, exposure), method="CIE 1976")


def pdiff(reference_hdr, test_hdr, exposure: float = 1.0, threshold: float = JND_CIE76) -> float:
    """Percent of pixels with CIE76 dE > ``threshold``."""
    d = delta_e76(reference_hdr, test_hdr, exposure)
    return float(np.mean(d > threshold) * 100.0)
