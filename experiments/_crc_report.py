"""The report of the crc experiment (experiments/crc.py): its Markdown tables and its
figures. ``c`` is the experiment's module (its constants)."""
from __future__ import annotations

import numpy as np

from slc.core import io
from slc.methods.crc.cache import CRCCache
from slc.reference.references import exposure_for
from slc.run import experiment, plots


def _f(v, fmt="{:.2f}"):
    return "-" if v is None else fmt.format(v)


def file_stem(name: str) -> str:
    """A scene name with its options (``village:sun=1``) as part of a file name."""
    return name.replace(":", "_").replace(",", "_")


# ---------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------

def markdown(c, rows, prof_rows, path_rows, sweep_rows, preset, names, term_rows=(), moving_rows=(),
             attribution_rows=()) -> str:
    """The results as Markdown: Table 1 (against Y3Co3Cg3), the same rows against RGB3 and the
    reference, the stage profile, Figs. 5 and 10, the error terms, the moving volume, where
    Y3Co1Cg1 differs, and the targets."""
    return (_table1(c, rows, preset) + _against(c, rows) + _profile(c, prof_rows) + _figs(path_rows, sweep_rows)
            + _terms(c, term_rows) + _moving(c, moving_rows) + _attribution(c, attribution_rows)
            + _targets(rows, prof_rows, preset, names, term_rows, moving_rows, attribution_rows))


def _table1(c, rows, preset) -> str:
    W, H = preset["width"], preset["height"]
    cols = [("scene", "scene"), ("bounces", "b"), ("variant", "variant"), ("visibility", "visibility"),
            ("occupancy", "occ."), ("encoding", "encoding"), ("chroma", "chroma"), ("coefficients", "coeffs"),
            ("occupancy_ratio", "occ. ratio"), ("time_ms", "t [ms]"), ("time_vs_rgb3", "t / RGB3"),
            ("time_vs_unoptimized", "t / unopt."), ("lab_rmse_final", "Lab RMSE final [%]"),
            ("pdiff_final", "pdiff final [%]"), ("lab_rmse_indirect", "Lab RMSE indirect [%]"),
            ("pdiff_indirect", "pdiff indirect [%]"), ("memory_mb", "memory [MB]")]
    md = (f"# {c.NAME}\n\n{W}x{H}, {preset['frames']} frames ({preset['warmup']} warm-up), grid resolution "
          f"{preset['resolution']}, the paper's defaults (RSM + Halton, march samples 10 / 5, depth stride 10 at "
          f"1 MPixel = {max(1, round(10 * (W * H / 1e6) ** 0.5))} here). t = median cache ms per frame through "
          f"the pipeline, configurations one after the other (load-sensitive; see the stage profile for "
          f"side-by-side ratios). The paper's Table 1 measures (Sec. 7) against the Y3Co3Cg3 cache of the same "
          f"sampling ('Y3Co3Cg3 vs Y3Co1Cg1'): CIE Lab RMSE (RMS over the frame's pixels of the CIE76 dE; "
          f"dE 1 = 1%) and pdiff (Yee's PerceptualDiff: percent of pixels visibly different), of the *final* "
          f"frame (ground-truth direct light + the cache's indirect light, textures, the scene's exposure) and "
          f"of the *indirect* light alone (exposure 0.8 / p99 of the reference's luminance). Variants: "
          f"`paths` = light-traced VPLs + PCG32, `dense` = one march sample per voxel, `stride10` = the literal "
          f"s = 10 at this frame size.\n\n" + experiment.markdown_table(rows, cols) + "\n")
    return md


