"""The report of the osc-gi experiment (experiments/osc_gi.py): its Markdown tables, the time
per stage and the targets section. ``c`` is the experiment's module (its name)."""
from __future__ import annotations

from slc.run import experiment

SLIDES_1080P_MB = (300, 700)        # the slides' single-viewer memory at 1080p (GPU)
STAGES = ("requests", "allocate", "queue", "update", "shade", "direct")


def _columns(text: str) -> list:
    """``"key: header; ..."`` -> [(key, header), ...] (the tables' columns)."""
    return [tuple(x.strip() for x in c.split(":", 1)) for c in text.split(";")]


ROW_COLUMNS = _columns("scene: scene; group: group; setting: method; time_ms: t [ms]; cache_ms: cache; effect_ms: "
                       "effect; display_ms: display; flip: FLIP; psnr: PSNR; ssim: SSIM; pt_flip_equal_time: PT FLIP @ "
                       "equal t; flip_vs_pt_equal_time: FLIP / PT; primary_mb_min: primary MB min; primary_mb_max: "
                       "primary MB max; secondary_mb_min: secondary MB min; secondary_mb_max: secondary MB max; "
                       "memory_mb: memory [MB]")
MULTI_COLUMNS = _columns("scene: scene; setting: method; viewers: viewers; measured_overlap: measured overlap %; "
                         "time_ms: t [ms]; time_vs_one: t / 1 viewer; time_vs_one_range: range; compiled_after_warmup: "
                         "kernels after warm-up; entries: entries; entries_updated: entries updated; flip_viewer0: "
                         "FLIP viewer 0; secondary_cells: secondary cells; memory_mb: memory [MB]; "
                         "memory_per_viewer_mb: memory / viewer [MB]")
MEMORY_COLUMNS = _columns("scene: scene; resolution: resolution; entries: entries; primary_mb: primary MB; "
                          "secondary_mb: secondary MB in use; secondary_table_mb: secondary table MB; "
                          "estimate_1080p_mb: 1080p estimate MB (primary + secondary in use)")


def _stage_line(r, label) -> str:
    st, kk = r.get("stages_ms", {}), r.get("stages_kernel_ms", {})
    return f"- {label}: " + ", ".join(f"{k} {st.get(k, 0.0):.1f} / {kk.get(k, 0.0):.1f}" for k in STAGES) + "\n"


def markdown(c, res, names, cfg) -> str:
    """The results as Markdown: the single-viewer rows, the multi-viewer rows, the time per
    stage, memory against resolution, the update's sub-stages and the targets."""
    rows, multi, memory = res["rows"], res["multi"], res["memory"]
    md = (f"# {c.NAME}\n\n{cfg.width}x{cfg.height}, {cfg.frames} frames ({cfg.warmup} warm-up), one moving viewer; "
          f"quality on frames {cfg.evaluated()} against the reference of each method's output (full: {cfg.ref_spp}-"
          f"sample direct + {cfg.ref_spp}-path indirect; indirect: the indirect reference); times are medians on "
          f"a shared CPU (compare within this table only). Memory: primary = on-surface cache + payloads, "
          f"secondary = cells in use (the table is allocated up front: secondary_table_mb in results.json).\n\n"
          + (experiment.markdown_table(rows, ROW_COLUMNS) if rows else "(single-viewer runs skipped)") + "\n")
    if multi:
        md += "\n## Multi-viewer\n\n" + experiment.markdown_table(multi, MULTI_COLUMNS) + "\n"
        md += "\nPer stage (wall ms / of which kernel execution):\n\n"
        md += "".join(_stage_line(r, f"{r['scene']} {r['setting']}, {r['viewers']} viewers") for r in multi)
    st_rows = [r for r in rows if r["family"] in ("osc-gi", "pt", "sharc") and r["group"] in ("full", "indirect")]
    if st_rows:
        md += ("\n## Where the frame time goes (wall ms per stage / of which kernel execution; the rest is host "
               "time: Python tracing of the kernels, launches, syncs)\n\n")
        md += "".join(_stage_line(r, f"{r['scene']} {r['setting']}") for r in st_rows)
    if memory:
        md += "\n## Memory against resolution (one viewer, 3 frames)\n\n" + experiment.markdown_table(
            memory, MEMORY_COLUMNS) + "\n"
    for name, lp in res["laps"].items():
        md += (f"\n## Update sub-stages, {name} (ms per frame after warm-up, separate run with host syncs)\n\n"
               + ", ".join(f"{k} {x:.1f}" for k, x in lp.items()) + "\n")
    return md + "\n## Targets\n\n" + "".join(_targets(res, name) for name in names)


