"""The crc experiment's (experiments/crc.py) protocol of the CRC paper's Table 1 (Sec. 7:
"the RMS error in the CIE Lab space and the PerceptualDiff metric [...] with respect to the
uncompressed linear space RGB values"; Table 1: "Y3Co3Cg3 vs Y3Co1Cg1"): each measure of each
image of a configuration against the same image of a reference configuration of the same
sampling, settings and frames. The choices where the paper's text is vague are stated in
docs/sh-crc.md."""
from __future__ import annotations

import numpy as np

from slc.methods.crc.quality import de76_fraction, pdiff
from slc.reference.metrics import lab_rmse
from slc.reference.references import exposure_for

#: the paper's two measures, each of two images against two references (row fields
#: ``{measure}_{image}`` against Y3Co3Cg3 and ``{measure}_{image}_vs_rgb3`` against RGB3)
PROTOCOL = dict(measures=("lab_rmse", "pdiff"), images=("final", "indirect"), references=("y3co3cg3", "rgb3"))


def base_for(r: dict, group: list[dict], encoding: str = "rgb3"):
    """Index of the row with ``encoding`` (and the paper's offset decoding) that differs from
    ``r`` only in the encoding and chroma decoding (None for the variants, or when there is none)."""
    if r["variant"]:
        return None
    return next((j for j, x in enumerate(group) if x["variant"] == "" and x["occupancy"] == r["occupancy"]
                 and x["visibility"] == r["visibility"] and x["encoding"] == encoding and x["chroma"] == "offset"),
                None)


def field_name(measure: str, image: str, reference: str) -> str:
    """Row field of a :data:`PROTOCOL` measure: ``lab_rmse_final`` (against Y3Co3Cg3, the
    paper's Table 1), ``pdiff_indirect_vs_rgb3``, ..."""
    return f"{measure}_{image}" + ("" if reference == "y3co3cg3" else f"_vs_{reference}")


def exposure_of(image: str, scene, reference) -> float:
    """Exposure of a compared image: the scene's for the final frame; for the indirect light
    alone 0.8 / the 99th percentile of the reference's luminance (as the pipeline shows it)."""
    return exposure_for("indirect" if image == "indirect" else "full", scene, reference)


def compare(group: list[dict], images: list[dict], scene) -> None:
    """The paper's measures (:data:`PROTOCOL`) of each row's images against those of its
    Y3Co3Cg3 and RGB3 rows (same sampling, settings and frames; None without such a row),
    averaged over the evaluated frames; the share of pixels with CIE76 dE > 2.3 in the final
    frame against Y3Co3Cg3; the time against RGB3 and the unoptimized cache."""
    fns = {"lab_rmse": lab_rmse, "pdiff": pdiff, "de76_fraction": de76_fraction}

    def measure(fn, b, im, image):
        if b is None:
            return None
        vals = []
        for f, x in im.items():
            ref = images[b][f][image]
            vals.append(fns[fn](ref, x[image], exposure_of(image, scene, ref)))
        return float(np.mean(vals))

    for r, im in zip(group, images):
        for reference in PROTOCOL["references"]:
            b = base_for(r, group, reference)
            for image in PROTOCOL["images"]:
                for fn in PROTOCOL["measures"]:
                    r[field_name(fn, image, reference)] = measure(fn, b, im, image)
        r["de76_fraction_final"] = measure("de76_fraction", base_for(r, group, "y3co3cg3"), im, "final")
    unopt = next(r for r in group if not r["occupancy"] and r["encoding"] == "rgb3")
    for r in group:
        b = base_for(r, group)
        r["time_vs_rgb3"] = r["time_ms"] / max(group[b]["time_ms"], 1e-9) if b is not None else None
        r["time_vs_unoptimized"] = r["time_ms"] / max(unopt["time_ms"], 1e-9)