def _against(c, rows) -> str:
    cols = [("scene", "scene"), ("bounces", "b"), ("variant", "variant"), ("occupancy", "occ."),
            ("encoding", "encoding"), ("chroma", "chroma"), ("lab_rmse_final_vs_rgb3", "Lab RMSE final [%]"),
            ("pdiff_final_vs_rgb3", "pdiff final [%]"), ("lab_rmse_indirect_vs_rgb3", "Lab RMSE indirect [%]"),
            ("pdiff_indirect_vs_rgb3", "pdiff indirect [%]"), ("de76_fraction_final", "dE > 2.3 final vs Y3Co3Cg3 [%]"),
            ("lab_rmse_final_vs_ref", "Lab RMSE final vs ref [%]"), ("pdiff_final_vs_ref", "pdiff final vs ref [%]"),
            ("flip", "FLIP final vs ref"), ("ssim", "SSIM final vs ref"),
            ("lab_rmse_indirect_vs_ref", "Lab RMSE indirect vs ref [%]")]
    return ("\n## Against RGB3 and against the reference\n\nThe same rows: the paper's measures against the RGB3 "
            "cache of the same sampling (the paper's text: 'with respect to the uncompressed linear space RGB "
            "values'; Y3Co3Cg3 is a linear transform of it), and the final frame against ground-truth direct "
            "light + the path-traced indirect reference (the indirect light alone against the indirect "
            "reference in the last column).\n\n" + experiment.markdown_table(rows, cols) + "\n")


def _profile(c, prof_rows) -> str:
    encs = [e for e in c.PROFILED if e != "rgb3"]
    stage_names = set(CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES)
    md = ("\n## Stage profile (encodings side by side)\n\nms per frame, minimum (median) over the profiled frames "
          f"after warm-up of {c.PROFILE_REPEATS} runs of each encoding, run in turn (A B, B A, ...; the same frames). "
           "*Coefficient stages* (work proportional to the coefficient count): bounce1_project (projection and "
           "accumulation of the first bounce), bounce2_project (secondary-bounce lookups of the previous volume "
           "+ projection: the propagation), blend, reconstruct. *Fixed stages*: occupancy, lights (light "
           "injection: RSM), bounce1_march and bounce2_march (visibility marching). *Total without lights*: the "
           "sum of the stages' minima but the RSM (the paper's GI time does not include rendering the RSM).\n\n")
    md += ("| scene | b | stage | RGB3 [ms] | " + " | ".join(f"{e.upper()} [ms] | {e.upper()} / RGB3" for e in encs)
           + " |\n|" + "---|" * (4 + 2 * len(encs)) + "\n")
    for r in prof_rows:
        cells = [r["scene"], str(r["bounces"]), f"**{r['stage']}**" if r["stage"] not in stage_names
                 else r["stage"], f"{r['rgb3_min']:.2f} ({r['rgb3_median']:.2f})"]
        for e in encs:
            cells += [f"{r[e + '_min']:.2f} ({r[e + '_median']:.2f})",
                      f"{r[e + '_vs_rgb3_min']:.2f} ({r[e + '_vs_rgb3_median']:.2f})"]
        md += "| " + " | ".join(cells) + " |\n"
    return md


def _figs(path_rows, sweep_rows) -> str:
    md = ""
    if path_rows:
        md += ("\n## Fig. 5: depth occupancy along the camera path (1 bounce, Y3Co1Cg1)\n\n"
               "| scene | position | frame | occupancy ratio | active cells | first bounce [ms] | total [ms] |\n"
               "|---|---|---|---|---|---|---|\n")
        for p in path_rows:
            md += (f"| {p['scene']} | {p['position'] + 1} | {p['frame']} | {p['occupancy_ratio']:.3f} | "
                   f"{p['active_cells']} | {p['bounce1_ms']:.2f} | {p['total_ms']:.2f} |\n")
    if sweep_rows:
        st = [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if any(k in r for r in sweep_rows)]
        md += ("\n## Fig. 10: stage ms against the CRC resolution (2 bounces, Y3Co1Cg1, min of 3 frames)\n\n"
               "| scene | resolution | cells | occupancy | " + " | ".join(st) + " | total | voxelize (once) |\n|"
               + "---|" * (6 + len(st)) + "\n")
        for r in sweep_rows:
            md += (f"| {r['scene']} | {r['resolution']} | {r['cells']} | {r['occupancy_ratio']:.3f} | "
                   + " | ".join(f"{r.get(k, 0.0):.2f}" for k in st) + f" | {r['total_ms']:.2f} | "
                   f"{r['voxelize_ms']:.0f} |\n")
    return md


