"""The crc experiment's (experiments/crc.py) supplementary measurements: the terms of the
errors, each alone, the moving volume against the grid over the whole scene, and where (which
pixels, which light) Y3Co1Cg1 differs from Y3Co3Cg3 in the final frame. ``c`` is the
experiment's module (its configuration specs and run settings)."""
from __future__ import annotations

import contextlib
import statistics

import mitsuba as mi
import numpy as np

from slc.methods.crc.bounces import front_normal
from slc.methods import FrameContext
from slc.methods.crc.quality import delta_e76
from slc.reference.metrics import lab_rmse
from slc.reference.references import image_of, reference_for
from slc.run.pipeline import run_sequence
from slc.scene.gbuffer import frame_gbuffers

#: the error terms: sample multiplier of the low-noise runs
TERMS_SAMPLES = 4
#: the moving volume: window side as a fraction of the grid resolution, camera-path frames per
#: rendered frame (a faster walk, so that the window moves within the quick preset's frames),
#: window centre ahead of the viewer [cells] (0: centred at the viewer, the paper); scenes whose
#: cameras stay outside the scene box (the Cornell box) are not run
MOVING = dict(window_fraction=0.5, step=20, ahead=0.0, skip=("cornell",))
#: the attribution: a pixel is lit mostly by indirect light when its indirect light is at least this
#: share of its luminance (final frame, Y3Co3Cg3); shapes listed by their share of the squared dE
INDIRECT_LIT = 0.5
TOP_SHAPES = 3
#: emitter parameters that scale its light (all of them 0: the emitter is off)
LIGHT_PARAMS = ("radiance.value", "intensity.value", "irradiance.value", "scale")
#: Rec. 709 luminance of linear RGB
LUMA = (0.2126, 0.7152, 0.0722)


def last_image(c, scene, viewers, config: dict, W: int, H: int, frames: int, seed: int):
    """(method, G-buffer, indirect image) of the last of ``frames`` frames of the crc method of
    ``config`` (:func:`make` of the experiment's module ``c``)."""
    m = c.make(scene, config, seed)
    res = run_sequence(scene, m, viewers, c.run_config(W, H, frames, 0))
    gb = frame_gbuffers(scene, viewers, frames - 1, W, H)[0]
    return m, gb, res.last[gb.viewer]


def error_terms(c, scene, viewers, nb: int, common: dict, W: int, H: int, frames: int, seed: int,
                 ref_spp: int, direct_spp: int) -> dict:
    """The terms of the errors, each alone at the last frame (composited: ground-truth direct
    + indirect; Lab RMSE, percent): encoding (Y3Co1Cg1 offset / ratio decoding against RGB3 of
    the same sampling, at the default samples and at ``TERMS_SAMPLES`` x: what stays is
    systematic); noise (RGB3 against RGB3 with another seed: sqrt(2) x one estimate's noise);
    quantisation (the RGB3 cache as float16, the GPU's render targets, against float32);
    interpolation (1 bounce: the grid against the estimator at each shaded point's own lookup
    point, both at the high samples); reference noise (``ref_spp`` against 4x); RGB3 and the
    unfiltered estimator against the reference."""
    f = frames - 1

    def last(seed_=seed, **kw):
        return last_image(c, scene, viewers, {**common, "bounces": nb, **kw}, W, H, frames, seed_)

    m0, gb, rgb = last(encoding="rgb3")
    hi = TERMS_SAMPLES * m0.samples
    direct = reference_for("direct", scene, gb, f, gb.viewer, spp=direct_spp)
    ind = reference_for("indirect", scene, gb, f, gb.viewer, spp=ref_spp, bounces=nb)
    ind4 = reference_for("indirect", scene, gb, f, gb.viewer, spp=4 * ref_spp, bounces=nb)

    def L(a, b):
        return lab_rmse(direct + a, direct + b, scene.exposure)

    img = {"rgb3": rgb, "offset": last(encoding="y3co1cg1")[2],
           "ratio": last(encoding="y3co1cg1", chroma="ratio")[2], "seed": last(seed + 1, encoding="rgb3")[2]}
    mh, _, img["rgb3_hi"] = last(encoding="rgb3", samples=hi)
    img["offset_hi"] = last(encoding="y3co1cg1", samples=hi)[2]
    img["ratio_hi"] = last(encoding="y3co1cg1", chroma="ratio", samples=hi)[2]
    out = {"scene": scene.name, "bounces": nb, "samples": m0.samples, "samples_hi": hi,
           "encoding_offset": L(img["rgb3"], img["offset"]), "encoding_ratio": L(img["rgb3"], img["ratio"]),
           "encoding_offset_hi": L(img["rgb3_hi"], img["offset_hi"]),
           "encoding_ratio_hi": L(img["rgb3_hi"], img["ratio_hi"]),
           "noise_two_seeds": L(img["rgb3"], img["seed"]), "noise_vs_hi": L(img["rgb3_hi"], img["rgb3"]),
           "rgb3_vs_ref": L(ind, img["rgb3"]), "rgb3_hi_vs_ref": L(ind, img["rgb3_hi"]),
           "reference_noise": L(ind4, ind), "rgb3_vs_ref4": L(ind4, img["rgb3"])}
    c32 = mh.cache
    mh.cache = mi.Float(np.array(c32, dtype=np.float32).astype(np.float16).astype(np.float32))
    out["quantisation_fp16"] = L(img["rgb3_hi"], image_of("indirect", gb, mh.shade(FrameContext(f), None, 0, gb)))
    mh.cache = c32
    out["interpolation"] = out["unfiltered_hi_vs_ref"] = None
    if nb == 1:
        unf = image_of("indirect", gb, mh.shade_unfiltered(f, gb))
        out["interpolation"], out["unfiltered_hi_vs_ref"] = L(unf, img["rgb3_hi"]), L(ind, unf)
    # mean indirect light over the reference's, per channel
    out["rgb3_hi_mean_over_ref"] = (img["rgb3_hi"].reshape(-1, 3).mean(0)
                                    / np.maximum(ind.reshape(-1, 3).mean(0), 1e-12)).round(3).tolist()
    out["indirect_share"] = float(np.mean(ind) / max(float(np.mean(direct + ind)), 1e-12))
    return out


