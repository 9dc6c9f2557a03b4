"""osc-gi on a scene whose surfaces have no diffuse albedo (a metal plane under a
light): no secondary cell traces rays. It crashed ("operands have incompatible
sizes (0, 1)" in the secondary update); now it renders, finite, with the indirect
light of the closed form (none)."""
import numpy as np

import slc.core.backend  # noqa: F401
from slc.methods import FrameContext, create
from slc.scene.gbuffer import frame_gbuffers
from slc.core.timing import NullTimer
from slc.scene.views import single
from test_cones_update_freeze import _growing_scene


def test_metal_only_scene_renders():
    sc = _growing_scene()
    full = create("osc-gi", sc)
    indirect = create("osc-gi:output=indirect", sc)
    for f in range(6):
        gbs = frame_gbuffers(sc, single(sc), f, 40, 30)
        img = np.array(full.render(FrameContext(f), gbs, NullTimer())[0])
        ind = np.array(indirect.render(FrameContext(f), gbs, NullTimer())[0])
    assert np.isfinite(img).all() and np.isfinite(ind).all()
    assert img.mean() > 0.0                   # the light reflected by the metal
    # closed form: a plane cannot light itself and the light's quad is black: no indirect light
    assert ind.max() == 0.0, ind.max()
