"""The pt baseline's frozen estimator: the images of the traced estimator bit for bit, new random
numbers every frame (the frame's streams are inputs, not baked into the recording), a replay
after the first recordings."""
import numpy as np
import pytest

from slc import methods

from slc.scene import scenes, views
from slc.methods import FrameContext
from slc.scene.gbuffer import frame_gbuffers
from slc.core.timing import NullTimer


def _frames(spec, scene, frames=4):
    m = methods.create(spec, scene)
    vs = views.single(scene)
    out = []
    for f in range(frames):
        gbs = frame_gbuffers(scene, vs, 0, 24, 14)        # a still camera: only the random numbers change
        out.append([np.array(x) for x in m.render(FrameContext(f), gbs, NullTimer())])
    return m, out


@pytest.mark.fresh_process
def test_frozen_pt_matches_the_traced_estimator_and_changes_per_frame():
    s = scenes.load("cornell")
    for spec in ("pt:spp=2", "pt:spp=1,output=indirect,bounces=3"):
        m, fz = _frames(spec, s)
        _, tr = _frames(spec + ",freeze=0", s)
        for a, b in zip(fz, tr):
            assert np.array_equal(a[0], b[0]), spec
        assert not np.array_equal(fz[0][0], fz[1][0])        # other random numbers each frame
        assert m._kernel.frozen and m._kernel.calls == 4
        assert m._kernel.n_recordings <= 2, m._kernel.n_recordings   # replayed afterwards