def _terms(c, term_rows) -> str:
    t = experiment.load_part("crc_terms")
    md = ""
    if term_rows:
        md += ("\n## Error terms (Lab RMSE [%] of the composited image, last frame, each term alone)\n\n"
               "*encoding*: Y3Co1Cg1 against RGB3 of the same sampling (the paper's Table 1 comparison), "
               "offset (the paper's) / ratio decoding, at the default samples per cache point and at "
               f"{t.TERMS_SAMPLES}x (what stays is systematic). *noise*: RGB3 against RGB3 with another seed "
               "(two independent estimates). *fp16*: the RGB3 cache (high samples) stored as float16 against "
               "float32. *interpolation* (1 bounce): the grid cache against the estimator evaluated at each "
               "shaded point's own lookup point, both at the high sample count (includes that per-point "
               "estimate's own noise). *ref noise*: the indirect "
               "reference against one with 4x its paths. Against the reference: RGB3 at both sample counts; "
               "*unfiltered*: the estimator at the shaded points.\n\n"
               "| scene | b | encoding offset / ratio | same at high samples | noise (2 seeds) | fp16 | "
               "interpolation | ref noise | RGB3 vs ref / high samples / vs 4x ref | unfiltered vs ref | "
               "RGB3 (high) mean / ref (R, G, B) | indirect share |\n|" + "---|" * 12 + "\n")
        for t in term_rows:
            md += (f"| {t['scene']} | {t['bounces']} | {t['encoding_offset']:.2f} / {t['encoding_ratio']:.2f} | "
                   f"{t['encoding_offset_hi']:.2f} / {t['encoding_ratio_hi']:.2f} | {t['noise_two_seeds']:.2f} | "
                   f"{t['quantisation_fp16']:.4f} | {_f(t['interpolation'])} | {t['reference_noise']:.2f} | "
                   f"{t['rgb3_vs_ref']:.2f} / {t['rgb3_hi_vs_ref']:.2f} / {t['rgb3_vs_ref4']:.2f} | "
                   f"{_f(t['unfiltered_hi_vs_ref'])} | {', '.join(f'{v:.2f}' for v in t['rgb3_hi_mean_over_ref'])} | "
                   f"{t['indirect_share']:.2f} |\n")
    return md


def _moving(c, moving_rows) -> str:
    t = experiment.load_part("crc_terms")
    md = ""
    if moving_rows:
        md += ("\n## Moving volume (volume=camera) against the grid over the scene (Y3Co1Cg1)\n\n"
               f"A window of `window` cells per side of the same lattice, re-centred on the viewer in whole "
               f"cells (coefficients scrolled); the camera walks {t.MOVING['step']} path frames per rendered frame; "
               "both caches render the same frames, one run after the other. Times: median ms per frame after 2 "
               "warm-up frames (load-sensitive). Kernels: built or loaded by the "
               "moving cache after warm-up and after its first move (which builds the scroll kernel once). "
               "Lab RMSE at the last frame against the reference, over the image and "
               "over the pixels inside the window (outside it the moving cache gives no indirect light; the "
               "paper blends in an ambient colour there).\n\n"
               "| scene | b | window | cells (window / scene) | moves | kernels built | t scene [ms] | "
               "t camera [ms] | camera / scene | scroll [ms] | pixels inside | Lab RMSE vs ref: scene / camera | "
               "inside: scene / camera | camera vs scene inside |\n|" + "---|" * 14 + "\n")
        for r in moving_rows:
            md += (f"| {r['scene']} | {r['bounces']} | {r['window']} | {r['window_cells']} / {r['grid_cells']} | "
                   f"{r['moves']} | {r['kernels_built_after_warmup']} | {r['time_scene_ms']:.1f} | "
                   f"{r['time_camera_ms']:.1f} | {r['time_camera_vs_scene']:.2f} | {r['scroll_ms']:.2f} | "
                   f"{r['inside_fraction']:.2f} | {_f(r['lab_rmse_ref_scene'])} / {_f(r['lab_rmse_ref_camera'])} | "
                   f"{_f(r['lab_rmse_ref_scene_inside'])} / {_f(r['lab_rmse_ref_camera_inside'])} | "
                   f"{_f(r['camera_vs_scene_inside'])} |\n")
    return md


