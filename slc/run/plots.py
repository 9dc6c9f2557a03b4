"""The plots every experiment shares: speed against error, time against viewers, a metric against a
setting's value. Points carry short names (what differs within a method family), the full settings
go to the legend or a key under the axes, labels are placed so that they overlap neither each other
nor the points, and a time axis is logarithmic where times span a decade or more."""
from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D
from matplotlib.transforms import Bbox

from slc.core import io

SHORT_NAME = 16        # longest point label drawn on a plot; longer settings get a number and a key line
KEY_WIDTH = 100        # characters per line of a plot's key (7 pt, the figure's width)


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (figures go to files; nothing is displayed)."""
    # matplotlib's backend is chosen when a figure is first made, not when slc is imported
    # (a notebook importing slc keeps its own backend)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def log_if_wide(ax, values, axis: str = "x", span: float = 10.0) -> None:
    """A log scale on ``axis`` when the positive ``values`` span ``span`` (a decade) or more."""
    v = [float(x) for x in values if x is not None and x > 0]
    if v and max(v) >= span * min(v):
        (ax.set_xscale if axis == "x" else ax.set_yscale)("log")


def place_labels(fig, ax, points, fontsize: int = 7) -> list:
    """Annotate ``points`` ((x, y, text) in data coordinates) without overlaps: each label takes
    the first of rings of offsets around its point where it stays inside the axes and covers
    no label placed before it, no other point and not the axes' legend (else the position
    covering least); labels set further off get a thin leader line. The figure's layout is
    computed first and then fixed, so the labels stay where they were checked."""
    fig.canvas.draw()
    fig.set_layout_engine("none")
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    px = ax.transData.transform(np.array([(x, y) for x, y, _ in points], float).reshape(-1, 2))
    marks = [Bbox.from_extents(u - 3, v - 3, u + 3, v + 3) for u, v in px]
    fixed = [ax.get_legend().get_window_extent(renderer)] if ax.get_legend() is not None else []
    offsets = [(d * dx, d * dy, ha, va) for d in (4, 10, 18, 28, 40, 55, 75)
               for dx, dy, ha, va in ((1, 1, "left", "bottom"), (1, -1, "left", "top"),
                                      (-1, 1, "right", "bottom"), (-1, -1, "right", "top"),
                                      (0, 1.5, "center", "bottom"), (0, -1.5, "center", "top"),
                                      (1.5, 0, "left", "center"), (-1.5, 0, "right", "center"))]

    def covered(bb, boxes):
        return sum(max(0.0, min(bb.x1, o.x1) - max(bb.x0, o.x0)) * max(0.0, min(bb.y1, o.y1) - max(bb.y0, o.y0))
                   for o in boxes)
    placed, texts = [], []
    scale = fig.dpi / 72.0                          # points -> pixels
    for i, (x, y, text) in enumerate(points):
        others = fixed + [m for j, m in enumerate(marks) if j != i]
        probe = ax.text(0, 0, text, fontsize=fontsize)
        w, h = (lambda bb: (bb.width, bb.height))(probe.get_window_extent(renderer))
        probe.remove()
        u, v = px[i]
        best = None
        for dx, dy, ha, va in offsets:
            x0 = u + dx * scale - {"left": 0.0, "center": w / 2, "right": w}[ha]
            y0 = v + dy * scale - {"bottom": 0.0, "center": h / 2, "top": h}[va]
            bb = Bbox.from_extents(x0 - 2, y0 - 2, x0 + w + 2, y0 + h + 2)      # a 2 px gap around the text
            inside = frame.x0 <= bb.x0 and bb.x1 <= frame.x1 and frame.y0 <= bb.y0 and bb.y1 <= frame.y1
            cost = 1e3 * covered(bb, placed) + covered(bb, others) + (0.0 if inside else 1e9)
            if best is None or cost < best[0]:
                best = (cost, bb, (dx, dy, ha, va))
            if cost == 0.0:
                break
        _, bb, (dx, dy, ha, va) = best
        far = abs(dx) > 4 or abs(dy) > 6          # a thin leader line to a label set further off
        texts.append(ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", ha=ha, va=va,
                                 fontsize=fontsize, arrowprops=dict(arrowstyle="-", lw=0.4, color="0.5",
                                                                    shrinkA=0, shrinkB=2) if far else None))
        placed.append(bb)
    return texts


def _options(r: dict) -> list[str]:
    """The ``key=value`` settings of a row's label (``method:key=value,...``)."""
    return [o for o in r.get("label", r["method"]).partition(":")[2].split(",") if o]


