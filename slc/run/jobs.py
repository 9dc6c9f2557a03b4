"""Experiments as jobs: run here or on Ray, resumable, the same rows either way.

The job description lives in :mod:`slc.run.jobspec`, the committed rows in :mod:`slc.run.rowstore`,
Ray in :mod:`slc.run.cluster`.

A :class:`Job` is one unit of work that can be retried on its own: one scene
and a list of :class:`Case` s (method spec, viewers, extra row fields) that
run one after another in the same process, so that the time ratios between
them are measured side by side. The experiments group every method of one
(scene, viewers) comparison into one job (:func:`jobs_from_cases`). A job is
plain data and pickles: the viewers travel as a :class:`Rig`, the camera of
every viewer at every frame the run touches, taken on the driver from the
experiment's own viewers, so a worker rebuilds exactly the same cameras
(bit for bit) without the experiment's code or a live scene.

Execution (:class:`Session`, :func:`run_jobs`):

- serial, in this process, when neither ``workers`` nor ``address`` is given
  (Ray is not even imported);
- on Ray otherwise (:mod:`slc.run.cluster`): one actor per worker, each caching
  the last scene it loaded and running one job at a time with a stated
  Dr.Jit thread count.

Persistence: each finished job is committed as ``OUT/EXPERIMENT/rows/KEY.json``
(written to a temporary file, fsync'ed, renamed; only the driver writes),
after the evaluated images of a ``keep_images`` job (``KEY.images.npz``).
A row file is either complete or absent: an interrupted run (Ctrl-C, kill -9,
a lost worker) loses at most the jobs in flight, never a written row, and a
re-run of a job overwrites its own file (the name is the job's key), so no row
is ever duplicated. One file per job rather than an append-only JSONL: a
torn append needs repair on read and appends from several writers on shared
storage (NFS) are not atomic, while rename is; and resuming is a directory
listing. ``resume=True`` reads the row files whose key matches a job of this
run and runs only the others; keys hash everything that decides a job's
rows (experiment, scene, cfg, seed, specs, extra fields, the cameras), so a
resumed run with other settings reruns what changed.

Failures: a job that raises is retried up to ``retries`` times (a lost Ray
worker counts as a failed attempt and is replaced); jobs that still fail are
listed in one line (:class:`JobsFailed`) after every other job ran. The rows
of the jobs that succeeded stay committed, so ``--resume`` reruns only the
failed ones.
"""
from __future__ import annotations

import gc
import os
import socket
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import drjit as dr
from tqdm import tqdm

from slc.core import io
from slc.core.backend import variant
from slc.core.check import CheckError
from slc.run.errors import ExperimentError, JobsFailed, raise_fatal
from slc.run.jobspec import Case, Job
from slc.run.pipeline import run_case
from slc.run.rowstore import RowStore, normalize_rows
from slc.scene import scenes

# Row fields that depend on the run, not on the job's inputs: how long things
# took and where/how the job ran. Everything else must be identical between a
# serial run and a Ray run with the same seed.
TIMING_FIELDS = ("time_ms", "stages_ms", "stages_kernel_ms", "frames_ms", "compiled_after_warmup",
                 "recordings_after_warmup", "startup_ms")
RUN_FIELDS = ("host", "threads", "backend", "job")


# -----------------------------------------------------------------------------
# Running one job (in this process or in a Ray actor)
# -----------------------------------------------------------------------------

def run_fields(threads: int | None = None) -> dict:
    return {"host": socket.gethostname(), "threads": int(threads or dr.thread_count()), "backend": variant()}


