"""False-colour images and tables of the adaptive cache's per-entry choice."""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import numpy as np

from slc import methods
from slc.core import io
from slc.core.timing import NullTimer
from slc.methods import FrameContext
from slc.methods.adaptive.choice import CONES, NONE, SH, VIS, NAMES
from slc.run.experiment import each_scene
from slc.scene import gbuffer, views

#: display colours (linear RGB in [0, 1]) of the representations
COLOURS = {NONE: (0.0, 0.0, 0.0), VIS: (1.0, 0.55, 0.05), CONES: (0.15, 0.4, 1.0), SH: (0.2, 0.8, 0.25)}


def false_colour(tags: np.ndarray) -> np.ndarray:
    """(H, W) representation tags -> (H, W, 3) colours (see ``COLOURS``)."""
    out = np.zeros(tags.shape + (3,), np.float32)
    for t, c in COLOURS.items():
        out[tags == t] = c
    return out


def run_choice(scene, spec: str = "adaptive", width: int = 160, height: int = 90, frames: int = 24,
               viewers=None, seed: int = 0):
    """Run ``spec`` (an adaptive method) for ``frames`` frames on the scene's
    single-viewer rig; returns (tags (H, W), composed image (H, W, 3), method)."""
    m = methods.create(spec, scene, seed=seed)
    vs = viewers or views.single(scene)
    for f in range(frames):
        gbs = gbuffer.frame_gbuffers(scene, vs, f, width, height)
        d = m.render(FrameContext(f), gbs, NullTimer())
    tags = np.array(m.pixel_tags(m.requests, 0, gbs[0]), np.uint32).reshape(height, width)
    img = gbuffer.to_image(gbs[0], gbuffer.compose(gbs[0], d[0]))
    dr.sync_thread()
    return tags, img, m


def write_choice_image(path: Path, img: np.ndarray, tags: np.ndarray, exposure: float) -> None:
    """The render and the false-colour choice side by side (PNG)."""
    ldr = io.tonemap(img, exposure)
    fc = false_colour(tags)
    gap = np.ones((img.shape[0], 4, 3), np.float32)
    io.write_png(path, np.concatenate([ldr, gap, fc], axis=1))


def shares(tags: np.ndarray) -> dict:
    """Share of the valid pixels whose entry uses each representation."""
    valid = tags != NONE
    n = max(int(valid.sum()), 1)
    return {NAMES[t]: float((tags == t).sum()) / n for t in (VIS, CONES, SH)}


def choice_table(rows: list[dict], field: str) -> str:
    """Markdown: per scene variant, the share of active entries per
    representation and the pool memory of each (from the adaptive rows' stats)."""
    lines = [f"| scene | {field} | method | visibility % | cones % | sh % | switches (last frame) | "
             "visibility KB | cones KB | sh KB | memory MB |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "share_visibility" not in r:
            continue
        lines.append(f"| {r['scene']} | {r.get(field, '')} | {r.get('label', r['method'])} | "
                     f"{100 * r['share_visibility']:.1f} | {100 * r['share_cones']:.1f} | {100 * r['share_sh']:.1f} | "
                     f"{r.get('switches', 0):.0f} | {r['bytes_visibility'] / 1024:.1f} | "
                     f"{r['bytes_cones'] / 1024:.1f} | {r['bytes_sh'] / 1024:.1f} | {r.get('memory_mb', 0):.2f} |")
    return "\n".join(lines) + "\n"


def add_choice_section(opts, name: str, results: dict, field: str) -> dict:
    """Append the choice table to experiment ``name``'s ``results.md`` and write
    a false-colour image of the choice per scene variant
    (``images/SCENE_choice.png``), for the adaptive specs among the results'
    methods. Returns ``results``."""
    out_dir = Path(opts.out) / name
    c = results["config"]
    width, height, frames = c["width"], c["height"], c["frames"]
    specs = [s for s in results["config"].get("methods", []) if s.split(":")[0] == "adaptive"]
    if not specs:
        return results
    md_path = Path(out_dir) / "results.md"
    text = md_path.read_text() if md_path.exists() else ""
    text += ("\n## Representation chosen by `adaptive` (share of the entries active in the last frame)\n\n"
             + choice_table(results["rows"], field)
             + "\nFalse-colour images (`images/*_choice.png`, render | choice): orange visibility, blue cones, "
               "green SH.\n")
    names = [v[1] for v in results["config"].get("variants", [])]
    for s in each_scene(names):
        tags, img, _ = run_choice(s, specs[0], width, height, frames, seed=results["config"].get("seed", 0))
        stem = s.name.replace(":", "_").replace("=", "")
        write_choice_image(Path(out_dir) / "images" / f"{stem}_choice.png", img, tags, s.exposure)
        sh = shares(tags)
        text += (f"- `{s.name}`: pixels by representation: visibility {100 * sh['visibility']:.0f}%, "
                 f"cones {100 * sh['cones']:.0f}%, sh {100 * sh['sh']:.0f}%\n")
    io.write_text(md_path, text)
    return results
