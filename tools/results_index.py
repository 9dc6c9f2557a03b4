"""The published results' bookkeeping, called by ``tools/run_experiments.sh``.

Usage (from the repository root):

    python tools/results_index.py stamp FILE --command CMD --wall SECONDS
    python tools/results_index.py jsonl-table LOG TITLE > FILE.md
    python tools/results_index.py index DIR
    python tools/results_index.py fill-readme README.md RESULTS.md [--marker single-viewer]

``stamp`` writes a provenance line at the top of a result file: the command, the date (UTC), the
machine (CPU model and cores), the code version (:func:`code_version`), the wall time
and the load average at the end of the run. Markdown files get it as an italic line, text files as a
``#`` comment; both read ``key: value`` fields split by `` · ``.

``index`` reads the provenance line of every ``*.md`` / ``*.txt`` file in DIR (``README.md``
excepted) and writes ``DIR/README.md``: one row per file with its experiment, command, date,
machine, code version and wall time. A file without a provenance line is listed with ``-`` fields.

``fill-readme`` copies the first Markdown table of RESULTS.md (the single-viewer quick run's
``results.md``) between the README's markers ``<!-- results:MARKER -->`` and ``<!-- /results -->``.

``jsonl-table`` turns the JSON lines a tool prints (``tools/megaviews_scale.py``) into a Markdown
table, one column per key in order of first appearance; other lines of LOG are ignored.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

SEP = " · "
FIELDS = ("command", "date", "machine", "code", "wall time")
CACHE_NOTE = "first run on an empty kernel cache (HOME a new empty folder; reference cache kept)"
REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- provenance

def machine() -> str:
    """CPU model and logical core count, e.g. ``Intel(R) Xeon(R) Processor, 2 cores``."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