class Runner:
    """Runs jobs, keeping the last scene loaded (jobs come grouped by scene).

    ``threads``: Dr.Jit worker threads for every kernel of this process
    (``dr.set_thread_count``); None keeps Dr.Jit's default (all cores)."""

    def __init__(self, threads: int | None = None):
        if threads:
            dr.set_thread_count(int(threads))
        self.threads = int(dr.thread_count())
        self._src = None
        self._scene = None

    def adopt(self, src: str, scene) -> None:
        """Use an already loaded scene for ``src`` (serial runs)."""
        self.release()
        self._src, self._scene = src, scene

    def release(self) -> None:
        if self._scene is not None:
            self._scene = self._src = None
            gc.collect()
            gc.collect()

    def scene(self, src: str):
        if src != self._src:
            self.release()  # one scene alive at a time (see slc.run.experiment.each_scene)
            self._scene, self._src = scenes.load(src), src
        return self._scene

    def run(self, job: Job, progress=None) -> dict:
        """Rows (and images) of every case of ``job``; ``run_s`` is the time
        spent in the cases, ``load_s`` in loading the scene."""
        t0 = time.perf_counter()
        s = self.scene(job.scene)
        t1 = time.perf_counter()
        fields = {**run_fields(self.threads), "job": job.key}
        rows, images = [], []
        for c in job.cases:
            if progress is not None:
                progress.case(c, job)
            row = run_case(s, c.spec, c.rig.build(), job.cfg, progress, seed=job.seed, **c.extra)
            res = row.pop("_result")
            row.update(fields)
            rows.append(row)
            images.append(res.images if job.keep_images else None)
        t2 = time.perf_counter()
        return {"rows": rows, "images": images, "exposure": float(s.exposure), "scene_name": s.name,
                "load_s": t1 - t0, "run_s": t2 - t1, "pid": os.getpid()}

    def run_safe(self, job: Job, progress=None) -> dict:
        """:meth:`run`, or ``{"error": "Type: message"}`` when it raises
        (reported and retried by the driver). A check-mode error
        (:class:`slc.core.check.CheckError`) is no job failure but stops the whole
        run: ``{"fatal": message}``."""
        try:
            return self.run(job, progress)
        except CheckError as e:
            return {"fatal": str(e)}
        except Exception as e:
            msg = str(e).strip().splitlines()
            return {"error": f"{type(e).__name__}: {msg[0] if msg else ''}".strip()}


# -----------------------------------------------------------------------------
# Sessions: serial or Ray execution, one bar, retries, commits
# -----------------------------------------------------------------------------

class _Progress:
    """One bar over all jobs (done / total, ETA); in serial runs the postfix
    follows the frames of the job that runs."""

    def __init__(self, total: int, done: int, desc: str):
        self.bar = tqdm(total=total, initial=done, desc=desc, unit="job", disable=None, dynamic_ncols=True)
        self._case = ""
        self._frame = 0

    def case(self, c: Case, job: Job) -> None:
        self._case, self._frame = f"{Path(job.scene).stem}/{c.spec}/{len(c.rig)}v", 0

    # the interface run_case / run_sequence use
    def set_postfix_str(self, s: str) -> None:
        pass

    def update(self, n: int = 1) -> None:
        self._frame += n
        self.bar.set_postfix_str(f"{self._case} frame {self._frame}", refresh=False)
        self.bar.refresh()

    def job_done(self) -> None:
        self.bar.update(1)

    def note(self, s: str) -> None:
        self.bar.set_postfix_str(s)

    def close(self) -> None:
        self.bar.close()


def images_of(session: "Session", job: Job) -> list:
    """The images of a ``keep_images`` job: from this experiment run, else as
    committed by an earlier run (resume)."""
    return session.images.pop(job.key, None) or session.store.load_images(job)


