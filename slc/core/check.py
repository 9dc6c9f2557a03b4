"""Check mode: stop at the first non-finite or negative value.

Methods return raw values (no clamping, no NaN/Inf replaced by 0: that
happens in the display tone map only, :func:`slc.core.io.tonemap`). Check mode
makes a bad value surface where it is made instead of as a black or white
pixel in a plot:

- every float-typed output of every timed stage (:meth:`slc.core.timing.StageTimer.stage`)
  is checked for NaN/Inf after the stage's ``dr.eval`` (outside the timed
  interval);
- every image a method returns (:func:`slc.run.pipeline.run_sequence`) is checked
  for NaN/Inf and for negative values, and so is the image composed from it
  with the emission seen directly (stage ``'compose'``), which is what is
  written and compared.

The first bad value raises :class:`CheckError` with a one-line message naming
the method, the frame, the stage and the pixel ``(viewer, x, y)`` or the
entry index, e.g.::

    check: rt16 frame 3 stage 'image': NaN at viewer 0 pixel (12, 7) (entry 292 of 1728)

Turn it on with ``SLC_CHECK=1`` in the environment or ``slc --check ...``
(which sets the variable, so experiments and their sub-steps see it).
Off (the default) it costs one environment look-up per stage: nothing is
read back from the device.

Stage outputs are what each stage declares (``st.outputs``), float arrays
checked, integer ones not: the cone cache's packed words (:mod:`slc.lib.cones.packing`)
encode a NaN or negative radiance sample as 0, so check mode sees such a
sample of the cone update only through the images it leads to.

Negative values are only an error in images (radiance): stage outputs hold
directions, SH coefficients, chroma and other quantities that are negative
by nature. +Inf is Mitsuba's "no hit / infinitely far" convention in the
struct fields ``t``, ``dist`` and ``maxt`` (interactions, direction samples,
rays) and is accepted there; NaN is not.
"""
from __future__ import annotations

import os
from contextlib import contextmanager

import drjit as dr
import numpy as np

ENV = "SLC_CHECK"
# struct fields in which +Inf means "no hit" / "infinitely far" (Mitsuba's convention)
_INF_FIELDS = ("t", "dist", "maxt")


class CheckError(RuntimeError):
    """A non-finite or negative value found in check mode (one-line message)."""


def enabled() -> bool:
    """Check mode is on (``SLC_CHECK`` set to anything but '', '0', 'false', 'no')."""
    return os.environ.get(ENV, "").strip().lower() not in ("", "0", "false", "no", "off")


def enable(on: bool = True) -> None:
    """Turn check mode on/off for this process and its children."""
    if on:
        os.environ[ENV] = "1"
    else:
        os.environ.pop(ENV, None)


# ------------------------------------------------------------------ context
# What is being run: set by the pipeline around ``method.render`` so that a
# stage check can name the method, the frame and translate lane indices into
# pixels.
_ctx: dict = {"method": "?", "frame": None, "sizes": []}


@contextmanager
def scope(method: str, frame: int | None = None, gbuffers=()):
    """Name the method/frame (and viewers' resolutions) for messages raised inside."""
    prev = dict(_ctx)
    _ctx.update(method=str(method), frame=frame,
                sizes=[(int(g.width), int(g.height)) for g in gbuffers])
    try:
        yield
    finally:
        _ctx.clear()
        _ctx.update(prev)


def _where(stage: str, what: str) -> str:
    f = _ctx.get("frame")
    fr = f" frame {f}" if f is not None else ""
    return f"check: {_ctx.get('method', '?')}{fr} stage '{stage}': {what}"


def _kind(x: float) -> str:
    if np.isnan(x):
        return "NaN"
    if np.isinf(x):
        return "+Inf" if x > 0 else "-Inf"
    return f"negative value {x:.6g}"


# ------------------------------------------------------------------ walking values

def _leaves(v, path: str, inf_ok: bool = False):
    """(path, 1-D float numpy array per component, +Inf allowed) of every
    float leaf of a Dr.Jit value or float numpy array, list/tuple/dict of them,
    or a DRJIT_STRUCT / Mitsuba struct (fields by name)."""
    if v is None or isinstance(v, (bool, int, str)):
        return
    if isinstance(v, (list, tuple)):
        for i, x in enumerate(v):
            yield from _leaves(x, f"{path}[{i}]")
        return
    if isinstance(v, dict):
        for k, x in v.items():
            yield from _leaves(x, f"{path}.{k}")
        return
    if isinstance(v, np.ndarray):              # host-side stage outputs (e.g. MegaViews' hierarchies)
        if v.dtype.kind == "f":
            yield path, v.astype(np.float64, copy=False).ravel(), inf_ok
        return
    fields = getattr(type(v), "DRJIT_STRUCT", None)
    if fields:
        for k in fields:
            yield from _leaves(getattr(v, k, None), f"{path}.{k}", k in _INF_FIELDS)
        return
    if not dr.is_array_v(v):
        return
    if not dr.is_float_v(v):
        return
    if dr.depth_v(v) == 1 or dr.is_tensor_v(v):
        yield path, np.asarray(v, dtype=np.float64).ravel(), inf_ok
    else:
        for i in range(len(v)):
            yield from _leaves(v[i], f"{path}[{i}]", inf_ok)


def _first_bad(a: np.ndarray, negative: bool, inf_ok: bool = False):
    bad = np.isnan(a) if inf_ok else ~np.isfinite(a)
    if inf_ok:
        bad |= np.isneginf(a)
    if negative:
        bad |= a < 0.0
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    return i, float(a[i])


def _pixel(i: int, n: int) -> str:
    """'pixel (x, y)' when ``n`` lanes are one viewer's image, else ''."""
    for w, h in _ctx.get("sizes", []):
        if n == w * h:
            return f" pixel ({i % w}, {i // w})"
    return ""


# ------------------------------------------------------------------ checks

def stage_outputs(stage: str, values) -> None:
    """Raise at the first NaN/Inf among the float leaves of a stage's outputs."""
    for k, v in enumerate(values):
        for path, a, inf_ok in _leaves(v, f"output {k}"):
            hit = _first_bad(a, negative=False, inf_ok=inf_ok)
            if hit is not None:
                i, x = hit
                raise CheckError(_where(stage, f"{_kind(x)} in {path}{_pixel(i, a.size)} "
                                               f"(entry {i} of {a.size})"))


def images(images, gbuffers, stage: str = "image") -> None:
    """Raise at the first NaN/Inf or negative value of per-viewer images
    (one Dr.Jit colour array per G-buffer, or (H, W, 3) numpy arrays)."""
    for v, (img, gb) in enumerate(zip(images, gbuffers)):
        if isinstance(img, np.ndarray):
            comps = [img.reshape(-1, img.shape[-1])[:, c].astype(np.float64) for c in range(img.shape[-1])]
        else:
            comps = [a for _, a, _ in _leaves(img, "")]
        w = int(gb.width)
        for c, a in enumerate(comps):
            hit = _first_bad(a, negative=True)
            if hit is not None:
                i, x = hit
                raise CheckError(_where(stage, f"{_kind(x)} at viewer {v} pixel ({i % w}, {i // w}) "
                                               f"channel {c} (entry {i} of {a.size})"))


def array(values, name: str, stage: str = "output", negative: bool = True) -> None:
    """Check one array (e.g. a reference image) outside a pipeline run."""
    for path, a, _ in _leaves(values, name):
        hit = _first_bad(np.asarray(a, np.float64).ravel(), negative)
        if hit is not None:
            i, x = hit
            raise CheckError(_where(stage, f"{_kind(x)} in {path} (entry {i} of {a.size})"))