def code_version(repo: Path = REPO) -> str:
    """The checkout's commit (``git describe --always --tags``), ``-dirty`` when a file outside
    the published results (``docs/results``, ``README.md``: what the run itself writes) differs
    from it; ``unknown`` outside git."""
    try:
        out = subprocess.run(["git", "-C", str(repo), "describe", "--always", "--tags"],
                             capture_output=True, text=True, check=True)
        changed = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no", "--",
                                  ".", ":!docs/results", ":!README.md"], capture_output=True, text=True, check=True)
        version = out.stdout.strip() or "unknown"
        return version + ("-dirty" if changed.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def provenance(command: str, wall_s: float, *, date: str | None = None, host: str | None = None,
               code: str | None = None, load: str | None = None) -> str:
    """The provenance fields joined by `` · `` (without the Markdown or comment marks)."""
    if date is None:
        date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    if load is None:
        load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    parts = [f"command: `{command}`", f"date: {date}", f"machine: {host or machine()}",
             f"code: {code or code_version()}", f"wall time: {wall_s:.0f} s",
             f"load average (1, 5, 15 min) at the end: {load}", CACHE_NOTE]
    return SEP.join(parts)


def header_line(path: Path, fields: str) -> str:
    """The first line of ``path`` carrying ``fields``: italic in Markdown, a comment elsewhere."""
    return f"*{fields}*" if path.suffix == ".md" else f"# {fields}"


def stamp(path: Path, command: str, wall_s: float, **kw) -> None:
    """Write the provenance line above the file's text (a Markdown file gets a blank line after it)."""
    text = path.read_text()
    line = header_line(path, provenance(command, wall_s, **kw))
    path.write_text(line + ("\n\n" if path.suffix == ".md" else "\n") + text)


def parse_header(line: str) -> dict[str, str] | None:
    """The fields of a provenance line, or None when ``line`` is not one."""
    body = line.strip()
    if body.startswith("# "):
        body = body[2:]
    elif body.startswith("*") and body.endswith("*"):
        body = body[1:-1]
    else:
        return None
    fields = {}
    for part in body.split(SEP):
        key, sep, value = part.partition(": ")
        if sep:
            fields[key.strip()] = value.strip()
    if "command" not in fields:
        return None
    fields["command"] = fields["command"].strip("`")
    return fields


# ---------------------------------------------------------------- the index

INDEX_HEAD = """# Results

Every file here is written by one command, each experiment a first run on an empty Dr.Jit kernel
cache (`HOME` pointed at a new empty folder; the reference cache `SLC_CACHE` kept):

```sh
tools/run_experiments.sh docs/results            # all of them, quick presets and the distributed full preset (about 2 hours on 2 cores)
tools/run_experiments.sh docs/results --only crc # a subset, by the names in the first column
```

The experiments run their `--quick` presets; the full presets render 4 s of camera motion per
sequence at 320x180 and take hours on 2 cores (`slc run NAME` without `--quick`). Each file's first
line states its command, date, machine, code version and wall time; this table repeats them.
Times are wall-clock on the machine named: compare ratios within one file, not milliseconds
across files or machines.
"""


def index_rows(folder: Path) -> list[dict[str, str]]:
    """One row per result file in ``folder`` (README.md excepted), sorted by file name."""
    rows = []
    for path in sorted(folder.iterdir()):
        if path.suffix not in (".md", ".txt") or path.name == "README.md":
            continue
        with path.open() as f:
            first = f.readline()
        fields = parse_header(first) or {}
        rows.append({"experiment": path.stem, "file": path.name,
                     **{k: fields.get(k, "-") for k in FIELDS}})
    return rows


def index_markdown(rows: list[dict[str, str]]) -> str:
    """The index page: the head text and one table row per result file."""
    lines = [INDEX_HEAD, "| experiment | command | date | machine | code version | wall time | file |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        cmd = f"`{r['command']}`" if r["command"] != "-" else "-"
        lines.append(f"| {r['experiment']} | {cmd} | {r['date']} | {r['machine']} | {r['code']} "
                     f"| {r['wall time']} | [{r['file']}]({r['file']}) |")
    walls = [float(r["wall time"].split()[0]) for r in rows if r["wall time"].endswith(" s")]
    dates = sorted(r["date"] for r in rows if r["date"] != "-")
    if walls:
        lines.append(f"\nThe whole run: {sum(walls) / 60:.0f} min of wall time over {len(walls)} files"
                     + (f", {dates[0]} to {dates[-1]}" if dates else "") + ".")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- the README's table

def first_table(markdown: str) -> list[str]:
    """The lines of the first Markdown table (a header row followed by a ``|---|`` row)."""
    lines = markdown.splitlines()
    for i in range(len(lines) - 1):
        if lines[i].startswith("|") and re.match(r"^\|(\s*:?-+:?\s*\|)+\s*$", lines[i + 1]):
            end = i
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            return lines[i:end]
    raise ValueError("no Markdown table found")


def fill_readme(readme: str, table: list[str], marker: str = "single-viewer") -> str:
    """``readme`` with the lines between ``<!-- results:MARKER -->`` and the next
    ``<!-- /results -->`` replaced by ``table``."""
    start, end = f"<!-- results:{marker} -->", "<!-- /results -->"
    i = readme.find(start)
    if i < 0:
        raise ValueError(f"marker {start} not found")
    j = readme.find(end, i)
    if j < 0:
        raise ValueError(f"marker {end} not found after {start}")
    return readme[:i + len(start)] + "\n" + "\n".join(table) + "\n" + readme[j:]


def jsonl_table(text: str, title: str) -> str:
    """A Markdown table of the JSON-object lines of ``text`` (other lines ignored)."""
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if not rows:
        raise ValueError("no JSON lines found")
    keys = list(dict.fromkeys(k for r in rows for k in r))
    out = [f"# {title}", "", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(str(r.get(k, "-")) for k in keys) + " |" for r in rows]
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------- command line

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("stamp", help="write the provenance line at the top of FILE")
    s.add_argument("file", type=Path)
    s.add_argument("--command", required=True, help="the command that wrote FILE, as a user types it")
    s.add_argument("--wall", type=float, required=True, help="its wall time in seconds")
    j = sub.add_parser("jsonl-table", help="JSON lines of LOG as a Markdown table on stdout")
    j.add_argument("log", type=Path)
    j.add_argument("title")
    i = sub.add_parser("index", help="write DIR/README.md from the result files' first lines")
    i.add_argument("folder", type=Path)
    f = sub.add_parser("fill-readme", help="copy RESULTS's first table between README's markers")
    f.add_argument("readme", type=Path)
    f.add_argument("results", type=Path)
    f.add_argument("--marker", default="single-viewer", help="the X of <!-- results:X --> (default single-viewer)")
    a = p.parse_args(argv)
    try:
        if a.cmd == "stamp":
            stamp(a.file, a.command, a.wall)
        elif a.cmd == "jsonl-table":
            sys.stdout.write(jsonl_table(a.log.read_text(), a.title))
        elif a.cmd == "index":
            (a.folder / "README.md").write_text(index_markdown(index_rows(a.folder)))
        else:
            a.readme.write_text(fill_readme(a.readme.read_text(), first_table(a.results.read_text()), a.marker))
    except (OSError, ValueError) as e:
        print(f"results_index: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
