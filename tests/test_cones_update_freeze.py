"""The cone update traced once and replayed (``slc.methods.cones.update_kernel.ConeUpdate``,
``dr.freeze``): the same images bit for bit as the update traced every frame, and a
bounded number of recordings over a run whose active entries and storage change size."""
import numpy as np
import pytest

from helpers import plane_under_rect_light, run_case
from slc.methods.cones.update_kernel import ConeUpdate
from slc.methods import FrameContext, create
from slc.osc import OnSurfaceCache
from slc.scene.gbuffer import frame_gbuffers
from slc.scene.builder import SceneBuilder, diffuse, rough_conductor
from slc.scene.camera import CameraPath
from slc.core.timing import NullTimer
from slc.scene.views import single
from test_cones import _moving_scene

pytestmark = pytest.mark.slow      # fresh interpreters counting kernels


W, H = 40, 30


def _growing_scene():
    """Static scene, camera sliding sideways over 24 frames: the OSC allocates new blocks
    (a 2-block pool: the storage grows) and the number of active entries changes."""
    b = SceneBuilder("sliding24")
    b.add_quad([0, 0, 0], [3, 0, 0], [0, 0, -3], bsdf=rough_conductor(0.1, "Al"), name="plane")
    b.add_quad([0, 1.0, 0], [0.2, 0, 0], [0, 0, 0.2], bsdf=diffuse([0, 0, 0]), emission=[10.0] * 3, name="light")
    cam = CameraPath([([-1.5, 0.6, 1.0], [-1.5, 0.0, 0.0]), ([1.5, 0.6, 1.0], [1.5, 0.0, 0.0])], frames=24, fov=50)
    return b.build([cam])


def _run(sc, viewers, frames, freeze, grow=False):
    kw = {"cache": OnSurfaceCache(sc, max_blocks=2)} if grow else {}
    m = create("slc", sc, **kw)
    if not freeze:
        m._cone_update = ConeUpdate(freeze=False)
    imgs, widths, active, recs = [], [], [], []
    for f in range(frames):
        out = m.render(FrameContext(f), frame_gbuffers(sc, viewers, f, W, H), NullTimer())
        imgs.append([np.array(x) for x in out])
        widths.append(len(m.storage))
        active.append(m.requests.n_active)
        recs.append(m._cone_update.n_recordings)
    m.recordings_per_frame = recs
    return m, imgs, widths, active


_RECORDINGS = """
import json, sys
sys.path.insert(0, "tests")
import slc.core.backend  # noqa: F401
import test_cones_update_freeze as F
n_views, preload = int(sys.argv[1]), sys.argv[2]
if preload:
    from slc.scene import scenes
    scenes.load(preload)           # loaded and released before the run
sc = F._growing_scene()
m, _, widths, _ = F._run(sc, F.single(sc) * n_views, 24, freeze=True, grow=True)
print("RESULT " + json.dumps(dict(recs=m.recordings_per_frame, widths=widths, frozen=m._cone_update.frozen)))
"""


@pytest.mark.parametrize("n_views", [1, 4], ids=["1-viewer", "4-viewers"])
def test_frozen_update_same_images_and_bounded_recordings(n_views):
    """24 frames of a static scene whose storage grows and whose active-entry count
    changes every frame: every image equals the one of the update traced every frame,
    and (in a fresh process) the frozen update records twice — the second recording
    makes the inputs that changed between the first two calls opaque — then only
    replays, although the storage grows again (frame 11) and the entry count keeps
    changing; still frozen at the end. The recordings are counted in a fresh process
    because they depend on what else is alive in the process (Mitsuba's registry):
    see the next test."""
    sc = _growing_scene()
    viewers = single(sc) * n_views
    m, imgs, widths, active = _run(sc, viewers, 24, freeze=True, grow=True)
    _, ref, _, _ = _run(sc, viewers, 24, freeze=False, grow=True)
    assert widths[-1] > widths[0], widths            # the storage grew during the run
    assert len(set(active)) > 3, active              # the number of entries changed
    for f, (a, b) in enumerate(zip(imgs, ref)):
        for v, (x, y) in enumerate(zip(a, b)):
            assert np.all(np.isfinite(x))
            assert np.array_equal(x, y), (f, v)
    r = run_case(_RECORDINGS, n_views, "")
    recs, widths = r["recs"], r["widths"]
    assert r["frozen"] and 1 <= recs[-1] <= 2, recs
    assert recs[1:] == [recs[1]] * (len(recs) - 1), recs      # replays only after frame 1
    assert len(set(widths[2:])) > 1, widths                   # ... also across a growth of the storage


def test_frozen_update_bounded_after_another_scene():
    """The same run after the atrium scene was loaded and released in the process
    (what a test suite, a notebook or a multi-scene experiment does): the same
    recordings as in a fresh process. It recorded at every frame until dropped
    ([1, 2, 3, 4, 5]) while the released scene's emitters and emissive shapes stayed
    alive in the emitter-table cache, hence in Mitsuba's registry, which the frozen
    function traverses (see slc/core/freeze.py and tests/test_freeze_scenes.py)."""
    r = run_case(_RECORDINGS, 1, "atrium")
    fresh = run_case(_RECORDINGS, 1, "")
    assert r["frozen"] and r["recs"][-1] <= 2, r["recs"]
    assert r["recs"] == fresh["recs"], (r["recs"], fresh["recs"])


@pytest.mark.fresh_process
def test_frozen_update_follows_a_moving_light():
    """An animated scene (the light's vertex buffer and the emitter table change every
    frame): the update is recorded at most twice and replayed, and gives the same images
    as ``freeze=False`` over 16 frames."""
    sc = _moving_scene()
    m, imgs, _, _ = _run(sc, single(sc), 16, freeze=True)
    _, ref, _, _ = _run(sc, single(sc), 16, freeze=False)
    for f, (a, b) in enumerate(zip(imgs, ref)):
        assert np.array_equal(a[0], b[0]), f
    assert m._cone_update.frozen and 1 <= m._cone_update.n_recordings <= 2, m.recordings_per_frame


@pytest.mark.fresh_process
def test_static_light_replays_without_recording():
    """A static scene of fixed size: after the first two calls every update is a replay."""
    sc = plane_under_rect_light(half=0.1, radiance=20.0, bsdf=rough_conductor(0.05, "Al"), name="static_upd")
    m, _, _, _ = _run(sc, single(sc), 12, freeze=True)
    assert m._cone_update.calls == 12 and m._cone_update.n_recordings <= 2