def _pt_ratio_text(x) -> str:
    q, lb = x.get("flip_vs_pt_equal_time"), x.get("flip_vs_pt_at_least")
    return f"{q:.2f}" if q else (f">= {lb:.2f} (slower than PT's slowest point)" if lb else "outside the PT range")


def _targets(res, name) -> str:
    """The scene's lines of the targets section: 16 viewers against one, osc-gi against PT at
    equal time, osc-gi against crc (indirect), memory at 1080p, secondary reuse."""
    rows, multi, memory = res["rows"], res["multi"], res["memory"]
    pick = lambda xs, **kv: next((x for x in xs if all(x.get(k) == v for k, v in kv.items())), None)  # noqa: E731
    r, ri = pick(rows, scene=name, setting="osc-gi"), pick(rows, scene=name, setting="osc-gi:output=indirect")
    crc, m16 = pick(rows, scene=name, setting="crc"), pick(multi, scene=name, viewers=16, setting="osc-gi")
    md = ""
    if m16:
        ov = m16["measured_overlap"] or 0
        md += (f"- {name}: 16 viewers at {ov:.0f}% measured overlap cost {m16['time_vs_one']:.2f}x one viewer "
               f"(median of {m16['repeats']} repetitions, {m16['time_vs_one_range']}; {m16['frames_timed']} timed "
               f"frames each; target <= 4 at 60-80% overlap{'' if 60 <= ov <= 80 else ': overlap outside it'})\n")
    if r is None:
        return md
    for x in rows:      # the other osc-gi rows (their FLIP / PT), then the rows timed again in turn
        if x["scene"] == name and x["group"] == "full" and x["family"] == "osc-gi" and x is not r:
            md += (f"- {name}, {x['setting']}: FLIP {x['flip']:.4f} at {x['time_ms']:.0f} ms; osc-gi / PT = "
                   f"{_pt_ratio_text(x)}\n")
    for x in (x for x in rows if x["scene"] == name and x.get("retimed_ms")):
        q, med = x.get("flip_vs_pt_retimed") or [], x.get("flip_vs_pt_retimed_median")
        md += (f"- {name}, {x['setting']}, timed again in turn: {x['time_ms']:.0f} -> "
               + ", ".join(f"{t:.0f}" for t in x["retimed_ms"]) + " ms" + ("; osc-gi / PT = " + ", ".join(
                   "-" if y is None else f"{y:.2f}" for y in q) + (f", median {med:.2f}" if med else "") if q else "")
               + "\n")
    ratio = r.get("flip_vs_pt_equal_time")
    md += (f"- {name}: FLIP {r['flip']:.4f} at {r['time_ms']:.0f} ms; PT at equal time "
           + (f"{r['pt_flip_equal_time']:.4f} -> osc-gi / PT = {ratio:.2f} (target <= 0.70)" if ratio else
              f"-> osc-gi / PT {_pt_ratio_text(r)} (target <= 0.70)") + "\n")
    if ri is not None and crc is not None:
        md += f"- {name}, indirect light: osc-gi FLIP {ri['flip']:.4f} vs crc {crc['flip']:.4f} (target: lower)\n"
    mem = [x for x in memory if x["scene"] == name]
    if mem and "estimate_1080p_mb" in mem[0]:
        md += (f"- {name}: memory per viewer at 1080p (linear in pixels from {mem[0]['resolution']}-"
               f"{mem[-1]['resolution']}): {mem[0]['estimate_1080p_mb']:.0f} MB + the secondary table "
               f"{mem[0]['secondary_table_mb']:.0f} MB (slides: {SLIDES_1080P_MB[0]}-{SLIDES_1080P_MB[1]} MB on GPU)\n")
    h = res["hists"].get(name)
    if h:
        md += f"- {name}: secondary reuse, mean {h['mean']:.1f} primary rays per cell (max {h['max']})\n"
    return md