def shared_options(rows: list[dict]) -> list[str]:
    """The settings every one of ``rows`` has (in the first row's order); none for one row."""
    if len(rows) < 2:
        return []
    common = set.intersection(*(set(_options(r)) for r in rows))
    return [o for o in _options(rows[0]) if o in common]


def short_names(rows: list[dict], family_of) -> tuple[list[str], list[str]]:
    """Per row a short name for its point: its settings without those its whole family shares
    (those go in the legend, :func:`shared_options`), the family's name when none is left, a
    number when still longer than :data:`SHORT_NAME`; and the key lines ``N  full label`` of
    the numbered rows."""
    shared = {}
    for r in rows:
        shared.setdefault(family_of(r), []).append(r)
    shared = {f: set(shared_options(rs)) for f, rs in shared.items()}
    names, key = [], []
    for r in rows:
        label, fam = r.get("label", r["method"]), family_of(r)
        if label.startswith(fam + ":"):
            short = ",".join(o for o in _options(r) if o not in shared[fam]) or fam
        else:
            short = label
        if len(short) > SHORT_NAME:
            n = str(len(key) + 1)
            key.append(textwrap.fill(f"{n}  {label.replace(',', ', ')}", KEY_WIDTH, subsequent_indent="     ",
                                     break_on_hyphens=False, break_long_words=False))
            short = n
        names.append(short)
    return names, key


def _one_sweep(rows: list[dict]) -> bool:
    """Whether the rows' settings (``method:key=value,...``) all name the same keys: points of
    one sweep, worth a line; ablations that each change something else are left unjoined."""
    def keys(r):
        _, _, opts = r.get("label", r["method"]).partition(":")
        return frozenset(o.partition("=")[0] for o in opts.split(",") if o)
    return len({keys(r) for r in rows}) == 1


