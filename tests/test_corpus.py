"""The corpus experiment's table (experiments/corpus.py): adaptive against the best rival per
scene, from rows; a bad scene file stops it with one line before anything is written."""
import pytest

from helpers import slc_cli
from test_cli import _one_line_error

from experiments.corpus import summary_table, versus_rivals


def _row(scene, label, flip, t, psnr):
    return {"scene": scene, "label": label, "method": label.split(":")[0], "flip": flip, "time_ms": t,
            "psnr": psnr}


def test_versus_rivals_picks_the_lowest_rival_flip():
    rows = [_row("a", "rt48", 0.10, 100.0, 20.0), _row("a", "restir", 0.08, 50.0, 19.0),
            _row("a", "slc", 0.09, 40.0, 22.0), _row("a", "adaptive", 0.06, 30.0, 21.8),
            _row("a", "adaptive:force=cones", 0.05, 30.0, 25.0),          # not a rival
            _row("b", "slc", 0.02, 10.0, 30.0)]                            # no adaptive row: no summary
    s = versus_rivals(rows)
    assert len(s) == 1 and s[0]["best_rival"] == "restir"
    assert s[0]["flip_vs_best_rival"] == pytest.approx(0.06 / 0.08)
    assert s[0]["time_vs_rt48"] == pytest.approx(0.3)
    assert s[0]["psnr_minus_slc"] == pytest.approx(-0.2)
    assert rows[1]["time_vs_rt48"] == pytest.approx(0.5)
    assert "| a | restir | 0.0800 | 0.0600 | 0.75x | 0.30x | -0.20 |" in summary_table(s)


def test_bad_scene_file_is_one_line(tmp_path):
    out = tmp_path / "out"
    r = slc_cli(["run", "corpus", "--quick", "--scene", str(tmp_path / "missing.xml"), "--out", str(out)])
    _one_line_error(r, "not found", "missing.xml")
    assert not (out / "corpus" / "results.json").exists()
