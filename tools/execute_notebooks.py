"""Execute the notebooks of ``notebooks/`` and store their outputs in the ``.ipynb`` files.

Usage (from the repository root):

    PYTHONPATH=. nice .venv/bin/python tools/execute_notebooks.py [NAME_OR_PATH ...]

Without arguments every ``notebooks/*.ipynb`` is run; arguments select notebooks by path or by a
part of the file name (``04`` or ``osc-gi``). Each notebook runs top to bottom in a ``python3``
kernel (nbclient) with the notebooks folder as its working folder and this checkout first on the
kernel's ``PYTHONPATH``, so that it imports this checkout's ``slc``. A notebook that raises is not
written and the tool exits with status 1.

The stored outputs are made reproducible, so that running unchanged code again gives a small diff:
execution counts numbered 1..n over the code cells, no per-cell ``metadata.execution`` timestamps,
consecutive prints to one stream kept as one output (however the kernel flushed them),
the kernel's ``language_info`` reduced to its name, file extension and MIME type, progress-bar
output on stderr (tqdm's carriage-return lines) dropped, and this machine's absolute paths (the
checkout, the home folder, the temp folder, the interpreter's prefix) in text outputs replaced by
``<repo>``, ``~``, ``<tmp>`` and ``<python>``.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
KERNEL = "python3"
TIMEOUT = 900                  # seconds per cell
KERNELSPEC = {"display_name": "Python 3", "language": "python", "name": KERNEL}
LANGUAGE_INFO = {"name": "python", "file_extension": ".py", "mimetype": "text/x-python"}
PROGRESS = re.compile(r"\r|\d+%\|")     # tqdm and similar progress bars redraw with '\r'


def path_replacements() -> list[tuple[str, str]]:
    """(absolute path, placeholder) pairs, longest path first."""
    pairs = {str(ROOT): "<repo>", str(Path(tempfile.gettempdir()).resolve()): "<tmp>",
             tempfile.gettempdir(): "<tmp>", sys.prefix: "<python>",
             str(Path(sys.prefix).resolve()): "<python>", str(Path.home()): "~"}
    return sorted(((p, r) for p, r in pairs.items() if len(p) > 1), key=lambda x: -len(x[0]))


def scrub_text(text: str, pairs) -> str:
    for p, r in pairs:
        text = text.replace(p, r)
    return text


def normalize(nb, pairs) -> None:
    """Strip what changes from run to run without a change of code (see the module docstring)."""
    count = 0
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
        if cell.cell_type != "code":
            continue
        count += 1
        cell.execution_count = count
        outputs = []
        for out in cell.outputs:
            if out.output_type == "stream":
                if out.name == "stderr" and PROGRESS.search(out.text):
                    continue
                out.text = scrub_text(out.text, pairs)
                last = outputs[-1] if outputs else None
                if last is not None and last.output_type == "stream" and last.name == out.name:
                    last.text += out.text          # one output per run of prints (flushes split them)
                    continue
            elif out.output_type in ("execute_result", "display_data"):
                if "execution_count" in out:
                    out.execution_count = count
                data = out.get("data", {})
                for mime in ("text/plain", "text/html", "text/markdown"):
                    if isinstance(data.get(mime), str):
                        data[mime] = scrub_text(data[mime], pairs)
            elif out.output_type == "error":
                out.traceback = [scrub_text(t, pairs) for t in out.traceback]
            outputs.append(out)
        cell.outputs = outputs
    nb.metadata["kernelspec"] = dict(KERNELSPEC)
    nb.metadata["language_info"] = dict(LANGUAGE_INFO)
    for key in ("widgets", "papermill"):
        nb.metadata.pop(key, None)


def execute(path: Path) -> float:
    """Run one notebook in place; returns the seconds it took. Raises CellExecutionError."""
    nb = nbformat.read(path, as_version=4)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                                       if p and Path(p).resolve() != ROOT])
    env["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"     # figures as image/png outputs
    env["TQDM_DISABLE"] = "1"
    client = NotebookClient(nb, timeout=TIMEOUT, kernel_name=KERNEL, record_timing=False,
                            resources={"metadata": {"path": str(path.parent)}})
    t0 = time.perf_counter()
    client.execute(env=env)        # the kernel's environment (passed on to start_kernel)
    seconds = time.perf_counter() - t0
    normalize(nb, path_replacements())
    nbformat.validate(nb)
    nbformat.write(nb, path)
    return seconds


def select(args: list[str]) -> list[Path]:
    every = sorted(NOTEBOOKS.glob("*.ipynb"))
    if not args:
        return every
    out = []
    for a in args:
        p = Path(a)
        hits = [p.resolve()] if p.suffix == ".ipynb" and p.exists() else [n for n in every if a in n.name]
        if not hits:
            raise SystemExit(f"no notebook matches '{a}' (notebooks: {', '.join(n.name for n in every)})")
        out += [h for h in hits if h not in out]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("notebooks", nargs="*", help="paths or parts of names (default: all of notebooks/)")
    args = ap.parse_args(argv)
    failed = []
    for path in select(args.notebooks):
        try:
            seconds = execute(path)
        except CellExecutionError as e:
            print(f"{path.name}: FAILED\n{e}", file=sys.stderr)
            failed.append(path.name)
            continue
        print(f"{path.name}: {seconds:.0f} s, {path.stat().st_size / 1024:.0f} KiB")
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