class _Moves:
    """A run's progress hook that records the method's move count after each frame."""

    def __init__(self, method):
        self.method, self.moves = method, []

    def update(self, n: int) -> None:
        self.moves.append(self.method.region.moves)


def moving(c, scene, viewers, nb: int, common: dict, W: int, H: int, frames: int, seed: int, ref_spp: int,
            direct_spp: int) -> dict:
    """The moving volume (``volume=camera``) against the grid over the whole scene, Y3Co1Cg1,
    on the camera path at ``MOVING['step']`` path frames per rendered frame, one run after the
    other on the same frames. Times: median ms per frame after 2 warm-up frames; kernels built
    or loaded by the moving cache after warm-up and after its first move (the first move
    builds the scroll kernel); errors at the last frame (composited, Lab RMSE): each against
    the reference over the image and over the pixels inside the window, and the two caches
    against each other inside the window."""
    window = max(4, int(round(common["resolution"] * MOVING["window_fraction"])))
    ms = c.make(scene, {**common, "bounces": nb}, seed)
    mc = c.make(scene, {**common, "bounces": nb, "volume": "camera", "window": window, "ahead": MOVING["ahead"]}, seed)
    warm, cfg = 2, c.run_config(W, H, frames, 2, frame_step=MOVING["step"])
    rs, moves = run_sequence(scene, ms, viewers, cfg), _Moves(mc)
    rc = run_sequence(scene, mc, viewers, cfg, progress=moves)
    first_move = next((k for k, n in enumerate(moves.moves) if n), None)
    built = sum(x["compiled"] for k, x in enumerate(rc.frames_ms)
                if first_move is not None and k > first_move and k >= warm)
    f = (frames - 1) * MOVING["step"]
    gb = frame_gbuffers(scene, viewers, f, W, H)[0]
    direct = reference_for("direct", scene, gb, f, gb.viewer, spp=direct_spp)
    ind = reference_for("indirect", scene, gb, f, gb.viewer, spp=ref_spp, bounces=nb)
    a, b = rs.last[gb.viewer], rc.last[gb.viewer]
    q = gb.si.p + front_normal(gb.si) * (0.5 * mc.grid.h)
    inside = np.array(gb.valid & mc.region.in_window(gb.si.p, q)).reshape(H, W)

    def err(r, t, mask=None):
        if mask is None:
            return lab_rmse(direct + r, direct + t, scene.exposure)
        return lab_rmse(direct[mask][None] + r[mask][None], direct[mask][None] + t[mask][None],
                        scene.exposure) if mask.any() else None

    def med(res, key):
        return statistics.median(x.get(key, 0.0) for x in res.frames_ms[warm:])
    return {"scene": scene.name, "bounces": nb, "window": window, "window_cells": mc.grid.n_cells,
            "grid_cells": ms.grid.n_cells, "step": MOVING["step"], "frames": frames, "last_frame": f,
            "moves": mc.region.moves, "first_move_frame": first_move, "kernels_built_after_warmup": built,
            "time_scene_ms": med(rs, "total"), "time_camera_ms": med(rc, "total"), "scroll_ms": med(rc, "scroll"),
            "time_camera_vs_scene": med(rc, "total") / max(med(rs, "total"), 1e-9),
            "active_scene": ms.n_active, "active_camera": mc.n_active,
            "inside_fraction": float(inside.sum() / max(int(np.array(gb.valid).sum()), 1)),
            "lab_rmse_ref_scene": err(ind, a), "lab_rmse_ref_camera": err(ind, b),
            "lab_rmse_ref_scene_inside": err(ind, a, inside), "lab_rmse_ref_camera_inside": err(ind, b, inside),
            "camera_vs_scene_inside": err(a, b, inside)}