def _attribution(c, att_rows) -> str:
    t = experiment.load_part("crc_terms")
    if not att_rows:
        return ""
    md = ("\n## Where Y3Co1Cg1 differs from Y3Co3Cg3 (final frame, last evaluated frame)\n\n"
          "Lab RMSE over the surface pixels: without the background (pixels showing no surface; the protocol "
          "counts every pixel of the frame, as the paper's screenshots do). "
          f"Pixels *lit mostly indirectly*: surface pixels whose indirect light (Y3Co3Cg3) is at least "
          f"{t.INDIRECT_LIT:.0%} of their luminance (in the direct light's shadows); their share of the summed "
          f"squared CIE76 dE and the Lab RMSE over them and over the other surface pixels. Shapes: the "
          f"{t.TOP_SHAPES} with the largest share of the squared dE (share of dE^2 / share of the frame's pixels). "
          "Lights: each light's share of the indirect light and the final frame's Lab RMSE when only its "
          "indirect light is compressed (both caches re-run with the other lights off). Images: "
          "`protocol_SCENE_bN.png` (final Y3Co3Cg3 and Y3Co1Cg1, dE map, the pixels lit mostly indirectly, "
          "indirect light of both).\n\n"
          "| scene | b | Lab RMSE final [%] | surface pixels [%] | Lab RMSE over them [%] | lit mostly indirectly "
          "[% of pixels] | their share of dE^2 [%] | Lab RMSE there / elsewhere [%] | shapes | lights |\n|"
          + "---|" * 10 + "\n")
    for a in att_rows:
        shapes = "; ".join(f"{x['shape']} {100 * x['error_share']:.0f} / {100 * x['pixels']:.0f}" for x in a["shapes"])
        lights = "; ".join(f"{x['light']}: {100 * x['indirect_share']:.0f}% of the indirect light, "
                           f"{x['lab_rmse_final_alone']:.2f}%" for x in a["lights"])
        md += (f"| {a['scene']} | {a['bounces']} | {a['lab_rmse_final']:.2f} | {100 * a['surface_pixels']:.0f} | "
               f"{_f(a['lab_rmse_final_surface'])} | {100 * a['indirect_lit_pixels']:.1f} | {100 * a['indirect_lit_error_share']:.0f} | "
               f"{_f(a['lab_rmse_final_indirect_lit'])} / {_f(a['lab_rmse_final_direct_lit'])} | {shapes} | "
               f"{lights} |\n")
    return md


def _met(ok: bool) -> str:
    return "met" if ok else "**missed**"


def equal_fixed_ratio(p: dict) -> float:
    """Y3Co1Cg1 / RGB3 GI time (without the RSM; the stage profile's minima, ``p``: its rows of
    one scene and bounce count by stage) with the stages that do not depend on the encoding
    (occupancy, marches: the same kernels on the same data) at their mean over both
    encodings' runs, so that the load of a shared machine on them cancels."""
    f = 0.5 * sum(p["fixed stages"][f"{e}_min"] - p["lights"][f"{e}_min"] for e in ("rgb3", "y3co1cg1"))
    c = p["coefficient stages"]
    return (f + c["y3co1cg1_min"]) / max(f + c["rgb3_min"], 1e-9)


