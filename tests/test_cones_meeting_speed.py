"""Shortcuts of the cone update and shading for the meeting rig (docs/cones.md) that change
no image. Pixels seen from behind whose cones are all in
front skip the quadrature (it sums zeros); the insertion's cases C/D run in a symbolic
branch; the shrink test reads constant area emitters without the emitter's virtual call."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import plane_under_rect_light
from slc.lib.cones import closedforms as cfmod
from slc.methods.cones import update_kernel as upmod
from slc.lib.cones.shading import ConeShading, bsdf_table
from slc.scene.builder import diffuse, principled, rough_conductor


def _inputs(sc, frames=12):
    from test_cones import _storage_after
    return _storage_after(sc, frames)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["principled", "conductor", "diffuse"])
def test_backside_pixels_same_as_quadrature(kind, monkeypatch):
    """A plane seen from behind (w_i mirrored below the surface) with the cones of the
    lit front side: the shortcut's image equals the quadrature's bit for bit (zeros: a
    reflection-only BSDF sends nothing from w_i's side into cones on the other side),
    and the front-side image is unchanged by the shortcut."""
    b = {"principled": principled([0.45, 0.36, 0.28], roughness=0.22),
         "conductor": rough_conductor(0.12, "Cu"),
         "diffuse": diffuse([0.5, 0.4, 0.3])}[kind]
    sc = plane_under_rect_light(half=0.3, radiance=5.0, bsdf=b, name=f"back_{kind}")
    m, gb, slot, ok, tf = _inputs(sc)
    table = bsdf_table(sc)
    si_back = mi.SurfaceInteraction3f(gb.si)
    si_back.wi = mi.Vector3f(gb.si.wi.x, gb.si.wi.y, -gb.si.wi.z)

    def shade(si):
        return np.array(ConeShading(3, freeze=False, table=table)(m.storage, slot, ok, si, tf, 16, 5))
    front, back = shade(gb.si), shade(si_back)
    monkeypatch.setattr(cfmod, "BACK_MARGIN", float("inf"))      # no cone is ever "clear": the quadrature
    front_q, back_q = shade(gb.si), shade(si_back)
    assert np.abs(front).sum() > 0 and np.all(np.isfinite(front))
    assert np.array_equal(front, front_q)
    assert np.array_equal(back, back_q) and np.all(back == 0.0)


@pytest.mark.slow
def test_update_shortcuts_same_storage(monkeypatch):
    """The update's storage after 6 frames is the same bit for bit with the shrink
    test's emitter shortcut and with the emitter's virtual call, and with the insertion's
    cases C/D computed for every lane (the branch's condition always true)."""
    from slc.scene import scenes
    from slc.methods import create
    from test_cones import _run
    sc = scenes.load("cornell")
    assert upmod.constant_area_emitters(sc.mi_scene)

    def storage():
        m = create("slc", sc, seed=3)
        _run(sc, m, 6)
        return np.array(m.storage)
    fast = storage()
    monkeypatch.setattr(upmod, "constant_area_emitters", lambda scene: False)
    vcall = storage()
    orig_if = dr.if_stmt

    def always(*a, **kw):
        if kw.get("label") == "insert_full":
            return kw["true_fn"](*kw["args"])
        return orig_if(*a, **kw)
    monkeypatch.setattr(upmod.dr, "if_stmt", always)
    full = storage()
    assert fast.size > 0 and np.any(fast != 0)
    assert np.array_equal(fast, vcall) and np.array_equal(fast, full)