def light_names(scene) -> list[str]:
    """``id (class)`` of each emitter (an area light by its shape's id)."""
    out = []
    for k, e in enumerate(scene.mi_scene.emitters()):
        sh = e.get_shape()
        out.append(f"{e.id() or (sh.id() if sh is not None else '') or f'emitter {k}'} ({e.class_name()})")
    return out


@contextlib.contextmanager
def only_light(scene, k: int):
    """Inside the block every emitter of ``scene`` but the ``k``-th is off (its
    :data:`LIGHT_PARAMS` are 0); they are restored on leaving it."""
    saved = []
    try:
        for i, e in enumerate(scene.mi_scene.emitters()):
            if i == k:
                continue
            p = mi.traverse(e)
            for key in p.keys():
                if key in LIGHT_PARAMS:
                    saved.append((p, key, type(p[key])(p[key])))
                    p[key] = p[key] * 0.0
            p.update()
        yield
    finally:
        for p, key, v in saved:
            p[key] = v
            p.update()


def attribution(c, scene, viewers, nb: int, common: dict, W: int, H: int, frame: int, seed: int, y333: dict,
                y311: dict) -> dict:
    """Where Y3Co1Cg1 differs from Y3Co3Cg3 in the final frame ``frame`` (``y333``, ``y311``: the
    Table 1 images of that frame, {"direct", "indirect", "final"}): the squared CIE76 dE of
    the surface pixels (those showing a surface, not the background), of the pixels lit
    mostly by indirect light (its indirect light >= ``INDIRECT_LIT`` of the pixel's
    luminance) and of the other surface pixels; the ``TOP_SHAPES`` shapes with the
    largest share of it; and per light the final frame's Lab RMSE when only that light's
    indirect light is compressed (both caches re-run with the other lights off; the offset
    decoding is linear in the coefficients and the coefficients in the lights, so the lights'
    differences add up to the whole but for the clamp of negative irradiance to 0)."""
    ex, fin = scene.exposure, y333["final"]
    luma = np.asarray(LUMA)
    de2 = delta_e76(fin, y311["final"], ex) ** 2
    gb = frame_gbuffers(scene, viewers, frame, W, H)[0]
    valid = np.array(gb.valid).reshape(H, W)
    shape = np.array(gb.shape_index).reshape(H, W)
    lit_ind = valid & (y333["indirect"] @ luma >= INDIRECT_LIT * (fin @ luma))
    total = max(float(de2.sum()), 1e-30)

    def rmse(mask):
        return float(np.sqrt(de2[mask].mean())) if mask.any() else None

    shapes = scene.mi_scene.shapes()
    per_shape = sorted(((float(de2[valid & (shape == i)].sum()) / total, i) for i in np.unique(shape[valid])),
                       reverse=True)[:TOP_SHAPES]
    lights = []
    names = light_names(scene)
    ind_all = max(float((y333["indirect"] @ luma).sum()), 1e-30)
    for k, name in enumerate(names):
        if len(names) == 1:
            d, share = y311["indirect"] - y333["indirect"], 1.0
        else:
            with only_light(scene, k):
                a, b = (last_image(c, scene, viewers, {**common, "bounces": nb, "encoding": e}, W, H, frame + 1,
                                   seed)[2] for e in ("y3co3cg3", "y3co1cg1"))
            d, share = b - a, float((a @ luma).sum()) / ind_all
        lights.append({"light": name, "indirect_share": share, "lab_rmse_final_alone": lab_rmse(fin, fin + d, ex)})
    return {"scene": scene.name, "bounces": nb, "frame": frame, "lab_rmse_final": float(np.sqrt(de2.mean())),
            "surface_pixels": float(valid.mean()), "lab_rmse_final_surface": rmse(valid),
            "indirect_lit_pixels": float(lit_ind.mean()),
            "indirect_lit_error_share": float(de2[lit_ind].sum()) / total,
            "lab_rmse_final_indirect_lit": rmse(lit_ind), "lab_rmse_final_direct_lit": rmse(valid & ~lit_ind),
            "shapes": [{"shape": shapes[i].id(), "pixels": float((valid & (shape == i)).mean()), "error_share": e}
                       for e, i in per_shape],
            "lights": lights, "_de_map": de2 ** 0.5, "_indirect_lit": lit_ind,
            "_images": {"y3co3cg3": y333, "y3co1cg1": y311}}
