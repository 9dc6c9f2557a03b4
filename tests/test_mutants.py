"""tools/mutants.py: every fault still applies to the current source (its text occurs exactly once
in its file, its tests exist), without running the faults' tests; and the tool refuses a fault
that no longer applies."""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("mutants", ROOT / "tools" / "mutants.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod          # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def test_every_fault_applies_to_the_current_source():
    mutants = _tool()
    assert len(mutants.FAULTS) >= 8
    assert mutants.problems(ROOT) == []


def test_a_fault_that_no_longer_applies_stops_the_tool(tmp_path, capsys):
    mutants = _tool()
    f = mutants.FAULTS[0]
    (tmp_path / f.file).parent.mkdir(parents=True)
    (tmp_path / f.file).write_text(f.old + "\n" + f.old)           # twice
    moved = mutants.Fault("moved", f.file, "text that is not there", "x", f.tests, "a fault whose code moved")
    found = mutants.problems(tmp_path, [f, moved])
    assert any(p.startswith(f"{f.name}: its text occurs 2 times") for p in found), found
    assert any(p.startswith("moved: its text occurs 0 times") for p in found), found
    assert any("not found" in p for p in found)                     # the tests are not under tmp_path
    assert mutants.main(["no-such-fault"]) == 2
    assert "unknown fault 'no-such-fault'" in capsys.readouterr().err