def _targets(rows, prof_rows, preset, names, term_rows, moving_rows, att_rows=()) -> str:
    md = ("\n## Targets\n\nFinal frame, Y3Co1Cg1 (the paper's offset decoding) against Y3Co3Cg3: Lab RMSE "
          "<= 0.6% at <= 0.75x RGB3's time (the stage profile's total without the RSM, the paper's GI time; "
          "minimum over frames, median in brackets).\n\n")
    for name in names:
        for nb in preset["bounces"]:
            g = [r for r in rows if r["scene"] == name and r["bounces"] == nb]
            std = [r for r in g if r["variant"] == "" and r["visibility"] == "march"]
            y1 = next(r for r in std if r["occupancy"] and r["encoding"] == "y3co1cg1" and r["chroma"] == "offset")
            y1r = next(r for r in std if r["chroma"] == "ratio")
            y2 = next(r for r in std if r["occupancy"] and r["encoding"] == "y3co2cg2")
            rgb = next(r for r in std if r["occupancy"] and r["encoding"] == "rgb3")
            off = next(r for r in std if not r["occupancy"])
            p = {r["stage"]: r for r in prof_rows if r["scene"] == name and r["bounces"] == nb}
            c, t, g = p["coefficient stages"], p["total"], p["total without lights"]
            ok_q, ok_t = y1["lab_rmse_final"] <= 0.6, g["y3co1cg1_vs_rgb3_min"] <= 0.75
            md += (f"- {name}, {nb} bounce(s): **final frame Lab RMSE {y1['lab_rmse_final']:.2f}%** "
                   f"({_met(ok_q)}), pdiff {y1['pdiff_final']:.2f}%; indirect light alone: Lab RMSE "
                   f"{y1['lab_rmse_indirect']:.2f}%, pdiff {y1['pdiff_indirect']:.2f}%; **time "
                   f"{g['y3co1cg1_vs_rgb3_min']:.2f}** ({g['y3co1cg1_vs_rgb3_median']:.2f}; {_met(ok_t)}; with the "
                   f"encoding-independent stages at their mean over both runs {equal_fixed_ratio(p):.2f}), total "
                   f"with the RSM {t['y3co1cg1_vs_rgb3_min']:.2f} ({t['y3co1cg1_vs_rgb3_median']:.2f}), coefficient "
                   f"stages {c['y3co1cg1_vs_rgb3_min']:.2f} ({c['y3co1cg1_vs_rgb3_median']:.2f}). Ratio decoding: "
                   f"final {y1r['lab_rmse_final']:.2f}%, indirect {y1r['lab_rmse_indirect']:.2f}%; Y3Co2Cg2: final "
                   f"{y2['lab_rmse_final']:.2f}%, indirect {y2['lab_rmse_indirect']:.2f}%. Against RGB3: final "
                   f"{y1['lab_rmse_final_vs_rgb3']:.2f}%, indirect {y1['lab_rmse_indirect_vs_rgb3']:.2f}%. Final frame "
                   f"against the reference: Y3Co1Cg1 {y1['lab_rmse_final_vs_ref']:.2f}%, RGB3 "
                   f"{rgb['lab_rmse_final_vs_ref']:.2f}%; occupancy ratio {rgb['occupancy_ratio']:.2f}, occupancy "
                   f"on/off time {rgb['time_ms'] / max(off['time_ms'], 1e-9):.2f}\n")
            a = next((x for x in att_rows if x["scene"] == name and x["bounces"] == nb), None)
            if a is not None and not ok_q:
                worst = max(a["lights"], key=lambda x: x["lab_rmse_final_alone"])
                md += (f"  - where: the pixels lit mostly indirectly ({100 * a['indirect_lit_pixels']:.1f}% of the "
                       f"frame) hold {100 * a['indirect_lit_error_share']:.0f}% of the squared dE (Lab RMSE "
                       f"{_f(a['lab_rmse_final_indirect_lit'])}% there, {_f(a['lab_rmse_final_direct_lit'])}% on "
                       f"the other surface pixels); most on {a['shapes'][0]['shape']} "
                       f"({100 * a['shapes'][0]['error_share']:.0f}%); light {worst['light']} alone "
                       f"{worst['lab_rmse_final_alone']:.2f}%\n")
            t = next((x for x in term_rows if x["scene"] == name and x["bounces"] == nb), None)
            if t is not None:
                md += (f"  - error terms (against RGB3): encoding (offset) {t['encoding_offset']:.2f}% "
                       f"({t['encoding_offset_hi']:.2f}% at {t['samples_hi']} samples: systematic), ratio "
                       f"{t['encoding_ratio']:.2f}% "
                       f"({t['encoding_ratio_hi']:.2f}%); noise {t['noise_two_seeds']:.2f}% between seeds; fp16 "
                       f"{t['quantisation_fp16']:.4f}%; interpolation {_f(t['interpolation'])}%; reference noise "
                       f"{t['reference_noise']:.2f}%; RGB3 vs reference {t['rgb3_vs_ref']:.2f}% "
                       f"({t['rgb3_hi_vs_ref']:.2f}% at {t['samples_hi']} samples)\n")
            mv = next((x for x in moving_rows if x["scene"] == name and x["bounces"] == nb), None)
            if mv is not None:
                md += (f"  - moving volume ({mv['window']}^3 of {mv['grid_cells']} cells): {mv['moves']} moves, "
                       f"{mv['kernels_built_after_warmup']} kernels built after warm-up, time "
                       f"{mv['time_camera_vs_scene']:.2f}x "
                       f"the scene grid's (scroll {mv['scroll_ms']:.2f} ms); Lab RMSE vs reference inside the window "
                       f"{_f(mv['lab_rmse_ref_camera_inside'])}% (scene grid {_f(mv['lab_rmse_ref_scene_inside'])}%), "
                       f"whole image {_f(mv['lab_rmse_ref_camera'])}% ({_f(mv['lab_rmse_ref_scene'])}%)\n")
    return md


