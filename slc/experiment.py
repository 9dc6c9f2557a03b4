"""Shared plumbing of the experiment scripts in ``experiments/``.

An experiment script defines ``NAME``, ``add_arguments(parser)`` (optional)
and ``run(opts) -> dict`` returning the ``results.json`` object; it is run
alone (``python experiments/single_viewer.py --quick``) or through
``slc run single-viewer --quick``. This module finds the scripts, writes
``results.json`` / ``results.md`` atomically (a failed run leaves no partial
results), renders the Markdown table and draws the speed-against-error
plots.
"""
from __future__ import annotations

import importlib.util
import math
import time
from pathlib import Path

from . import io
from .backend import env_info
from .scenes import REPO_ROOT

EXPERIMENTS_DIR = REPO_ROOT / "experiments"


class ExperimentError(ValueError):
    """Unknown experiment or bad experiment options (one-line message)."""


def names() -> list[str]:
    if not EXPERIMENTS_DIR.is_dir():
        return []
    return sorted(p.stem.replace("_", "-") for p in EXPERIMENTS_DIR.glob("*.py") if not p.stem.startswith("_"))


def load(name: str):
    path = EXPERIMENTS_DIR / f"{name.replace('-', '_')}.py"
    if not path.exists():
        raise ExperimentError(f"unknown experiment '{name}' (available: {', '.join(names())})")
    spec = importlib.util.spec_from_file_location(f"slc_experiment_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def results_object(name: str, config: dict, rows: list[dict]) -> dict:
    return {"experiment": name, "config": config, "env": env_info(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "rows": rows}


def _fmt(v, nd=3):
    if isinstance(v, float):
        if math.isinf(v):
            return "inf"
        if math.isnan(v):
            return "-"
        return f"{v:.{nd}f}" if abs(v) < 1e4 else f"{v:.3g}"
    return str(v)


DEFAULT_COLUMNS = [("scene", "scene"), ("method", "method"), ("viewers", "viewers"),
                   ("time_ms", "t [ms]"), ("flip", "FLIP"), ("psnr", "PSNR"), ("ssim", "SSIM"),
                   ("memory_mb", "memory [MB]")]


def markdown_table(rows: list[dict], columns=None) -> str:
    columns = columns or DEFAULT_COLUMNS
    cols = [(k, h) for k, h in columns if any(k in r for r in rows)]
    nd = {"time_ms": 2, "flip": 4, "psnr": 2, "ssim": 4, "memory_mb": 3}
    out = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        out.append("| " + " | ".join(_fmt(r.get(k, "-"), nd.get(k, 3)) for k, _ in cols) + " |")
    return "\n".join(out)


def write_results(out_dir: Path, results: dict, markdown: str) -> None:
    """``results.json`` and ``results.md``, each written atomically."""
    out_dir.mkdir(parents=True, exist_ok=True)
    io.write_json(out_dir / "results.json", results)
    io.write_text(out_dir / "results.md", markdown)


def speed_error_plot(path: Path, rows: list[dict], title: str, x="time_ms", y="flip") -> None:
    """Time per frame against FLIP, one point per row, labelled by method
    (and setting); rows of one method family are joined by a line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.5, 4))
    fams: dict[str, list] = {}
    for r in rows:
        if r.get(x) is None or r.get(y) is None:
            continue
        fams.setdefault(r.get("family", r["method"]), []).append(r)
    for fam, rs in sorted(fams.items()):
        rs = sorted(rs, key=lambda r: r[x])
        ax.plot([r[x] for r in rs], [r[y] for r in rs], "o-", label=fam)
        for r in rs:
            ax.annotate(r.get("label", r["method"]), (r[x], r[y]), fontsize=7,
                        textcoords="offset points", xytext=(3, 3))
    ax.set_xlabel("time per frame [ms]")
    ax.set_ylabel("FLIP (lower is better)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    io._atomic(path, lambda p: fig.savefig(p, dpi=120, format="png"))
    plt.close(fig)
