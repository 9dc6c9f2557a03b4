import gc
import os
import sys
from pathlib import Path

import pytest

# References are cached on disk under a key that holds everything they depend on
# (slc.reference.cache: estimator version, the reference and scene code, the scene's
# content, camera, time, G-buffer), so a cached reference is the one a test would
# compute; the tests keep theirs apart from the experiments' cache.
os.environ.setdefault("SLC_CACHE", str(Path.home() / ".cache" / "slc-tests"))
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from slc.core import backend  # noqa: E402

backend.init()  # test modules build Mitsuba types on import

import mitsuba as mi  # noqa: E402

FRESH_ENV = "SLC_TEST_FRESH_PROCESS"     # set in the interpreter that runs a fresh_process test


@pytest.fixture(scope="session")
def root():
    return ROOT


# the scenes of the `scene` fixture, kept while one test file runs
_LOADED: dict = {}


@pytest.fixture(scope="session")
def scene():
    """``scene(name)``: a built-in scene (or scene file) loaded once per test file and shared
    by its tests. Tests must not modify it (moving a light, mi.traverse updates); load a private
    copy with ``slc.scenes.load`` for that."""
    from slc.scene import scenes

    def load(name: str):
        if name not in _LOADED:
            _LOADED[name] = scenes.load(name)
        return _LOADED[name]
    return load


@pytest.fixture(scope="module", autouse=True)
def _release_scenes_after_each_file():
    """Every live Mitsuba object joins Dr.Jit's virtual call tables: a scene kept alive after
    its file would be traced and dispatched over in every later kernel of the process (its
    kernels larger and other than a fresh process's, slower to build and to run; the osc-gi
    budget tests took 98 s after the built-in scenes were loaded, 11 s without). So the scenes
    of a file are released when it ends (slc.run.experiment.release_scenes)."""
    yield
    _LOADED.clear()
    from slc.run.experiment import release_scenes
    release_scenes()


_MADE = [False]       # a Mitsuba object was loaded since the last test ended


def _noting_loads(load):
    def wrapped(*args, **kw):
        _MADE[0] = True
        return load(*args, **kw)
    return wrapped


for _name in ("load_dict", "load_file", "load_string"):
    setattr(mi, _name, _noting_loads(getattr(mi, _name)))


@pytest.fixture(autouse=True)
def _release_private_scenes_after_each_test():
    """The same for the scenes a test builds for itself: Mitsuba objects live in reference
    cycles that only a full garbage collection frees, so without one a test's scene stays in
    the call tables of the tests after it (tests/test_adaptive_polygons.py alone, one
    process, empty kernel cache: 45.9 s of CPU, 32.3 s with a collection after each test).
    A test that loaded a Mitsuba object collects when it ends (about 30 ms)."""
    yield
    if _MADE[0]:
        _MADE[0] = False
        gc.collect()


@pytest.fixture(scope="session")
def reference():
    """``reference(kind, scene, gb, frame, spp=None, bounces=1)``: the reference image
    (slc.reference.references.reference_for: ``direct`` ground truth, ``indirect`` or ``full``) of
    the G-buffer, computed once per pytest session and shared across tests and files (the
    reference cache on disk, SLC_CACHE, keys it by scene, camera, frame,
    resolution, samples and the G-buffer's content)."""
    from slc.reference import references

    def ref(kind, scene, gb, frame, spp=None, bounces=1):
        return references.reference_for(kind, scene, gb, frame, gb.viewer, spp=spp, bounces=bounces)
    return ref


# ----------------------------------------------------------------------------- a fresh interpreter per test


def _run_in_fresh_process(item):
    """Run ``item`` alone in a new pytest process (its fixtures are set up there)."""
    import subprocess
    env = dict(os.environ, **{FRESH_ENV: "1"})
    cmd = [sys.executable, "-m", "pytest", "-q", "--no-header", "-p", "no:cacheprovider",
           "-rfEs", item.nodeid]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=item.config.rootpath, env=env, timeout=1800)
    summary = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
    if p.returncode == 0 and " passed" in summary:
        return
    if p.returncode == 0 and " skipped" in summary:
        pytest.skip(f"in a fresh process: {summary}")
    pytest.fail(f"in a fresh process (exit status {p.returncode}):\n{p.stdout[-6000:]}\n{p.stderr[-3000:]}",
                pytrace=False)


def pytest_addoption(parser):
    parser.addoption("--shuffle", type=int, default=None, metavar="SEED",
                     help="run the test files in an order shuffled by SEED, and the tests of each file in an "
                          "order shuffled by it too (a file's tests stay together: its module fixtures are "
                          "built once), to check that no test depends on which tests ran before it in its "
                          "process; the seed is printed in the header. Default: the collection order")