def speed_error_plot(path: Path, rows: list[dict], title: str, x="time_ms", y="flip") -> None:
    """Time per frame against FLIP, one point per row; rows of one method family (``family``,
    else the method) share a colour and are joined by a line in order of time. Points carry
    short names (:func:`short_names`); the full settings of numbered points are listed under
    the axes, whose width the key leaves alone. A family's points are joined by a line when
    they are one sweep (:func:`_one_sweep`). The time axis is logarithmic when the times
    span a decade or more."""
    plt = pyplot()
    rows = [r for r in rows if r.get(x) is not None and r.get(y) is not None]
    fam_of = lambda r: r.get("family", r["method"])  # noqa: E731
    fams: dict[str, list] = {}
    for r in rows:
        fams.setdefault(fam_of(r), []).append(r)
    ordered = [r for _, rs in sorted(fams.items()) for r in sorted(rs, key=lambda r: r[x])]
    names, key = short_names(ordered, fam_of)
    key_lines = sum(k.count("\n") + 1 for k in key)
    fig = plt.figure(figsize=(6.4, 4.2 + 0.15 * key_lines), layout="constrained")
    ax = fig.add_subplot()
    for fam, rs in sorted(fams.items()):
        rs = sorted(rs, key=lambda r: r[x])
        common = shared_options(rs)
        ax.plot([r[x] for r in rs], [r[y] for r in rs], "o-" if _one_sweep(rs) else "o", ms=4,
                label=textwrap.fill(fam + (f" ({', '.join(common)})" if common else ""), 36))
    log_if_wide(ax, [r[x] for r in rows])
    ax.set_xlabel("time per frame [ms]" + (" (log)" if ax.get_xscale() == "log" else ""))
    ax.set_ylabel("FLIP (lower is better)")
    ax.set_title(title, fontsize=10, wrap=True)
    ax.grid(alpha=0.3, which="both")
    ax.margins(0.12)
    if fams:
        ax.legend(fontsize=7, title="method", title_fontsize=7)
    if key:
        blank = [Line2D([], [], linestyle="none") for _ in key]
        fig.legend(blank, key, loc="outside lower left", fontsize=7, frameon=False, handlelength=0,
                   handletextpad=0, title="settings of the numbered points", title_fontsize=7,
                   alignment="left")
    place_labels(fig, ax, [(r[x], r[y], n) for r, n in zip(ordered, names)])
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def time_vs_viewers_plot(path: Path, rows: list[dict], title: str, group=("method",), x="viewers",
                         y="time_ms", ylabel="time per frame [ms]") -> None:
    """One line per group (e.g. method and overlap), ``y`` against ``x`` (log 2), ``y`` on a log
    axis when it spans a decade or more; points labelled with the measured overlap when rows
    carry it (:func:`place_labels`); the legend under the axes."""
    plt = pyplot()
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(g) for g in group), []).append(r)
    fig = plt.figure(figsize=(6.4, 4.4 + 0.18 * ((len(groups) + 2) // 3)), layout="constrained")
    ax = fig.add_subplot()
    marks = []
    for key, rs in sorted(groups.items(), key=lambda kv: str(kv[0])):
        rs = sorted(rs, key=lambda r: r[x])
        label = " ".join(f"{g}={k}" if g != "method" else str(k) for g, k in zip(group, key))
        ax.plot([r[x] for r in rs], [r[y] for r in rs], "o-", label=label, ms=4)
        marks += [(r[x], r[y], f"{r['measured_overlap']:.0f}%") for r in rs
                  if r.get("measured_overlap") is not None and r.get(x, 1) > 1]
    ax.set_xscale("log", base=2)
    log_if_wide(ax, [r.get(y) for r in rows], "y")
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel + (" (log)" if ax.get_yscale() == "log" else ""))
    ax.set_title(title, fontsize=10, wrap=True)
    ax.grid(alpha=0.3, which="both")
    ax.margins(0.1)
    if groups:
        fig.legend(loc="outside lower center", ncol=min(3, len(groups)), fontsize=7, frameon=False)
    place_labels(fig, ax, marks, fontsize=6)
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def metric_vs_value_plot(path: Path, rows: list[dict], field: str, title: str) -> None:
    """FLIP (left) and time (right, log when it spans a decade or more) against ``field``, one
    line per method setting; the settings in one legend under both axes."""
    plt = pyplot()
    groups: dict[str, list] = {}
    for r in rows:
        groups.setdefault(r.get("setting", r["method"]), []).append(r)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2 + 0.18 * ((len(groups) + 3) // 4)), layout="constrained")
    numeric = all(isinstance(r[field], (int, float)) for r in rows)
    order = sorted({r[field] for r in rows}, key=lambda v: (not numeric, v))
    for label, rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: order.index(r[field]))
        xs = [r[field] if numeric else order.index(r[field]) for r in rs]
        for ax, key in zip(axes, ("flip", "time_ms")):
            ax.plot(xs, [r.get(key) for r in rs], "o-", label=label, ms=4)
    log_if_wide(axes[1], [r.get("time_ms") for r in rows], "y")
    for ax, ylabel in zip(axes, ("FLIP (lower is better)", "time per frame [ms]"
                                 + (" (log)" if axes[1].get_yscale() == "log" else ""))):
        if not numeric:
            ax.set_xticks(range(len(order)), [str(v) for v in order])
        ax.set_xlabel(field)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    if groups:
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=min(4, len(groups)),
                   fontsize=7, frameon=False)
    fig.suptitle(title, fontsize=10)
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)