# ---------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------

def _figure(ncols: int, size):
    plt = plots.pyplot()
    return plt.subplots(1, ncols, figsize=size)


def _save(path, fig, title: str, fontsize: int = 9) -> None:
    plt = plots.pyplot()
    fig.suptitle(title, fontsize=fontsize)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def plot(path, rows, title):
    """Table 1 as bars: cache time per configuration, Lab RMSE of the final frame against
    Y3Co3Cg3 and the reference."""
    fig, (a1, a2) = _figure(2, (9, 3.6))
    std = [r for r in rows if r["variant"] == "" and r["visibility"] == "march" and r["chroma"] == "offset"]
    a1.bar(range(len(std)), [r["time_ms"] for r in std], color="tab:blue")
    a1.set_xticks(range(len(std)), [r["encoding"].upper() + ("" if r["occupancy"] else "\nocc. off") for r in std],
                  fontsize=7)
    a1.set_ylabel("cache time per frame [ms] (median)")
    rs = [r for r in std if r["occupancy"] and r.get("lab_rmse_final") is not None]
    a2.bar(range(len(rs)), [r["lab_rmse_final"] for r in rs], color="tab:red", label="vs Y3Co3Cg3 cache")
    a2.plot(range(len(rs)), [r["lab_rmse_final_vs_ref"] for r in rs], "ko", label="vs reference")
    a2.set_xticks(range(len(rs)), [f"{r['encoding'].upper()}\n({r['coefficients']})" for r in rs], fontsize=7)
    a2.set_ylabel("Lab RMSE, final frame [%]")
    a2.legend(fontsize=7)
    _save(path, fig, title)


def _strip(path, panels, exposure, title):
    """Fig. 9: tone-mapped images side by side, titles with their errors."""
    fig, axes = _figure(len(panels), (2.6 * len(panels), 2.0))
    for ax, (label, img) in zip(axes, panels):
        ax.imshow(io.tonemap(img, exposure))
        ax.set_title(label, fontsize=7)
        ax.axis("off")
    _save(path, fig, title, 8)


def plot_path(path, pts, title):
    fig, a1 = _figure(1, (5, 3.2))
    x = [p["position"] + 1 for p in pts]
    a1.plot(x, [100 * p["occupancy_ratio"] for p in pts], "o-", color="tab:blue")
    a1.set_xlabel("viewer position along the camera path")
    a1.set_ylabel("depth occupancy [% of cells]", color="tab:blue")
    a2 = a1.twinx()
    a2.plot(x, [p["bounce1_ms"] for p in pts], "s--", color="tab:red")
    a2.set_ylabel("first bounce [ms]", color="tab:red")
    _save(path, fig, title)


