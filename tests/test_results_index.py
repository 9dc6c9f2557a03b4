"""tools/results_index.py (the provenance lines, the index of docs/results and the README's table,
written by tools/run_experiments.sh) on small synthetic inputs, and the links from README.md and
docs/*.md into docs/results."""
import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("results_index", REPO / "tools" / "results_index.py")
ri = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ri)

RESULTS_MD = """# single-viewer

160x90, 24 frames (10 warm-up).

| scene | method | t [ms] | FLIP |
|---|---|---|---|
| atrium | rt48 | 30.28 | 0.1220 |
| atrium | slc | 14.57 | 0.1114 |

## Targets

| not | this |
|---|---|
| one | two |
"""

README = """# slc

Intro.

<!-- results:single-viewer -->
| scene | method | t [ms] | FLIP |
|---|---|---|---|
| atrium | old | 1.00 | 0.9 |
<!-- /results -->

After the table.
<!-- /results -->
"""


def test_first_table_takes_the_first_table_only():
    table = ri.first_table(RESULTS_MD)
    assert table[0] == "| scene | method | t [ms] | FLIP |"
    assert table[-1] == "| atrium | slc | 14.57 | 0.1114 |"
    assert len(table) == 4
    with pytest.raises(ValueError):
        ri.first_table("no table\n| a |\n")


def test_fill_readme_replaces_only_between_the_markers():
    out = ri.fill_readme(README, ri.first_table(RESULTS_MD))
    assert "| atrium | old |" not in out
    assert "| atrium | slc | 14.57 | 0.1114 |" in out
    assert out.startswith("# slc\n\nIntro.\n\n<!-- results:single-viewer -->\n| scene |")
    assert out.endswith("<!-- /results -->\n\nAfter the table.\n<!-- /results -->\n")
    assert ri.fill_readme(out, ri.first_table(RESULTS_MD)) == out      # idempotent
    with pytest.raises(ValueError):
        ri.fill_readme(README, ["| x |"], marker="overlap")


def test_stamp_then_index_round_trip(tmp_path):
    md = tmp_path / "overlap.md"
    md.write_text(RESULTS_MD)
    txt = tmp_path / "bench-rays.txt"
    txt.write_text("scene atrium\n")
    (tmp_path / "hand-written.md").write_text("# no provenance\n")
    kw = dict(date="2030-01-02 03:04 UTC", host="Test CPU, 2 cores", code="v1-2-gabc", load="1.0, 1.1, 1.2")
    ri.stamp(md, "slc run overlap --quick", 363.4, **kw)
    ri.stamp(txt, "slc bench rays ; slc bench rays --scene sponza", 95, **kw)
    assert md.read_text().endswith("\n\n" + RESULTS_MD)
    assert txt.read_text().splitlines()[1] == "scene atrium"
    fields = ri.parse_header(md.read_text().splitlines()[0])
    assert fields["command"] == "slc run overlap --quick"
    assert fields["wall time"] == "363 s" and fields["code"] == "v1-2-gabc"
    assert ri.parse_header(txt.read_text().splitlines()[0])["machine"] == "Test CPU, 2 cores"
    rows = ri.index_rows(tmp_path)
    assert [r["experiment"] for r in rows] == ["bench-rays", "hand-written", "overlap"]
    assert rows[1]["command"] == "-"
    page = ri.index_markdown(rows)
    assert "| overlap | `slc run overlap --quick` | 2030-01-02 03:04 UTC | Test CPU, 2 cores | v1-2-gabc " \
           "| 363 s | [overlap.md](overlap.md) |" in page


def test_jsonl_table():
    log = 'warming up\n{"views": 65536, "method": "megaviews", "wall_s": 16.5}\n' \
          '{"views": 65536, "method": "manylods", "wall_s": 70.4, "passes": 6}\n'
    out = ri.jsonl_table(log, "scale")
    assert out.splitlines()[2] == "| views | method | wall_s | passes |"
    assert out.splitlines()[4] == "| 65536 | megaviews | 16.5 | - |"
    with pytest.raises(ValueError):
        ri.jsonl_table("nothing\n", "t")


def test_results_links_resolve():
    """Every link from README.md, docs/*.md and the notebooks into docs/results names a file there."""
    files = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), *sorted((REPO / "notebooks").glob("*.ipynb"))]
    missing = []
    for f in files:
        for name in re.findall(r"results/([A-Za-z0-9_.-]+\.(?:md|txt|png))", f.read_text()):
            if not (REPO / "docs" / "results" / name).exists():
                missing.append(f"{f.name}: results/{name}")
    assert not missing, missing
