"""The suite's shared fixtures (tests/conftest.py) keep nothing alive that would change later
test files' kernels."""
import os
import subprocess
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

FIRST = '''
import builtins, weakref
def test_loads_a_scene(scene):
    s = scene("cornell")
    assert scene("cornell") is s                     # shared within the file
    builtins.slc_probe = weakref.ref(s)
'''

SECOND = '''
import builtins
def test_the_scene_of_the_file_before_is_gone():
    assert builtins.slc_probe() is None, "a scene of the previous test file is still alive"
'''


def test_scenes_of_a_file_are_released_when_it_ends(tmp_path):
    """A scene the ``scene`` fixture loaded for one file is freed before the next file runs (a
    live scene joins every later kernel's virtual calls)."""
    (tmp_path / "test_a_first.py").write_text(FIRST)
    (tmp_path / "test_b_second.py").write_text(SECOND)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                        "-p", "no:randomly", "-p", "conftest", "--rootdir", str(tmp_path),
                        str(tmp_path / "test_a_first.py"), str(tmp_path / "test_b_second.py")],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "2 passed" in r.stdout, r.stdout[-3000:]
