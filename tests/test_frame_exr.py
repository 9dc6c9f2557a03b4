"""The multi-layer EXR of an experiment's evaluated frame: a layer per method, the reference and
each method's FLIP map, with scene, frame, settings and code version in the header, read back
with OpenEXR itself."""
import json
from types import SimpleNamespace

import numpy as np
import OpenEXR

from slc.run.images import _FRAME_EXRS, save_strip

from slc.core import io


def _images(rng, gt, frame=5):
    img = gt + rng.normal(0, 0.05, gt.shape).astype(np.float32)
    return {"v0": {"gt": gt, "img": img, "flip_map": rng.random(gt.shape[:2]).astype(np.float32),
                   "frame": frame, "exposure": 1.5}}


def test_frame_exr_layers_and_header(tmp_path):
    rng = np.random.default_rng(0)
    out = tmp_path / "single-viewer"
    scene = SimpleNamespace(name="cornell", exposure=1.5)
    gt = rng.random((9, 16, 3)).astype(np.float32)
    other_gt = gt * 0.5                                 # a method of another output kind
    runs = {"rt16": _images(rng, gt), "osc-gi:sharp=0.2": _images(rng, gt), "osc-gi:output=indirect":
            _images(rng, other_gt)}
    for label, images in runs.items():
        save_strip(out, scene, label, SimpleNamespace(images=images))
    path = out / "images" / "cornell_frame5.exr"

    with OpenEXR.File(str(path), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: np.array(c.pixels) for k, c in f.channels().items()}
    assert header["slc:scene"] == "cornell" and header["slc:frame"] == 5
    assert header["slc:experiment"] == "single-viewer" and header["slc:code_version"]
    meta = json.loads(header["slc:layers"])
    assert {m["setting"] for m in meta.values()} == set(runs)
    assert meta["osc-gi:sharp=0_2"]["reference"] == "reference"
    assert meta["osc-gi:output=indirect"]["reference"] == "osc-gi:output=indirect_reference"
    for name in ("rt16", "osc-gi:sharp=0_2", "osc-gi:output=indirect", "reference",
                 "osc-gi:output=indirect_reference"):
        assert {f"{name}.{c}" for c in "RGB"} <= set(chans), name
    for name in meta:
        assert f"{name}_error.Y" in chans
    np.testing.assert_array_equal(chans["reference.G"], gt[..., 1])
    np.testing.assert_array_equal(chans["osc-gi:output=indirect_reference.B"], other_gt[..., 2])
    layers, _ = io.read_layers(path)
    np.testing.assert_array_equal(layers["rt16"], runs["rt16"]["v0"]["img"])
    np.testing.assert_array_equal(layers["rt16_error"], runs["rt16"]["v0"]["flip_map"])

    # a new run (a new process) starts the file again: no layer of the old one is kept
    _FRAME_EXRS.clear()
    save_strip(out, scene, "rt16", SimpleNamespace(images=runs["rt16"]))
    layers, header = io.read_layers(path)
    assert set(layers) == {"rt16", "rt16_error", "reference"}
    assert set(json.loads(header["slc:layers"])) == {"rt16"}