class Session:
    """Runs lists of jobs for one experiment run (see the module).

    ``out``: the experiment's output folder (None: nothing is committed, no
    resume). ``workers``/``address``: Ray (None for both: serial, in this
    process). ``threads``: Dr.Jit threads per worker. A Ray instance or
    connection is made on first use and closed by :meth:`close`."""

    def __init__(self, experiment: str, out=None, workers: int | None = None, address: str | None = None,
                 threads: int | None = None, resume: bool = False, retries: int = 2):
        if workers is not None and workers < 1:
            raise ExperimentError("--workers must be at least 1")
        if threads is not None and threads < 1:
            raise ExperimentError("--threads must be at least 1")
        if retries < 0:
            raise ExperimentError("--retries must be at least 0")
        self.experiment = experiment
        self.store = RowStore(out)
        self.workers, self.address, self.threads = workers, address, threads
        self.resume, self.retries = resume, retries
        self.distributed = bool(workers or address)
        if self.distributed:
            try:
                import ray  # noqa: F401  (Ray: checked only when jobs go to workers)
            except ImportError:
                raise ExperimentError("--workers/--address need Ray (pip install 'ray==2.60.0')") from None
        self._pool = None
        self._runner = None
        self.stats: list[dict] = []  # per finished job: key, wall_s, run_s, load_s, attempts, host
        self.images: dict[str, list] = {}  # keep_images jobs run by this experiment run: key -> images per case
        self.jobs_seen = 0

    # ----------------------------------------------------------------------
    def pool(self):
        if self._pool is None:
            from slc.run.cluster import RayPool  # Ray is optional: imported for --workers/--address only
            self._pool = RayPool(Runner, workers=self.workers, address=self.address, threads=self.threads)
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._runner is not None:
            self._runner.release()
            self._runner = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ----------------------------------------------------------------------
    def run(self, jobs: list[Job], desc: str = "jobs", scenes: dict | None = None, on_result=None) -> list[dict]:
        """Run ``jobs`` (only the missing ones when resuming); returns their
        rows in job order, each job's in case order. ``scenes``: loaded scenes
        by source for serial runs (an entry is removed from the dict when the
        run moves on to another scene, so that only one stays alive).
        ``on_result(job, rows, result)`` is called on the driver before a job
        is committed (e.g. to write its images)."""
        self.jobs_seen += len(jobs)
        keys = [j.key for j in jobs]
        if len(set(keys)) != len(keys):
            raise ValueError("two jobs of one run have the same key")
        done: dict[str, list] = {}
        if self.resume:
            for j in jobs:
                rows = self.store.load(j)
                if rows is not None:
                    done[j.key] = rows
            if done:
                print(f"resume: {len(done)} of {len(jobs)} {desc} jobs already done, {len(jobs) - len(done)} to run",
                      file=sys.stderr)
        todo = [j for j in jobs if j.key not in done]
        failed: list[tuple[Job, str]] = []
        progress = _Progress(len(jobs), len(done), desc)

        def finished(job, res, t_submit, attempts):
            rows = normalize_rows(res["rows"])
            t_out = time.perf_counter()
            if on_result is not None:
                on_result(job, rows, res)
            self.store.save_images(job, res["images"])
            timing = {"run_s": res["run_s"], "load_s": res["load_s"], "output_s": time.perf_counter() - t_out,
                      "attempts": attempts, "pid": res.get("pid"), "node": res.get("node")}
            self.store.commit(job, rows, timing)
            if job.keep_images:
                self.images[job.key] = res["images"]
            timing["wall_s"] = time.perf_counter() - t_submit  # submitted -> committed
            timing.update(key=job.key, host=rows[0].get("host") if rows else None)
            self.stats.append(timing)
            done[job.key] = rows
            progress.job_done()

        def gave_up(job, err):
            failed.append((job, err))
            progress.job_done()

        try:
            if todo:
                if self.distributed:
                    self.pool().run(todo, finished, gave_up, self.retries, progress)
                else:
                    self._run_serial(todo, finished, gave_up, scenes if scenes is not None else {}, progress)
        finally:
            progress.close()
            if self._runner is not None and not self.distributed:
                self._runner.release()  # never keep a scene alive past the caller's each_scene
        if failed:
            parts = "; ".join(f"{j.describe()}: {e}" for j, e in failed)
            where = f" (the other jobs' rows are in {self.store.folder}; rerun with --resume)" \
                if self.store.folder else ""
            raise JobsFailed(f"{len(failed)} of {len(jobs)} jobs failed after {self.retries + 1} attempt(s): "
                             f"{parts}{where}")
        return [r for j in jobs for r in done[j.key]]

    def _run_serial(self, todo, finished, gave_up, scenes, progress):
        if self._runner is None:
            self._runner = Runner(self.threads)
        runner = self._runner
        for job in todo:
            if runner._src != job.scene:
                scenes.pop(runner._src, None)  # the caller's reference goes too: one scene alive at a time
                if job.scene in scenes:
                    runner.adopt(job.scene, scenes[job.scene])
            for attempt in range(1, self.retries + 2):
                t0 = time.perf_counter()
                res = runner.run_safe(job, progress)
                raise_fatal(res)
                if "error" not in res:
                    finished(job, res, t0, attempt)
                    break
                progress.note(f"{job.describe()}: attempt {attempt} failed: {res['error']}")
            else:
                gave_up(job, res["error"])

    # ----------------------------------------------------------------------
    def overhead(self) -> dict | None:
        """Job time and job overhead. A job's time is its wall time on the
        driver (submitted -> committed); its overhead is that minus the time
        in its cases, split into the scene load (when the worker did not hold
        the scene), the experiment's output (``on_result``: image files) and
        the rest (dispatch, transfer, row commit: the job machinery)."""
        if not self.stats:
            return None
        st = self.stats
        wall = [s["wall_s"] for s in st]
        over = [s["wall_s"] - s["run_s"] for s in st]
        mach = [s["wall_s"] - s["run_s"] - s["load_s"] - s["output_s"] for s in st]
        med = statistics.median(wall)
        pct = (lambda x: 100.0 * x / med if med else float("nan"))
        return {"jobs": len(st), "median_job_s": med, "total_job_s": sum(wall),
                "median_overhead_s": statistics.median(over), "overhead_pct": pct(statistics.median(over)),
                "total_overhead_s": sum(over), "total_load_s": sum(s["load_s"] for s in st),
                "total_output_s": sum(s["output_s"] for s in st),
                "median_machinery_s": statistics.median(mach), "machinery_pct": pct(statistics.median(mach))}


