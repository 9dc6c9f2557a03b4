"""The report of the crc experiment (experiments/crc.py): its Markdown tables and its
figures. ``c`` is the experiment's module (its constants)."""
from __future__ import annotations

from slc.run import experiment


def _f(v, fmt="{:.2f}"):
    return "-" if v is None else fmt.format(v)


# ---------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------

def markdown(c, rows, prof_rows, path_rows, sweep_rows, preset, names, term_rows=(), moving_rows=()) -> str:
    """The results as Markdown: Table 1, the stage profile, Figs. 5 and 10, the error terms,
    the moving volume and the targets."""
    return (_table1(c, rows, preset) + _profile(c, prof_rows) + _figs(path_rows, sweep_rows)
            + _terms(c, term_rows) + _moving(c, moving_rows) + _targets(rows, prof_rows, preset, names, term_rows,
                                                                        moving_rows))


def _table1(c, rows, preset) -> str:
    W, H = preset["width"], preset["height"]
    cols = [("scene", "scene"), ("bounces", "b"), ("variant", "variant"), ("visibility", "visibility"),
            ("occupancy", "occ."), ("encoding", "encoding"), ("chroma", "chroma"), ("coefficients", "coeffs"),
            ("occupancy_ratio", "occ. ratio"), ("time_ms", "t [ms]"), ("time_vs_rgb3", "t / RGB3"),
            ("time_vs_unoptimized", "t / unopt."), ("lab_rmse", "Lab RMSE vs RGB3 [%]"),
            ("pdiff", "pdiff vs RGB3 [%]"), ("lab_rmse_ref", "Lab RMSE vs ref [%]"), ("pdiff_ref", "pdiff vs ref [%]"),
            ("flip", "FLIP"), ("ssim", "SSIM"), ("memory_mb", "memory [MB]")]
    md = (f"# {c.NAME}\n\n{W}x{H}, {preset['frames']} frames ({preset['warmup']} warm-up), grid resolution "
          f"{preset['resolution']}, the paper's defaults (RSM + Halton, march samples 10 / 5, depth stride 10 at "
          f"1 MPixel = {max(1, round(10 * (W * H / 1e6) ** 0.5))} here). t = median cache ms per frame through "
          f"the pipeline, configurations one after the other (load-sensitive; see the stage profile for "
          f"side-by-side ratios). Lab RMSE and pdiff (Yee's PerceptualDiff) against the RGB3 cache of the same "
          f"sampling (the paper's Table 1 comparison) and against the reference (ground-truth direct + "
          f"{preset['ref_spp']} spp path-traced indirect, slc.reference.references; FLIP and SSIM too). Variants: "
          f"`paths` = light-traced VPLs + PCG32, `dense` = one march sample per voxel, `stride10` = the literal "
          f"s = 10 at this frame size.\n\n" + experiment.markdown_table(rows, cols) + "\n")
    return md


def _profile(c, prof_rows) -> str:
    encs = [e for e in c.PROFILED if e != "rgb3"]
    from slc.methods.crc.cache import CRCCache
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
        from slc.methods.crc.cache import CRCCache
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