def plot_sweep(path, rows, title):
    fig, ax = _figure(1, (5.5, 3.4))
    bottom = [0.0] * len(rows)
    for k in _stages(rows):
        v = [r.get(k, 0.0) for r in rows]
        ax.bar(range(len(rows)), v, bottom=bottom, label=k)
        bottom = [b + y for b, y in zip(bottom, v)]
    for i, r in enumerate(rows):
        ax.annotate(f"{100 * r['occupancy_ratio']:.0f}%", (i, bottom[i]), ha="center", fontsize=7,
                    textcoords="offset points", xytext=(0, 2))
    ax.set_xticks(list(range(len(rows))), [f"{r['resolution']}" for r in rows])
    ax.set_xlabel("CRC resolution (cells on the longest side); label: occupancy")
    ax.set_ylabel("ms per frame (min of 3)")
    ax.legend(fontsize=6)
    _save(path, fig, title)


def _stages(rows) -> list[str]:
    """The cache's stages that ``rows`` have, in the cache's order."""
    return [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if any(k in r for r in rows)]


def fig9(c, out, s, nb: int, group: list[dict], images: list[dict]) -> None:
    """The last evaluated frame's final images (reference, RGB3 and the equal-budget encodings)
    and their strip."""
    stem = out / "images" / f"{file_stem(s.name)}_b{nb}"
    last = max(images[0])
    io.write_hdr_and_png(stem.with_name(stem.name + "_reference"), images[0][last]["final_ref"], s.exposure)
    panels = [("reference (path traced)", images[0][last]["final_ref"])]
    for enc in ["rgb3"] + c.BUDGET:
        j = next(i for i, r in enumerate(group) if r["variant"] == "" and r["occupancy"]
                 and r["visibility"] == "march" and r["chroma"] == "offset" and r["encoding"] == enc)
        r, img = group[j], images[j][last]["final"]
        io.write_hdr_and_png(stem.with_name(f"{stem.name}_{enc}"), img, s.exposure)
        err = "" if enc == "rgb3" else f"\nvs RGB3 {r['lab_rmse_final_vs_rgb3']:.2f}%,"
        label = "Y2Co2Cg2 = RGB2" if enc == "y2co2cg2" else enc.upper()
        panels.append((f"{label} ({r['coefficients']}){err} vs ref {r['lab_rmse_final_vs_ref']:.2f}%", img))
    _strip(out / f"fig9_{file_stem(s.name)}_b{nb}.png", panels, s.exposure,
           f"Fig. 9: {s.name}, {nb} bounce(s): encodings at equal budget (Lab RMSE)")


def protocol_strip(out, s, nb: int, a: dict) -> None:
    """Where Y3Co1Cg1 differs (one attribution row): the final frames of Y3Co3Cg3 and
    Y3Co1Cg1, the CIE76 dE map, the pixels lit mostly by indirect light, and the indirect
    light of both (at the exposure of the indirect comparison)."""
    y3, y1 = a["_images"]["y3co3cg3"], a["_images"]["y3co1cg1"]
    ex_ind = exposure_for("indirect", s, y3["indirect"])
    fig, axes = _figure(6, (2.6 * 6, 2.1))
    panels = [("final Y3Co3Cg3", io.tonemap(y3["final"], s.exposure)),
              (f"final Y3Co1Cg1 ({a['lab_rmse_final']:.2f}%)", io.tonemap(y1["final"], s.exposure)), None,
              (f"lit mostly indirectly ({100 * a['indirect_lit_pixels']:.0f}%)", a["_indirect_lit"].astype(float)),
              ("indirect Y3Co3Cg3", io.tonemap(y3["indirect"], ex_ind)),
              ("indirect Y3Co1Cg1", io.tonemap(y1["indirect"], ex_ind))]
    for ax, p in zip(axes, panels):
        if p is None:
            top = max(float(np.percentile(a["_de_map"], 99.5)), 1e-6)
            ax.imshow(a["_de_map"], cmap="magma", vmin=0.0, vmax=top)
            ax.set_title(f"CIE76 dE, final (black 0, white {top:.1f})", fontsize=7)
        else:
            ax.imshow(p[1], cmap="gray" if p[1].ndim == 2 else None, vmin=0.0, vmax=1.0)
            ax.set_title(p[0], fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([])
    _save(out / f"protocol_{file_stem(s.name)}_b{nb}.png", fig,
          f"{s.name}, {nb} bounce(s): Y3Co1Cg1 against Y3Co3Cg3, final frame and indirect light", 8)
