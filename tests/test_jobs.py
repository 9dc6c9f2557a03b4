"""Experiments as jobs: serial and Ray runs give the same rows and images,
runs killed mid-way resume to the same results, failed jobs are retried
and reported (slc.run.jobs, slc.run.cluster)."""
import filecmp
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import slc_cli
from slc.run import jobs, jobspec

from slc.scene import views
from slc.run.pipeline import RunConfig

ROOT = Path(__file__).resolve().parents[1]
SLC = [sys.executable, "-m", "slc.run.cli"]
SCENES = ["cornell", "garden", "hangar"]  # three jobs (one per scene), cheap to load
TINY = ["run", "single-viewer", "--quick", "--res", "32x18", "--frames", "3", "--methods", "rt4", "slc",
        "--sweep"] + [a for s in SCENES for a in ("--scene", s)]
SKIP = set(jobs.TIMING_FIELDS) | set(jobs.RUN_FIELDS)

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="ray is not importable (pip install ray==2.60.0)")


def slc_run(out, *extra, timeout=900):
    """The tiny preset, in this process (helpers.slc_cli) unless it starts Ray workers."""
    if "--workers" in extra:
        r = subprocess.run(SLC + TINY + ["--out", str(out), *extra], capture_output=True, text=True, cwd=ROOT,
                           timeout=timeout)
    else:
        r = slc_cli(TINY + ["--out", out, *extra])
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def spawn(out, *extra):
    return subprocess.Popen(SLC + TINY + ["--out", str(out), *extra], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)


def rows_dir(out):
    return Path(out) / "single-viewer" / "rows"


def committed(out) -> dict:
    d = rows_dir(out)
    return {p.name: p.stat().st_mtime_ns for p in d.glob("*.json") if not p.name.startswith(".")} \
        if d.is_dir() else {}


def wait_for(cond, proc, timeout=600):
    t0 = time.time()
    while not cond():
        assert proc.poll() is None, f"run ended early: {proc.stderr.read()[-3000:]}"
        assert time.time() - t0 < timeout, "timed out"
        time.sleep(0.2)


def assert_same_results(a, b):
    """Equal rows but for timing and run fields; image files equal byte for byte."""
    ra = json.loads((Path(a) / "single-viewer" / "results.json").read_text())["rows"]
    rb = json.loads((Path(b) / "single-viewer" / "results.json").read_text())["rows"]
    strip = [[{k: v for k, v in r.items() if k not in SKIP} for r in rs] for rs in (ra, rb)]
    assert len(ra) == 2 * len(SCENES)
    assert strip[0] == strip[1]
    ia, ib = Path(a) / "single-viewer" / "images", Path(b) / "single-viewer" / "images"
    names = sorted(p.name for p in ia.iterdir())
    assert names == sorted(p.name for p in ib.iterdir()) and any(n.endswith(".exr") for n in names)
    _, mismatch, errors = filecmp.cmpfiles(ia, ib, names, shallow=False)
    assert not mismatch and not errors, mismatch + errors
    return ra, rb


