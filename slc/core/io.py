"""Images in and out: EXR for HDR, PNG previews with one documented tone
map, and comparison strips (ground truth | method | FLIP error map).

Tone map (used for every PNG and for every LDR metric: FLIP, PSNR, SSIM):

    x = exposure * L                      (exposure fixed per scene)
    y = x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)   (Narkowicz's ACES fit)
    PNG = sRGB_OETF(clamp(y, 0, 1))

All writes go to a temporary file in the same folder and are renamed, so
no reader ever sees a half-written file.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import matplotlib
import matplotlib.image as mpimg
import mitsuba as mi
import numpy as np
import OpenEXR

from slc.core.backend import exr_pool


def tonemap(hdr: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """HDR linear RGB -> display sRGB in [0, 1] (float32)."""
    x = np.nan_to_num(np.asarray(hdr, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.maximum(x * exposure, 0.0)
    y = np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return np.clip(srgb, 0.0, 1.0).astype(np.float32)


def _atomic(path: Path, write):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_exr(path, img: np.ndarray) -> None:
    # raw HDR values: NaN/Inf/negative are written as they are (clamping is for display only)
    a = np.ascontiguousarray(img, dtype=np.float32)
    with exr_pool():
        _atomic(path, lambda p: mi.Bitmap(a, pixel_format=mi.Bitmap.PixelFormat.RGB).write(p))


def read_exr(path) -> np.ndarray:
    with exr_pool():
        return np.array(mi.Bitmap(str(path)), dtype=np.float32)


def layer_name(name: str) -> str:
    """``name`` as an EXR layer name: a dot would nest layers in EXR viewers, so dots become
    underscores (the full name belongs in the header)."""
    return str(name).replace(".", "_")


def write_layers(path, layers: dict, header: dict | None = None) -> None:
    """One multi-layer EXR written with OpenEXR: an (H, W, 3) image as the channels
    ``LAYER.R``, ``LAYER.G``, ``LAYER.B``, an (H, W) map as ``LAYER.Y``; float32, ZIP
    compression, raw values (NaN/Inf/negative as they are). ``header``: extra attributes
    (str, int or float values) next to the standard ones."""
    channels = {}
    for name, a in layers.items():
        a = np.asarray(a, np.float32)
        name = layer_name(name)
        if a.ndim == 3 and a.shape[2] == 3:
            for i, c in enumerate("RGB"):
                channels[f"{name}.{c}"] = np.ascontiguousarray(a[..., i])
        elif a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1):
            channels[f"{name}.Y"] = np.ascontiguousarray(a.reshape(a.shape[:2]))
        else:
            raise ValueError(f"layer {name!r}: expected an (H, W, 3) image or an (H, W) map, got {a.shape}")
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}

    def write(p):
        with OpenEXR.File(hdr, channels) as f:
            f.write(p)
    _atomic(path, write)


def read_layers(path) -> tuple[dict, dict]:
    """(layers, header) of an EXR: per layer an (H, W, 3) image (channels R, G, B) or an
    (H, W) map (one channel); the header with OpenEXR's standard attributes."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: np.array(c.pixels, np.float32) for k, c in f.channels().items()}
    groups: dict[str, dict] = {}
    for k, a in chans.items():
        layer, _, c = k.rpartition(".")
        groups.setdefault(layer, {})[c] = a
    layers = {}
    for layer, cs in groups.items():
        layers[layer] = np.stack([cs[c] for c in "RGB"], axis=-1) if set("RGB") <= set(cs) else \
            next(iter(cs.values()))
    return layers, header


def write_png(path, ldr: np.ndarray) -> None:
    a = np.clip(np.asarray(ldr, np.float32), 0.0, 1.0)
    _atomic(path, lambda p: mpimg.imsave(p, a, format="png"))


def write_hdr_and_png(stem, hdr: np.ndarray, exposure: float) -> None:
    """``stem.exr`` (linear) and ``stem.png`` (tone-mapped)."""
    stem = Path(stem)
    write_exr(stem.with_suffix(".exr"), hdr)
    write_png(stem.with_suffix(".png"), tonemap(hdr, exposure))


def comparison_strip(path, reference_hdr, test_hdr, flip_map, exposure: float) -> None:
    """One PNG: ground truth | method | FLIP error map (magma)."""
    fm = np.asarray(flip_map, np.float32)
    if fm.ndim == 3 and fm.shape[2] == 3:
        err = fm
    else:
        err = matplotlib.colormaps["magma"](np.clip(fm.squeeze(), 0, 1))[..., :3]
    h = reference_hdr.shape[0]
    sep = np.ones((h, 2, 3), np.float32)
    strip = np.concatenate([tonemap(reference_hdr, exposure), sep, tonemap(test_hdr, exposure), sep,
                            err.astype(np.float32)], axis=1)
    write_png(path, strip)


def write_npz(path, **arrays) -> None:
    """numpy arrays in one ``.npz`` file, written atomically."""
    _atomic(path, lambda p: np.savez(p, **arrays))


def write_figure(path, fig, dpi: int = 120) -> None:
    """A Matplotlib figure as PNG, written atomically."""
    _atomic(path, lambda p: fig.savefig(p, dpi=dpi, format="png"))


def write_json(path, obj) -> None:
    def enc(o):
        if isinstance(o, (np.floating,)):
            return float(o)
        if isinstance(o, (np.integer,)):
            return int(o)
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(type(o))
    text = json.dumps(obj, indent=2, default=enc, allow_nan=True)
    _atomic(path, lambda p: Path(p).write_text(text))


def write_text(path, text: str) -> None:
    _atomic(path, lambda p: Path(p).write_text(text))


def cached_array(path, compute, use_cache: bool = True) -> np.ndarray:
    """``np.load(path)`` when a cached copy exists, else ``compute()``, saved
    atomically to ``path`` (reference images: ground truth, path-traced
    indirect light)."""
    path = Path(path)
    if use_cache and path.exists():
        try:
            return np.load(path)
        except (OSError, ValueError):
            pass
    arr = np.asarray(compute())
    if use_cache:
        _atomic(path, lambda p: np.save(p, arr, allow_pickle=False))
    return arr
