"""An experiment's images: each evaluated image as EXR and PNG with its comparison strip
against the reference (:func:`save_strip`), and the multi-layer EXR of each scene and
evaluated frame that collects every method's image, its FLIP map and the reference
(:func:`add_to_frame_exr`).
"""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from slc.core import io
from slc.core.backend import code_version


def _file_name(name: str) -> str:
    return name.replace(':', '_').replace(',', '_')


def strip_saver(out: Path):
    """An ``on_result`` callback for :func:`slc.run.experiment.run_per_scene` (on the driver,
    before a job is committed) that saves every row's images with :func:`save_strip`."""
    def save(job, rows, res):
        scene = SimpleNamespace(name=res["scene_name"], exposure=res["exposure"])
        for row, images in zip(rows, res["images"]):
            save_strip(out, scene, row["label"], SimpleNamespace(images=images))
    return save


def save_strip(out: Path, scene, label: str, res) -> None:
    """EXR/PNG of the first evaluated viewer and its comparison strip, and the image, its
    reference and its FLIP map as layers of the scene's multi-layer EXR of that frame
    (:func:`add_to_frame_exr`)."""
    for vname, im in res.images.items():
        stem = out / "images" / f"{scene.name}_{_file_name(label)}"
        io.write_hdr_and_png(stem, im["img"], scene.exposure)
        io.write_hdr_and_png(out / "images" / f"{scene.name}_gt", im["gt"], scene.exposure)
        io.comparison_strip(stem.with_name(stem.name + "_strip.png"), im["gt"], im["img"], im["flip_map"],
                            scene.exposure)
        add_to_frame_exr(out, scene, label, im)
        break


_FRAME_EXRS: set = set()    # frame EXRs this process started: later methods add their layers


def add_to_frame_exr(out: Path, scene, label: str, im: dict) -> Path:
    """Add a method's evaluated image to ``OUT/images/SCENE_frameF.exr``, one multi-layer EXR
    per experiment, scene and evaluated frame: a layer per method (named by its label, dots
    as underscores), its FLIP error map (``LABEL_error``, one channel) and the reference
    (``reference``; a method whose reference differs, e.g. another output kind, gets its own
    ``LABEL_reference``). Header: ``slc:experiment`` (the folder's name), ``slc:scene``,
    ``slc:frame``, ``slc:code_version`` (:func:`slc.core.backend.code_version`) and ``slc:layers``,
    JSON: per method layer its full setting, its reference and error layers and the exposure
    of its tone map (PNGs, FLIP). The first call of a run replaces a file left
    by an earlier run; later calls read it back and add their layers."""
    frame = int(im.get("frame", -1))
    path = out / "images" / f"{_file_name(scene.name)}_frame{frame}.exr"
    layers, meta = {}, {}
    if path in _FRAME_EXRS and path.exists():
        layers, header = io.read_layers(path)
        meta = json.loads(header.get("slc:layers", "{}"))
    _FRAME_EXRS.add(path)
    name = io.layer_name(label)
    gt = np.asarray(im["gt"], np.float32)
    ref = "reference" if "reference" not in layers or np.array_equal(layers["reference"], gt) \
        else f"{name}_reference"
    layers[ref] = gt
    layers[name] = im["img"]
    layers[f"{name}_error"] = im["flip_map"]
    meta[name] = {"setting": label, "reference": ref, "error": f"{name}_error",
                  "exposure": float(im.get("exposure", scene.exposure))}
    io.write_layers(path, layers, {"slc:experiment": out.name, "slc:scene": scene.name, "slc:frame": frame,
                                   "slc:code_version": code_version(), "slc:layers": json.dumps(meta)})
    return path
