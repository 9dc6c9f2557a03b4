"""``slc bench ab``: two settings timed in turn in one process, run through click's CliRunner
at a tiny size (2 frames, 16x9)."""
import json

import pytest
from click.testing import CliRunner

from slc.run import cli


def test_bench_ab_reports_both_settings(tmp_path):
    out = tmp_path / "ab.json"
    r = CliRunner().invoke(cli.cli, ["bench", "ab", "rt4", "rt8", "--scene", "cornell", "--res", "16x9",
                                     "--frames", "2", "--repeat", "2", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "B / A time" in r.output and "images: differ" in r.output
    (res,) = json.loads(out.read_text())
    a, b = res["settings"]
    assert (a["setting"], b["setting"]) == ("rt4", "rt8")
    assert len(res["ratios"]) == 2 and all(x > 0 for x in res["ratios"])
    for x in (a, b):
        assert len(x["times_ms"]) == 2 and x["time_ms"] > 0
        assert 0 < x["metrics"]["flip"] < 1
        assert len(set(x["md5"])) == 1, "same seed and settings must give the same image in every repetition"
    assert a["md5"][0] != b["md5"][0]
    assert b["metrics"]["flip"] < a["metrics"]["flip"]      # 8 light samples against 4


@pytest.mark.parametrize("args, words", [(["rt4", "nosuchmethod"], "unknown method"),
                                         (["rt4", "rt8", "--frames", "2", "--warmup", "2"], "--warmup")])
def test_bench_ab_bad_input(args, words, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["bench", "ab", *args, "--res", "16x9"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slc: error:") and words in err[0]


@pytest.mark.parametrize("args, words", [
    (["update", "--method", "rt4"], "no cone update"),
    (["update", "--repeats", "0"], "--repeats"),
    (["update", "--frames", "5", "--warmup", "5"], "--warmup"),
    (["update", "--warmup", "-1"], "--warmup"),
    (["rays", "--repeats", "0"], "--repeats"),
    (["rays", "--n", "0"], "--n")])
def test_bench_bad_input(args, words, capsys):
    """Bad settings of `slc bench update` and `slc bench rays` stop with one line before any frame."""
    with pytest.raises(SystemExit) as e:
        cli.main(["bench", *args, "--scene", "cornell", "--res", "16x9"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slc: error:") and words in err[0]