def pytest_collection_modifyitems(config, items):
    seed = config.getoption("--shuffle")
    if seed is not None:
        import random
        rng = random.Random(seed)
        files = {}
        for it in items:
            files.setdefault(it.nodeid.split("::")[0], []).append(it)
        order = list(files)
        rng.shuffle(order)
        items[:] = []
        for f in order:
            tests = files[f]
            rng.shuffle(tests)
            items.extend(tests)
    if os.environ.get(FRESH_ENV):
        return
    for it in items:
        if it.get_closest_marker("fresh_process") is not None:
            # fixtures are set up in the fresh process, not here
            it.setup = lambda: None
            it.runtest = (lambda item: lambda: _run_in_fresh_process(item))(it)


def pytest_report_header(config):
    seed = config.getoption("--shuffle")
    return None if seed is None else f"test order shuffled with seed {seed} (--shuffle)"


# ----------------------------------------------------------------------------- a Ray cluster while tests use it

_RAY: dict = {}       # the running cluster, if any


@pytest.fixture
def ray_cluster():
    """A local Ray cluster of two nodes of one CPU each (``ray.cluster_utils.Cluster``), started
    when a test asks for it and shared with the tests right after it that ask for it too; tests
    connect to it by ``cluster.address`` and disconnect again (``ray.shutdown()``). It is shut
    down after the last of them (:func:`pytest_runtest_teardown`): an idle cluster of two nodes
    takes about 2.5 s of CPU a minute, which the rest of the suite would lose."""
    ray = pytest.importorskip("ray")
    if "cluster" not in _RAY:
        from ray.cluster_utils import Cluster
        cluster = Cluster(initialize_head=True,
                          head_node_args={"num_cpus": 1, "_system_config": backend.RAY_SYSTEM_CONFIG})
        _RAY["cluster"] = cluster
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
    yield _RAY["cluster"]
    if ray.is_initialized():
        ray.shutdown()


def _stop_ray_cluster() -> None:
    cluster = _RAY.pop("cluster", None)
    if cluster is not None:
        cluster.shutdown()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """After a test's fixtures are torn down: the Ray cluster stops unless the next test of this
    process asks for it too."""
    yield
    if "cluster" in _RAY and (nextitem is None or "ray_cluster" not in nextitem.fixturenames):
        _stop_ray_cluster()


def pytest_sessionfinish(session):
    _stop_ray_cluster()


# ----------------------------------------------------------------------------- xdist: work units and their order

# Files that start Ray clusters (tests/test_jobs.py, the fresh processes of tests/test_distributed.py):
# one work unit, which one worker runs test after test, so that at most one of their Ray instances is up.
SHARED_UNITS = {"tests/test_jobs.py": "ray", "tests/test_distributed.py": "ray"}

# Seconds of the longest files in make test (2 cores, empty kernel cache, --durations), so that
# they start first; any other file counts one second a test.
UNIT_SECONDS = {
    "tests/test_compile.py": 160, "tests/test_error_bounds.py": 160, "tests/test_cones.py": 100,
    "tests/test_hard_cases.py": 95, "tests/test_jobs.py": 90, "tests/test_scenes.py": 85,
    "tests/test_adaptive.py": 75, "tests/test_check.py": 60, "tests/test_adaptive_polygons.py": 55,
    "tests/test_distributed.py": 50, "tests/test_sampling.py": 48,
}


def _unit_weight(nodeids) -> float:
    """Expected seconds of a work unit: the measured ones of the files in UNIT_SECONDS, else one
    second a test."""
    files = {n.split("::")[0] for n in nodeids}
    return sum(UNIT_SECONDS.get(f, 0.0) for f in files) + sum(1.0 for n in nodeids
                                                               if n.split("::")[0] not in UNIT_SECONDS)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` with two changes: the files of SHARED_UNITS form one work unit each, and
    a worker that asks for work gets the unit expected to take longest (UNIT_SECONDS), so that the
    long files start first and no worker runs one alone at the end."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class Scheduling(LoadFileScheduling):
        def _split_scope(self, nodeid):
            f = nodeid.split("::", 1)[0]       # a test's work unit: its file, or its shared unit
            return SHARED_UNITS.get(f, f)

        def _assign_work_unit(self, node):
            longest = max(self.workqueue, key=lambda scope: _unit_weight(self.workqueue[scope]))
            self.workqueue.move_to_end(longest, last=False)
            super()._assign_work_unit(node)

    return Scheduling(config, log)
