"""CRC's moving volume (the paper's Sec. 7: a window of the grid centred at
the viewer, moved in whole cells): coefficients are scrolled, not
recomputed; a scrolled window equals a freshly computed one at the cells
both hold; moving builds no kernels; shaded points outside the window get
no cached light."""
import gc

import drjit as dr
import numpy as np
import pytest

from slc import methods

from slc.scene import views
from slc.methods import FrameContext
from slc.scene.gbuffer import frame_gbuffers
from slc.core.timing import KernelCounter, NullTimer

W, H = 64, 36


@pytest.fixture(scope="module")
def atrium(scene):
    return scene("atrium")


def _pinned(scene, offset, **kw):
    """A moving-volume cache whose window corner is pinned at ``offset``
    (world cells) instead of following the camera."""
    m = methods.create("crc", scene, volume="camera", **kw)
    m.region.corner = lambda gbs: np.asarray(offset, dtype=np.int64)
    return m


def _centre(m):
    return (np.array(m.world.dims) - m.window) // 2


def _cells(m, cells):
    """World integer coordinates (n, 3) of window cells."""
    nx, ny, _ = m.grid.dims
    c = np.asarray(cells, np.int64)
    return np.stack([c % nx, (c // nx) % ny, c // (nx * ny)], 1) + m.region.offset


def _coeffs(m):
    n = m.grid.n_cells
    return np.array(m.cache).reshape(m.enc.n, n)


@pytest.mark.parametrize("bounces,shift", [(1, (1, 0, -1)), (2, (1, 0, 0))])
def test_scrolled_window_equals_fresh_window(atrium, bounces, shift):
    """Window A computed at frame f then scrolled to B (no recomputation)
    against a cache computed at B for the same frame (blend 1: no history).
    1 bounce: equal (float rounding) at every cell active in both. 2 bounces:
    a secondary ray reads the previous bounce only inside its own window, so
    equality is asserted at cells at least secondary_distance + 2 cells from
    both windows' faces."""
    v = views.single(atrium)
    kw = dict(window=12, resolution=16, bounces=bounces, blend=1.0, depth_stride=1, secondary_distance=2.0)
    probe = methods.create("crc", atrium, volume="camera", **kw)
    A = _centre(probe)
    B = A + np.array(shift)
    gbs = frame_gbuffers(atrium, v, 0, W, H)
    a = _pinned(atrium, A, **kw)
    a.render(FrameContext(0), gbs, NullTimer())
    act_a = {tuple(x) for x in _cells(a, np.array(a.active))}
    a.place(B)                                    # scroll only
    assert a.region.moves == 1
    b = _pinned(atrium, B, **kw)
    b.render(FrameContext(0), gbs, NullTimer())
    cb = np.array(b.active)
    wb = _cells(b, cb)
    keep = np.array([tuple(x) in act_a for x in wb])
    if bounces > 1:
        margin = int(kw["secondary_distance"]) + 2
        for o in (A, B):
            loc = wb - o
            keep &= np.all((loc >= margin) & (loc < kw["window"] - margin), axis=1)
    assert keep.sum() >= 20, "too few common cells to compare"
    ca, cbv = _coeffs(a)[:, cb[keep]], _coeffs(b)[:, cb[keep]]
    assert np.abs(ca[0]).max() > 0.0
    err = np.abs(ca - cbv).max() / np.abs(cbv).max()
    assert err < 1e-5, f"scrolled vs fresh: max relative difference {err:.2e}"
    # history scrolled too: the common cells count as occupied last frame
    assert np.all(np.array(a.hist)[cb[keep]] == 1)


@pytest.mark.fresh_process
def test_moving_window_builds_no_kernels(atrium):
    """After warm-up, frames whose window moves to corners never seen
    before build no kernel (none compiled, none loaded from disk: the
    window's origin and shift are opaque inputs). Would fail if the origin
    were baked into the kernels as a literal."""
    # Free what earlier tests left: their scenes' emitters, once collected, change the set of instances
    # a virtual call (the RSM's sample_ray) dispatches over, hence its kernel; and flush queued work
    gc.collect()
    dr.eval()
    dr.sync_thread()
    v = views.single(atrium)
    gbs = frame_gbuffers(atrium, v, 0, W, H)
    m = methods.create("crc", atrium, volume="camera", window=8, resolution=16, bounces=2)
    c = _centre(m)
    offsets = [c, c + [1, 0, 0], c + [1, 1, 0], c + [0, 1, -1], c + [-1, 0, 1], c + [2, -1, 0]]
    for f in range(3):
        m.region.corner = lambda gbs, o=offsets[f]: np.asarray(o, dtype=np.int64)
        dr.eval(m.render(FrameContext(f), gbs, NullTimer()))
    dr.sync_thread()
    with KernelCounter() as kc:
        kc.take()
        for f in range(3, 6):
            m.region.corner = lambda gbs, o=offsets[f]: np.asarray(o, dtype=np.int64)
            dr.eval(m.render(FrameContext(f), gbs, NullTimer()))
        dr.sync_thread()
        built = kc.take()
        hist = kc.last
    assert m.region.moves == 5
    assert built == 0, f"{built} kernels built or loaded while the window moved: {hist[:3]}"


def test_window_follows_camera_and_shades_nothing_outside(atrium):
    """Along the camera path the window re-centres on the viewer in whole
    cells; G-buffer points whose stencil leaves the window get exactly 0."""
    v = views.single(atrium)
    m = methods.create("crc", atrium, volume="camera", window=8, resolution=16)
    offs = []
    for f in range(0, 160, 40):
        gbs = frame_gbuffers(atrium, v, f, W, H)
        out = m.render(FrameContext(f), gbs, NullTimer())
        cam = np.asarray(gbs[0].camera.origin, float)
        cell = np.floor((cam - m.world.lo) / m.world.h).astype(int)
        assert np.array_equal(cell - m.region.offset, [m.window // 2] * 3)
        offs.append(m.region.offset.copy())
    assert m.region.moves >= 1 and len({tuple(o) for o in offs}) >= 2
    gb = gbs[0]
    from slc.methods.crc.bounces import front_normal
    q = gb.si.p + front_normal(gb.si) * (0.5 * m.grid.h)
    outside = np.array(gb.valid & ~m.region.in_window(gb.si.p, q))
    img = np.array(out[0])
    assert outside.sum() > 0
    assert np.all(img[:, outside] == 0.0) if img.shape[0] == 3 else np.all(img[outside] == 0.0)
    assert img.max() > 0.0
