"""The notebooks run top to bottom (their own asserts check the results), and the committed
notebooks carry their outputs (written by tools/execute_notebooks.py): every code cell run, at
least one image, no error, nothing of the machine that ran them."""
import base64
import importlib.util
import io
import json
import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def _executor():
    spec = importlib.util.spec_from_file_location("execute_notebooks", ROOT / "tools" / "execute_notebooks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_committed_notebook_spells_no_history_word(path):
    """No line of a committed notebook (its figures' base64 text included) holds a word of
    tools/execute_notebooks.py's HISTORY."""
    pat = _executor().HISTORY
    hits = [(i, m.group(0)) for i, line in enumerate(path.read_text().splitlines(), 1) for m in pat.finditer(line)]
    assert not hits, f"{path.name}: {hits[:5]} (run tools/execute_notebooks.py)"


def test_clean_png_keeps_the_image_and_drops_the_word():
    """A PNG whose base64 spells a HISTORY word comes back spelling none, decoding to the same pixels."""
    import matplotlib.image as mpimg
    import numpy as np
    mod = _executor()
    rng = np.random.default_rng(0)
    for seed in range(400):                      # find a small image whose encoding spells a word
        img = rng.random((24, 24, 3))
        buf = io.BytesIO()
        mpimg.imsave(buf, img, format="png")
        b64 = base64.b64encode(buf.getvalue()).decode("ascii")
        if mod.HISTORY.search(b64):
            break
    else:
        pytest.fail("no test image spelled a word")
    out = mod.clean_png(b64)
    assert not mod.HISTORY.search(out)
    a = mpimg.imread(io.BytesIO(base64.b64decode(b64)), format="png")
    b = mpimg.imread(io.BytesIO(base64.b64decode(out)), format="png")
    assert np.array_equal(a, b)
    assert mod.clean_png(out) == out                # a clean image is left as it is


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_committed_notebook_has_its_outputs(path):
    nb = json.loads(path.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    outputs = [o for c in code for o in c.get("outputs", [])]
    assert [c.get("execution_count") for c in code] == list(range(1, len(code) + 1)), \
        f"{path.name}: not executed top to bottom (run tools/execute_notebooks.py)"
    assert any("image/png" in o.get("data", {}) for o in outputs), f"{path.name}: no image output"
    errors = [o.get("ename") for o in outputs if o.get("output_type") == "error"]
    assert not errors, f"{path.name}: error outputs {errors}"
    assert not any("execution" in c.get("metadata", {}) for c in nb["cells"]), f"{path.name}: cell timestamps"
    text = json.dumps([o for o in outputs if o.get("output_type") == "stream"])
    assert str(ROOT) not in text and str(Path.home()) not in text, f"{path.name}: a local path in its outputs"
    assert path.stat().st_size < 1.5e6, f"{path.name}: {path.stat().st_size / 1e6:.1f} MB"


@pytest.mark.slow       # notebooks run in Jupyter kernels
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    # the kernel runs in notebooks/: this checkout's slc first on its path, not an installed one
    path_list = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path_list)}
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(path.parent)}}).execute(env=env)
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