def descendants(pid: int) -> list[int]:
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def stop(proc):
    if proc.poll() is None:
        for pid in [proc.pid] + descendants(proc.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.wait(timeout=60)


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """An uninterrupted serial run of the tiny preset (the reference)."""
    out = tmp_path_factory.mktemp("serial")
    slc_run(out)
    return out


# -----------------------------------------------------------------------------
# Jobs as data
# -----------------------------------------------------------------------------

def test_rig_rebuilds_the_same_cameras_and_keys_follow_the_inputs():
    from slc.scene import scenes
    s = scenes.load("cornell")
    s.source = "cornell"
    cfg = RunConfig(width=16, height=9, frames=3, warmup=1)
    live = views.independent(s, 2)
    rig = jobspec.Rig.from_viewers(live, cfg)
    import pickle
    rebuilt = pickle.loads(pickle.dumps(rig)).build()
    for v, w in zip(live, rebuilt):
        assert v.name == w.name and v.rig == w.rig
        for f in range(3):
            a, b = v.camera(f), w.camera(f)
            assert (a.origin.tobytes(), a.target.tobytes(), a.fov) == (b.origin.tobytes(), b.target.tobytes(), b.fov)
    with pytest.raises(KeyError, match="outside"):
        rebuilt[0].camera(7)
    cases = [(s, spec, views.independent(s, n), {"rig": "single"}) for spec in ("rt4", "slc") for n in (1, 2)]
    js = jobspec.jobs_from_cases("t", cases, cfg)
    # one job per viewer set, every method of the comparison in it, in the given order
    assert [[c.spec for c in j.cases] for j in js] == [["rt4", "slc"], ["rt4", "slc"]]
    assert [[c.index for c in j.cases] for j in js] == [[0, 2], [1, 3]]
    again = jobspec.jobs_from_cases("t", cases, cfg)
    assert [j.key for j in js] == [j.key for j in again]
    other = jobspec.jobs_from_cases("t", cases, RunConfig(width=16, height=9, frames=3, warmup=1, seed=1))
    assert not {j.key for j in js} & {j.key for j in other}


def test_failed_jobs_are_retried_reported_and_resumable(tmp_path):
    from slc.scene import scenes
    s = scenes.load("cornell")
    s.source = "cornell"
    cfg = RunConfig(width=16, height=9, frames=2, warmup=1, eval_frames=[])
    good = jobspec.jobs_from_cases("t", [(s, "rt4", views.single(s), {})], cfg)[0]
    bad = jobspec.Job("t", "no-such-scene", good.cases, cfg)
    sess = jobs.Session("t", tmp_path, retries=1)
    with pytest.raises(jobs.JobsFailed) as e:
        sess.run([bad, good])
    msg = str(e.value)
    assert "\n" not in msg and "1 of 2 jobs failed after 2 attempt(s)" in msg and "no-such-scene" in msg
    assert (tmp_path / "rows" / f"{good.key}.json").exists()  # the other job went on and was committed
    assert not (tmp_path / "rows" / f"{bad.key}.json").exists()
    # a torn or foreign file is not a committed job
    (tmp_path / "rows" / f"{bad.key}.json").write_text('{"key": "x", "rows": [')
    resumed = jobs.Session("t", tmp_path, resume=True)
    rows = resumed.run([good])
    assert resumed.stats == [] and rows[0]["method"] == "rt4"  # nothing ran again
    assert resumed.store.load(bad) is None


# -----------------------------------------------------------------------------
# Serial: killed mid-way, resumed
# -----------------------------------------------------------------------------

@pytest.mark.slow
def test_serial_run_killed_then_resumed_equals_uninterrupted(serial, tmp_path):
    out = tmp_path / "killed"
    p = spawn(out)
    try:
        wait_for(lambda: len(committed(out)) >= 1, p)
        os.kill(p.pid, signal.SIGKILL)  # kill -9 after the first row file
        p.wait(timeout=60)
    finally:
        stop(p)
    before = committed(out)
    assert 1 <= len(before) < len(SCENES)
    assert not (out / "single-viewer" / "results.json").exists()
    r = slc_run(out, "--resume")
    assert f"resume: {len(before)} of {len(SCENES)}" in r.stderr
    after = committed(out)
    assert len(after) == len(SCENES)
    assert all(after[k] == t for k, t in before.items())  # committed rows were kept, not recomputed
    assert_same_results(serial, out)


# -----------------------------------------------------------------------------
# Ray
# -----------------------------------------------------------------------------

@pytest.mark.slow
@needs_ray
def test_two_node_cluster_gives_the_serial_rows(serial, tmp_path, ray_cluster):
    """The tiny preset on the session's two-node cluster (``--address``): the serial rows,
    jobs on both nodes, and the driver disconnected afterwards."""
    import ray

    from slc.run.cli import main
    out = tmp_path / "cluster"
    assert not ray.is_initialized()
    assert main(TINY + ["--out", str(out), "--address", ray_cluster.address]) == 0
    assert not ray.is_initialized()              # the run disconnected the connection it made
    assert_same_results(serial, out)
    stats = json.loads((out / "single-viewer" / "jobs.json").read_text())["jobs"]
    assert len({s["node"] for s in stats}) == 2  # both nodes ran jobs


@pytest.mark.slow
@needs_ray
def test_killed_ray_worker_loses_no_row_and_the_run_completes(serial, tmp_path):
    """Two Ray workers, one killed in the middle of a job: the job is retried, no row is lost,
    and the rows are the serial run's (each worker with half the cores)."""
    out = tmp_path / "raykill"
    p = spawn(out, "--workers", "2")
    try:
        busy = []

        def first_row_and_a_busy_worker():
            if not committed(out):
                return False
            busy[:] = [q for q in descendants(p.pid) if cmdline(q).startswith("ray::SceneWorker.run")]
            return bool(busy)

        wait_for(first_row_and_a_busy_worker, p)
        before = committed(out)
        os.kill(busy[0], signal.SIGKILL)  # a worker dies in the middle of a job
        _, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-3000:]
    finally:
        stop(p)
    after = committed(out)
    assert len(after) == len(SCENES) and all(after[k] == t for k, t in before.items())
    stats = json.loads((out / "single-viewer" / "jobs.json").read_text())["jobs"]
    assert len(stats) == len(SCENES) and max(s["attempts"] for s in stats) == 2  # the lost job was retried
    # the rows of two Ray workers are the serial run's, each worker on its share of the cores
    ra, rb = assert_same_results(serial, out)
    assert {r["threads"] for r in rb} == {max((os.cpu_count() or 1) // 2, 1)}
    assert {r["backend"] for r in rb} == {r["backend"] for r in ra}
    assert all(r["host"] and r["job"] for r in rb)


@pytest.mark.slow
def test_serial_runs_do_not_import_ray(tmp_path):
    code = ("import sys, slc\n"
            "from slc.run import jobs, jobspec\n"
            "from slc.scene import scenes, views\n"
            "from slc.run.pipeline import RunConfig\n"
            "s = scenes.load('cornell')\n"
            "cfg = RunConfig(width=8, height=6, frames=1, warmup=0, eval_frames=[])\n"
            "js = jobspec.jobs_from_cases('t', [(s, 'rt4', views.single(s), {})], cfg)\n"
            f"rows = jobs.run_jobs(js, {str(tmp_path)!r})\n"
            "assert len(rows) == 1 and rows[0]['threads'] >= 1 and rows[0]['backend']\n"
            "print('ray' in sys.modules, 'slc.run.cluster' in sys.modules)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["False", "False"]


def test_one_thread_runner_loads_exr_scenes_and_writes_exr(tmp_path):
    """A job runner of one Dr.Jit thread (a cluster's default on 2-core nodes) loads a scene whose
    environment map is an EXR file and writes and reads an EXR: Mitsuba's EXR reader and writer
    wait forever on a one-thread pool, so slc runs them with two (backend.exr_pool)."""
    code = ("import drjit as dr, numpy as np\n"
            "from slc.core import backend, io\n"
            "backend.init()\n"
            "from slc.run.jobs import Runner\n"
            "r = Runner(threads=1)\n"
            "s = r.scene('preview_export')\n"
            f"io.write_exr({str(tmp_path / 'a.exr')!r}, np.full((4, 6, 3), 0.5, np.float32))\n"
            f"a = io.read_exr({str(tmp_path / 'a.exr')!r})\n"
            "print(r.threads, dr.thread_count(), s.name, a.shape, float(a.mean()))\n")
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("a one-thread runner did not load preview_export and write an EXR within 120 s")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["1", "1", "preview_export", "(4,", "6,", "3)", "0.5"]


def test_check_mode_error_stops_the_run_without_retries(tmp_path, monkeypatch):
    from slc.scene import scenes
    from slc.core.check import CheckError
    s = scenes.load("cornell")
    s.source = "cornell"
    cfg = RunConfig(width=8, height=6, frames=1, warmup=0, eval_frames=[])
    js = [jobspec.jobs_from_cases("t", [(s, spec, views.single(s), {})], cfg)[0] for spec in ("rt4", "rt8")]
    calls = []

    def bad(self, job, progress=None):
        calls.append(job.key)
        raise CheckError("rt4: frame 0, stage shade: NaN at pixel (1, 2)")

    monkeypatch.setattr(jobs.Runner, "run", bad)
    with pytest.raises(CheckError, match="NaN at pixel"):
        jobs.Session("t", tmp_path, retries=2).run(js)
    assert calls == [js[0].key]  # neither retried nor followed by the other job
    assert not list(tmp_path.glob("rows/*.json"))  # nothing committed
