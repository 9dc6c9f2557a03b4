r"""The YCoCg colour transform (Malvar and Sullivan) and the radiance
encodings of Compressed Radiance Caching: luminance Y in 3 SH bands,
chrominance Co, Cg in 3, 2 or 1 bands.

.. math:: Y = R/4 + G/2 + B/4,\quad Co = R/2 - B/2,\quad Cg = -R/4 + G/2 - B/4

and back: R = Y + Co - Cg, G = Y + Cg, B = Y - Co - Cg. The transform is
linear, so accumulation and interpolation of SH coefficients hold in YCoCg.
"""
from __future__ import annotations

from dataclasses import dataclass

from slc.lib.sh.basis import n_coeffs


def rgb_to_ycocg(r, g, b):
    return 0.25 * r + 0.5 * g + 0.25 * b, 0.5 * r - 0.5 * b, -0.25 * r + 0.5 * g - 0.25 * b


def ycocg_to_rgb(y, co, cg):
    t = y - cg
    return t + co, y + cg, t - co


@dataclass(frozen=True)
class Encoding:
    """Per-channel SH band counts of a radiance encoding.

    ``space``: ``"ycocg"`` (channels Y, Co, Cg) or ``"rgb"``; ``bands``: SH
    bands per channel. Coefficients are laid out channel by channel:
    channel 0's ``bands[0]**2`` coefficients, then channel 1's, then 2's."""
    name: str
    space: str
    bands: tuple

    @property
    def counts(self) -> tuple:
        return tuple(n_coeffs(b) for b in self.bands)

    @property
    def offsets(self) -> tuple:
        c = self.counts
        return (0, c[0], c[0] + c[1])

    @property
    def n(self) -> int:
        return sum(self.counts)

    @property
    def max_bands(self) -> int:
        return max(self.bands)

    def to_space(self, r, g, b):
        return rgb_to_ycocg(r, g, b) if self.space == "ycocg" else (r, g, b)

    def to_rgb(self, c0, c1, c2):
        return ycocg_to_rgb(c0, c1, c2) if self.space == "ycocg" else (c0, c1, c2)


ENCODINGS = {
    "rgb3": Encoding("rgb3", "rgb", (3, 3, 3)),
    "y3co3cg3": Encoding("y3co3cg3", "ycocg", (3, 3, 3)),
    "y3co2cg2": Encoding("y3co2cg2", "ycocg", (3, 2, 2)),
    "y3co1cg1": Encoding("y3co1cg1", "ycocg", (3, 1, 1)),
    # further settings used for comparisons in the paper (Fig. 9)
    "rgb2": Encoding("rgb2", "rgb", (2, 2, 2)),
    "y2co2cg2": Encoding("y2co2cg2", "ycocg", (2, 2, 2)),
}


def encoding(name) -> Encoding:
    if isinstance(name, Encoding):
        return name
    try:
        return ENCODINGS[str(name).lower()]
    except KeyError:
        raise ValueError(f"unknown SH encoding '{name}' (available: {', '.join(ENCODINGS)})") from None