# -----------------------------------------------------------------------------
# The session of the experiment being run
# -----------------------------------------------------------------------------

_current: Session | None = None


def current(experiment: str = "experiment") -> Session:
    """The session set by :func:`session_for`, or a serial one that commits
    nothing (experiment code called from a notebook or a test)."""
    return _current if _current is not None else Session(experiment)


@contextmanager
def session_for(experiment: str, opts):
    """The session of ``slc run EXPERIMENT`` with options ``opts`` (--out,
    --workers, --address, --threads, --resume, --retries); writes the job
    timings to ``OUT/EXPERIMENT/jobs.json`` at the end."""
    global _current
    out = Path(getattr(opts, "out", None) or "out") / experiment
    s = Session(experiment, out, workers=getattr(opts, "workers", None), address=getattr(opts, "address", None),
                threads=getattr(opts, "threads", None), resume=bool(getattr(opts, "resume", False)),
                retries=getattr(opts, "retries", 2) if getattr(opts, "retries", None) is not None else 2)
    prev, _current = _current, s
    try:
        yield s
        if s.distributed and not s.jobs_seen:
            print(f"note: {experiment} runs its own loop, not jobs: --workers/--address had no effect",
                  file=sys.stderr)
    finally:
        _current = prev
        s.close()
        o = s.overhead()
        if o is not None:
            io.write_json(out / "jobs.json", {"summary": o, "jobs": s.stats})
            print(f"jobs: {o['jobs']} run, median job {o['median_job_s']:.2f} s; median overhead "
                  f"{o['median_overhead_s']:.3f} s ({o['overhead_pct']:.2f}%), of which job machinery "
                  f"{o['median_machinery_s']:.3f} s ({o['machinery_pct']:.2f}%); in all {o['total_overhead_s']:.1f} s "
                  f"overhead ({o['total_load_s']:.1f} s scene loads, {o['total_output_s']:.1f} s image files) "
                  f"in {o['total_job_s']:.1f} s of jobs", file=sys.stderr)


def run_jobs(jobs: list[Job], out_dir=None, workers: int | None = None, address: str | None = None,
             resume: bool = False, retries: int = 2, threads: int | None = None, desc: str = "jobs",
             on_result=None) -> list[dict]:
    """Run ``jobs`` once, serially or on Ray (see :class:`Session`)."""
    exp = jobs[0].experiment if jobs else "experiment"
    with Session(exp, out_dir, workers=workers, address=address, threads=threads, resume=resume,
                 retries=retries) as s:
        return s.run(jobs, desc, on_result=on_result)
