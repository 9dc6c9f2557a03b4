r"""Real spherical harmonics up to 3 bands (l = 0, 1, 2; 9 coefficients).

The basis is the usual real, orthonormal one (Sloan, "Stupid SH tricks"),
indexed ``i = l * (l + 1) + m``:

.. math:: Y_0^0 = \tfrac{1}{2}\sqrt{1/\pi},\quad
          (Y_1^{-1}, Y_1^0, Y_1^1) = \tfrac{1}{2}\sqrt{3/\pi}\,(y, z, x),\quad
          Y_2^{-2} = \tfrac{1}{2}\sqrt{15/\pi}\,xy, \dots

Every function here only uses arithmetic, so it works on Dr.Jit arrays
(inside kernels) and on numpy arrays (tests, set-up) alike.
"""
from __future__ import annotations

import math

# ------------------------------- Constants -------------------------------
C0 = 0.5 * math.sqrt(1.0 / math.pi)            # 0.282095
C1 = 0.5 * math.sqrt(3.0 / math.pi)            # 0.488603
C2 = 0.5 * math.sqrt(15.0 / math.pi)           # 1.092548
C20 = 0.25 * math.sqrt(5.0 / math.pi)          # 0.315392
C22 = 0.25 * math.sqrt(15.0 / math.pi)         # 0.546274

#: Ramamoorthi-Hanrahan cosine-lobe convolution factors per band: the
#: irradiance of a radiance field with coefficients L_lm is
#: E(n) = sum_lm A_l L_lm Y_lm(n).
A_HAT = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)

MAX_BANDS = 3


def n_coeffs(bands: int) -> int:
    """Coefficients of an SH expansion with ``bands`` bands (l < bands)."""
    if not 1 <= bands <= MAX_BANDS:
        raise ValueError(f"SH bands must be 1..{MAX_BANDS}, got {bands}")
    return bands * bands


def band_of(i: int) -> int:
    """Band l of coefficient index i = l(l+1)+m."""
    return int(math.isqrt(i))


def basis(x, y, z, bands: int = 3) -> list:
    """The first ``bands**2`` real SH functions at the unit direction (x, y, z)."""
    n = n_coeffs(bands)
    out = [C0 + 0.0 * x]
    if n > 1:
        out += [C1 * y, C1 * z, C1 * x]
    if n > 4:
        out += [C2 * x * y, C2 * y * z, C20 * (3.0 * z * z - 1.0), C2 * x * z, C22 * (x * x - y * y)]
    return out


def clamped_cosine_zonal(bands: int = 3) -> list:
    """Zonal coefficients z_l of max(cos(theta), 0) about the z axis:
    sqrt(pi)/2, sqrt(pi/3), sqrt(5 pi)/8. A lobe about the unit axis a has
    coefficients sqrt(4 pi / (2l+1)) z_l Y_lm(a)."""
    z = [math.sqrt(math.pi) / 2.0, math.sqrt(math.pi / 3.0), math.sqrt(5.0 * math.pi) / 8.0]
    return z[:bands]


def ringing_bound() -> float:
    r"""kappa such that the 9-coefficient irradiance of any non-negative
    radiance field L satisfies E_9(n) >= -kappa \int L d\omega.

    E_9(n) = \int L(w) K(n.w) dw with the kernel
    K(c) = 1/4 + c/2 + 5/16 (3c^2 - 1)/2, whose minimum, at c = -8/15, is
    -kappa = 1/4 - 4/15 + (15 (8/15)^2 - 5)/32 = -0.03958."""
    c = -8.0 / 15.0
    return -(0.25 + 0.5 * c + (15.0 * c * c - 5.0) / 32.0)
