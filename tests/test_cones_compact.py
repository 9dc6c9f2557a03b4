"""The quadrature's pixels packed into a launch of their own (``ConeShading(compact=True)``,
the default; docs/cones.md): the same values bit for bit as the quadrature
in a branch of the launch of all pixels, whatever share of the pixels takes it (none, some,
all), frozen and not, with the shading options that send other pixels to the quadrature;
one recording for calls whose packed widths differ; the method's images unchanged."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import render_frames
from slc import methods
from slc.scene import scenes, views
from slc.lib.cones import shading as shmod
from slc.lib.cones.shading import ConeShading

W, H = 48, 27


@pytest.fixture(scope="module")
def captured():
    """The inputs of a batched shading call of 3 atrium viewers (60 % overlap), frame 5."""
    sc = scenes.load("atrium")
    cap = {}
    orig = ConeShading.__call__

    def grab(self, *a, **k):
        cap["call"] = (self, a, k)
        return orig(self, *a, **k)
    ConeShading.__call__ = grab
    try:
        m = methods.create("slc", sc, seed=3)
        render_frames(sc, m, views.overlap_rig(sc, 3, 0.6), frames=6, width=W, height=H, seed=3)
    finally:
        ConeShading.__call__ = orig
    return sc, cap["call"]


def _shade(call, active=None, freeze=False, **opts):
    """One shading of the captured inputs."""
    self, a, k = call
    sh = ConeShading(self.max_cones, table=self.table, freeze=freeze, **opts)
    storage, slot, ok, si, tf, ns, key, pid, ef = a
    return sh, sh(storage, slot, ok if active is None else active, si, tf, ns, key, pid, ef)


def _sampled(call, **opts):
    """Which pixels take the quadrature: those where a quadrature returning a marker
    (1e30) shows it."""
    orig = shmod.quadrature
    shmod.quadrature = lambda bsdf, si, ctx, sampled, *rest: mi.Color3f(dr.select(sampled, 1e30, 0.0))
    try:
        v = np.array(_shade(call, compact=False, **opts)[1])
    finally:
        shmod.quadrature = orig
    return v[0] == 1e30


@pytest.mark.slow
@pytest.mark.parametrize("opts", [{}, {"principled": "sample"}, {"conductor": "sg", "principled": "sample"}, {"glossy": "half"},
                                  {"horizon": False}])
def test_compact_equals_branch(captured, opts):
    """Packed and in-branch quadrature: the same values bit for bit; the quadrature ran on
    some pixels and not on others (else the test would say nothing)."""
    _, call = captured
    a = np.array(_shade(call, compact=False, **opts)[1])
    b = np.array(_shade(call, compact=True, **opts)[1])
    q = _sampled(call, **opts)
    n = q.size
    assert 0 < q.sum() < n, f"{q.sum()} of {n} pixels on the quadrature"
    assert np.all(np.isfinite(a)) and a.max() > 0
    assert np.array_equal(a, b)


@pytest.mark.slow
def test_compact_no_and_all_quadrature_pixels(captured):
    """None of the active pixels on the quadrature (only the last pixel of the packed
    launch, masked off), and only quadrature pixels: the same values as in a branch."""
    _, call = captured
    self, a, _ = call
    ok = np.array(mi.Bool(a[2]))
    q = _sampled(call)
    for mask in (ok & ~q, ok & q, np.zeros_like(ok)):
        act = mi.Bool(mask)
        x = np.array(_shade(call, active=act, compact=False)[1])
        y = np.array(_shade(call, active=act, compact=True)[1])
        assert np.array_equal(x, y)
        assert np.all(x[:, ~mask] == 0)


@pytest.mark.slow
@pytest.mark.fresh_process
def test_compact_frozen_one_recording(captured):
    """Frozen: calls whose packed launch has another width (other pixels active) replay
    the one recording and give the unfrozen values."""
    _, call = captured
    self, a, _ = call
    ok = np.array(mi.Bool(a[2]))
    rng = np.random.default_rng(1)
    sh = ConeShading(self.max_cones, table=self.table, freeze=True, compact=True)
    storage, slot, _, si, tf, ns, key, pid, ef = a
    widths = set()
    for keep in (1.0, 0.7, 0.4, 0.9):
        act = mi.Bool(ok & (rng.random(ok.size) < keep))
        got = np.array(sh(storage, slot, act, si, tf, ns, key, pid, ef))
        ref = np.array(_shade(call, active=act, compact=False)[1])
        assert np.array_equal(got, ref)
        widths.add(int((np.array(act) & _sampled(call)).sum()))
    assert len(widths) > 1
    assert sh.n_recordings == 1


@pytest.mark.slow
def test_compact_frozen_after_a_call_without_quadrature_pixels(captured):
    """Frozen: a first call in which no active pixel takes the quadrature (the packed launch
    holds only the always-taken pixels, masked off; the adaptive cache's warm-up frames
    with no entry in cones), then calls with many: the unfrozen values. (A packed launch of
    width 1 recorded first loaded its inputs as scalars in every replay: all quadrature
    pixels got one pixel's value, most of them 0.)"""
    _, call = captured
    self, a, _ = call
    ok = np.array(mi.Bool(a[2]))
    q = _sampled(call)
    storage, slot, _, si, tf, ns, key, pid, ef = a
    sh = ConeShading(self.max_cones, table=self.table, freeze=True, compact=True)
    sh(storage, slot, mi.Bool(ok & ~q), si, tf, ns, key, pid, ef)
    rng = np.random.default_rng(2)
    for keep in (1.0, 0.6):
        act = mi.Bool(ok & (rng.random(ok.size) < keep))
        got = np.array(sh(storage, slot, act, si, tf, ns, key, pid, ef))
        ref = np.array(_shade(call, active=act, compact=False)[1])
        assert (np.array(act) & q).sum() > 10
        assert np.array_equal(got, ref)


@pytest.mark.slow
def test_method_images_unchanged():
    """The method's images with ``compact=on`` (default) and ``off``: bit for bit."""
    sc = scenes.load("atrium")
    rig = views.overlap_rig(sc, 2, 0.6)
    out = []
    for spec in ("slc:compact=off", "slc"):
        imgs, _ = render_frames(sc, methods.create(spec, sc, seed=3), rig, frames=4, width=W, height=H, seed=3)
        out.append(imgs)
    for a, b in zip(*out):
        assert a.max() > 0 and np.array_equal(a, b)


def test_erf_saturates():
    """The far-cap shortcut of the SG lobe (``shading._sg_cone``) rests on Dr.Jit's erf
    being -1 exactly for arguments <= -4 (down to -inf)."""
    x = mi.Float(np.concatenate([-np.geomspace(4.0, 3e38, 4000), [-np.inf, -4.0]]).astype(np.float32))
    assert np.all(np.array(dr.erf(x)) == -1.0)
    assert float(dr.erf(mi.Float(-3.5))[0]) > -1.0          # (not saturated above: the test can fail)


@pytest.mark.slow
@pytest.mark.parametrize("opts", [{}, {"conductor": "sg"}])
def test_far_cap_shortcut_same_values(captured, opts, monkeypatch):
    """Principled (and GGX conductor) pixels: the SG lobe's share of caps far from the peak
    skipped (+0) or computed: the same values bit for bit. Some caps are far (counted on
    the principled pixels) and some near (all skipped changes the values)."""
    _, call = captured
    a = np.array(_shade(call, **opts)[1])
    orig_if = dr.if_stmt
    seen = {"far": 0}

    def hook(mode):
        def if_stmt(*args, **kw):
            if kw.get("label") != "sg_share":
                return orig_if(*args, **kw)
            try:        # (countable where the branch is not itself inside a symbolic branch)
                seen["far"] += int(dr.count(~kw["cond"])[0])
            except RuntimeError:
                pass
            return kw["true_fn"](*kw["args"]) if mode == "near" else kw["false_fn"](*kw["args"])
        return if_stmt
    monkeypatch.setattr(shmod.dr, "if_stmt", hook("near"))
    b = np.array(_shade(call, **opts)[1])
    monkeypatch.setattr(shmod.dr, "if_stmt", hook("far"))
    c = np.array(_shade(call, **opts)[1])
    assert np.all(np.isfinite(a)) and a.max() > 0
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    if not opts:
        assert seen["far"] > 0