def _targets(rows, prof_rows, preset, names, term_rows, moving_rows) -> str:
    md = "\n## Targets\n\n"
    for name in names:
        for nb in preset["bounces"]:
            g = [r for r in rows if r["scene"] == name and r["bounces"] == nb]
            std = [r for r in g if r["variant"] == "" and r["visibility"] == "march"]
            y1 = next(r for r in std if r["occupancy"] and r["encoding"] == "y3co1cg1" and r["chroma"] == "offset")
            y1r = next(r for r in std if r["chroma"] == "ratio")
            rgb = next(r for r in std if r["occupancy"] and r["encoding"] == "rgb3")
            off = next(r for r in std if not r["occupancy"])
            p = {r["stage"]: r for r in prof_rows if r["scene"] == name and r["bounces"] == nb}
            c, t, g = p["coefficient stages"], p["total"], p["total without lights"]
            md += (f"- {name}, {nb} bounce(s): Y3Co1Cg1 / RGB3 time on the coefficient stages "
                   f"{c['y3co1cg1_vs_rgb3_min']:.2f} (median {c['y3co1cg1_vs_rgb3_median']:.2f}; target <= 0.75), "
                   f"total {t['y3co1cg1_vs_rgb3_min']:.2f} (median {t['y3co1cg1_vs_rgb3_median']:.2f}), without "
                   f"the RSM {g['y3co1cg1_vs_rgb3_min']:.2f} ({g['y3co1cg1_vs_rgb3_median']:.2f}); "
                   f"Lab RMSE vs RGB3 {y1['lab_rmse']:.2f}% (ratio decoding {y1r['lab_rmse']:.2f}%), pdiff "
                   f"{y1['pdiff']:.2f}% ({y1r['pdiff']:.2f}%); Lab RMSE vs reference: Y3Co1Cg1 "
                   f"{y1['lab_rmse_ref']:.2f}%, RGB3 {rgb['lab_rmse_ref']:.2f}% (target < 1% on non-Cornell "
                   f"scenes); occupancy ratio {rgb['occupancy_ratio']:.2f}, occupancy on/off time "
                   f"{rgb['time_ms'] / max(off['time_ms'], 1e-9):.2f}\n")
            t = next((x for x in term_rows if x["scene"] == name and x["bounces"] == nb), None)
            if t is not None:
                md += (f"  - error terms: encoding (offset) {t['encoding_offset']:.2f}% "
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
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt.subplots(1, ncols, figsize=size)


def _save(path, fig, title: str, fontsize: int = 9) -> None:
    import matplotlib.pyplot as plt

    from slc.core import io
    fig.suptitle(title, fontsize=fontsize)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def plot(path, rows, title):
    """Table 1 as bars: cache time per configuration, Lab RMSE against RGB3 and the reference."""
    fig, (a1, a2) = _figure(2, (9, 3.6))
    std = [r for r in rows if r["variant"] == "" and r["visibility"] == "march" and r["chroma"] == "offset"]
    a1.bar(range(len(std)), [r["time_ms"] for r in std], color="tab:blue")
    a1.set_xticks(range(len(std)), [r["encoding"].upper() + ("" if r["occupancy"] else "\nocc. off") for r in std],
                  fontsize=7)
    a1.set_ylabel("cache time per frame [ms] (median)")
    rs = [r for r in std if r["occupancy"] and r.get("lab_rmse") is not None]
    a2.bar(range(len(rs)), [r["lab_rmse"] for r in rs], color="tab:red", label="vs RGB3 cache")
    a2.plot(range(len(rs)), [r["lab_rmse_ref"] for r in rs], "ko", label="vs reference")
    a2.set_xticks(range(len(rs)), [f"{r['encoding'].upper()}\n({r['coefficients']})" for r in rs], fontsize=7)
    a2.set_ylabel("Lab RMSE [%]")
    a2.legend(fontsize=7)
    _save(path, fig, title)


def _strip(path, panels, exposure, title):
    """Fig. 9: tone-mapped images side by side, titles with their errors."""
    from slc.core import io
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
    from slc.methods.crc.cache import CRCCache
    return [k for k in CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES if any(k in r for r in rows)]


def fig9(c, out, s, nb: int, group: list[dict], finals: list[dict]) -> None:
    """The last evaluated frame's images (reference, RGB3 and the equal-budget encodings) and
    their strip."""
    from slc.core import io
    stem = out / "images" / f"{s.name}_b{nb}"
    last = max(finals[0])
    io.write_hdr_and_png(stem.with_name(stem.name + "_reference"), finals[0][last][1], s.exposure)
    panels = [("reference (path traced)", finals[0][last][1])]
    for enc in ["rgb3"] + c.BUDGET:
        j = next(i for i, r in enumerate(group) if r["variant"] == "" and r["occupancy"]
                 and r["visibility"] == "march" and r["chroma"] == "offset" and r["encoding"] == enc)
        r, img = group[j], finals[j][last][0]
        io.write_hdr_and_png(stem.with_name(f"{stem.name}_{enc}"), img, s.exposure)
        err = "" if enc == "rgb3" else f"\nvs RGB3 {r['lab_rmse']:.2f}%,"
        label = "Y2Co2Cg2 = RGB2" if enc == "y2co2cg2" else enc.upper()
        panels.append((f"{label} ({r['coefficients']}){err} vs ref {r['lab_rmse_ref']:.2f}%", img))
    _strip(out / f"fig9_{s.name}_b{nb}.png", panels, s.exposure,
           f"Fig. 9: {s.name}, {nb} bounce(s): encodings at equal budget (Lab RMSE)")
