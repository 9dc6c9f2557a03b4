"""Execute the notebooks of ``notebooks/`` and store their outputs in the ``.ipynb`` files.

Usage (from the repository root):

    PYTHONPATH=. nice .venv/bin/python tools/execute_notebooks.py [NAME_OR_PATH ...]

Without arguments every ``notebooks/*.ipynb`` is run; arguments select notebooks by path or by a
part of the file name (``04`` or ``osc-gi``). Each notebook runs top to bottom in a ``python3``
kernel (nbclient) with the notebooks folder as its working folder and this checkout first on the
kernel's ``PYTHONPATH``, so that it imports this checkout's ``slc``. A notebook that raises is not
written and the tool exits with status 1.

The stored outputs are made reproducible, so that running unchanged code again gives a small diff
(and a figure whose base64 text spells a word of ``HISTORY`` by chance is compressed again until
it spells none, see ``clean_png``):
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
# Words that would speak of how the project was made (its history belongs to git), searched in the
# committed notebooks by tests/test_notebooks.py. A figure's base64 text can spell one by chance
# (about two "ovl" + digit in 400 KB): clean_png compresses such an image again.
# (each word with one letter in brackets, so that a search for the words does not find this line)
HISTORY = re.compile(r"s[e]ssion|h[e]lper|l[e]ad|a[g]ent|\bg[i][0-9]+\b|o[v]l[0-9]|m[e]et[0-9]", re.IGNORECASE)


def _chunks(png: bytes):
    """(type, data) of each chunk of a PNG."""
    import struct
    at, out = 8, []
    while at < len(png):
        n, = struct.unpack(">I", png[at:at + 4])
        out.append((png[at + 4:at + 8], png[at + 8:at + 8 + n]))
        at += 12 + n
    return out


def _png(chunks) -> bytes:
    import binascii
    import struct
    body = b"".join(struct.pack(">I", len(d)) + t + d + struct.pack(">I", binascii.crc32(t + d) & 0xFFFFFFFF)
                    for t, d in chunks)
    return b"\x89PNG\r\n\x1a\n" + body


def clean_png(b64: str) -> str:
    """The PNG ``b64`` (base64 text) unchanged when it spells no HISTORY word, else the same image
    (same pixels, same other chunks) with its pixel data compressed again, the first zlib setting
    (level, memory level, strategy) whose base64 spells none, a tEXt chunk of 0-2 bytes after the
    header shifting the text's alignment if needed. Deterministic: one image gives one text."""
    import base64
    import zlib
    text = b64.strip()
    if not HISTORY.search(text):
        return b64
    chunks = _chunks(base64.b64decode(text))
    raw = zlib.decompress(b"".join(d for t, d in chunks if t == b"IDAT"))
    first = next(i for i, (t, _) in enumerate(chunks) if t == b"IDAT")
    rest = [c for c in chunks if c[0] != b"IDAT"]
    for level in range(9, 0, -1):
        for mem in range(9, 0, -1):
            for strategy in (zlib.Z_DEFAULT_STRATEGY, zlib.Z_FILTERED, zlib.Z_RLE, zlib.Z_HUFFMAN_ONLY):
                z = zlib.compressobj(level, zlib.DEFLATED, 15, mem, strategy)
                idat = (b"IDAT", z.compress(raw) + z.flush())
                for pad in range(3):
                    extra = [(b"tEXt", b"Comment\0" + b"." * pad)] if pad else []
                    body = rest[:1] + extra + rest[1:first] + [idat] + rest[first:]
                    out = base64.b64encode(_png(body)).decode("ascii")
                    if not HISTORY.search(out):
                        return out + ("\n" if b64.endswith("\n") else "")
    raise RuntimeError("no compression of the PNG avoids the HISTORY words")


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
                if isinstance(data.get("image/png"), str):
                    data["image/png"] = clean_png(data["image/png"])
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
