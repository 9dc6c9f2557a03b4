"""Committed rows: ``OUT/EXPERIMENT/rows/KEY.json``, one file per finished job, written atomically
(temporary file, fsync, rename), and the evaluated images of a ``keep_images`` job beside it
(see :mod:`slc.run.jobs` for why one file per job)."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from slc.core import io
from slc.run.jobspec import Job

def _write_durable(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically and durably: temp file in the
    same folder, fsync, rename, fsync the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".part", dir=path.parent)  # never matches *.json
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def _json_default(o):
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def normalize_rows(rows: list[dict]) -> list[dict]:
    """Rows as they read back from their file (a resumed run and a fresh one
    hand the experiment exactly the same values)."""
    return json.loads(json.dumps(rows, default=_json_default, allow_nan=True))


class RowStore:
    """``OUT/EXPERIMENT/rows/KEY.json``, one committed file per finished job."""

    def __init__(self, folder: Path | None):
        self.folder = Path(folder) / "rows" if folder is not None else None

    def path(self, job: Job) -> Path:
        return self.folder / f"{job.key}.json"

    def load(self, job: Job):
        """The job's committed rows, or None (absent, unreadable or another key)."""
        if self.folder is None:
            return None
        try:
            d = json.loads(self.path(job).read_text())
        except (OSError, ValueError):
            return None
        if d.get("key") != job.key or len(d.get("rows", [])) != len(job.cases):
            return None
        return d["rows"]

    def images_path(self, job: Job) -> Path:
        return self.folder / f"{job.key}.images.npz"

    def save_images(self, job: Job, images: list) -> None:
        """The evaluated images of a ``keep_images`` job (before its commit)."""
        if self.folder is None or not job.keep_images:
            return
        arrays = {}
        for i, per_case in enumerate(images):
            for viewer, d in (per_case or {}).items():
                for k, v in d.items():
                    arrays[f"{i}\x1f{viewer}\x1f{k}"] = np.asarray(v)
        io.write_npz(self.images_path(job), **arrays)

    def load_images(self, job: Job) -> list:
        """Per case, ``{viewer: {"gt", "img", "flip_map", "frame"}}`` as saved ({} when absent)."""
        out = [{} for _ in job.cases]
        if self.folder is None:
            return out
        try:
            with np.load(self.images_path(job), allow_pickle=False) as z:
                for name in z.files:
                    i, viewer, k = name.split("\x1f")
                    v = z[name]
                    out[int(i)].setdefault(viewer, {})[k] = v.item() if v.ndim == 0 else v
        except (OSError, ValueError):
            pass
        return out

    def commit(self, job: Job, rows: list[dict], timing: dict) -> None:
        if self.folder is None:
            return
        text = json.dumps({"key": job.key, "experiment": job.experiment, "scene": job.scene,
                           "job": job.describe(), "timing": timing, "rows": rows},
                          indent=1, default=_json_default, allow_nan=True)
        _write_durable(self.path(job), text)
