"""MegaViews frames build no kernels after warm-up (``compiled_after_warmup``
== 0 through :func:`slc.run.pipeline.run_sequence`), although the VPL count, the
view hierarchy, the traversal's level widths and the gathering's walk change
every frame; numpy arrays that Dr.Jit would map at unaligned addresses (new
kernels) are aligned by
:func:`slc.methods.megaviews.hierarchy.aligned`.

Each pipeline case runs in a fresh process (as ``tests/test_compile.py``):
kernels an earlier case built would hide one a case builds anew.
"""
import numpy as np
import pytest

from helpers import run_case

pytestmark = pytest.mark.slow      # fresh interpreters counting kernels

FRAMES, WARMUP = 8, 2

_CASE = r"""
import json, sys
from slc import methods
from slc.scene import scenes, views
from slc.run.pipeline import RunConfig, run_sequence
spec, F, WU = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
s = scenes.load("cornell")
cfg = RunConfig(width=16, height=16, frames=F, warmup=WU, eval_frames=[], keep_images=False,
                measure_overlap=False)
m = methods.create(spec, s)
res = run_sequence(s, m, views.make_rig(s, "single", 1), cfg)
print("RESULT " + json.dumps({"compiled_after_warmup": res.compiled_after_warmup,
                              "per_frame": [f["compiled"] for f in res.frames_ms]}))
"""


@pytest.mark.parametrize("spec", ["megaviews:views=512,scene_depth=5,view_depth=5",
                                  "manylods:views=256,scene_depth=5"])
def test_no_kernel_built_after_warmup(spec):
    r = run_case(_CASE, spec, FRAMES, WARMUP, timeout=900)
    per = r["per_frame"]
    assert len(per) == FRAMES and sum(per[:WARMUP]) > 0     # the counter saw the warm-up's kernels
    assert r["compiled_after_warmup"] == sum(per[WARMUP:]) == 0, f"{spec}: kernels built per frame {per}"


_ALIGN = r"""
import json
import drjit as dr
import mitsuba as mi
import numpy as np
import slc  # noqa: F401  (sets the variant)
from slc.methods.megaviews.hierarchy import aligned
from slc.core.timing import KernelCounter

src = dr.arange(mi.Float, 100) * 0.5 + 7.25
dr.eval(src)
base = np.zeros(64 + 16, dtype=np.uint32)        # buf starts on a 64-byte boundary, so the views
off = ((-base.ctypes.data) % 64) // 4            # below start aligned and misaligned whatever the
buf = base[off:off + 64]                         # allocator returned
buf[:] = np.arange(64, dtype=np.uint32)


def run(make):
    counts = []
    with KernelCounter() as kc:
        for k in range(8):          # views starting at 8 consecutive 4-byte offsets
            kc.take()
            idx = make(buf[k:k + 17])
            r = dr.gather(mi.Float, src, idx) * 3.0 + 1.0
            dr.eval(r)
            assert np.allclose(np.array(r), (buf[k:k + 17] * 0.5 + 7.25) * 3.0 + 1.0)
            counts.append(kc.take())
    return counts


raw = run(lambda a: mi.UInt32(a))
fixed = run(lambda a: mi.UInt32(aligned(a, np.uint32)))
print("RESULT " + json.dumps({"raw": raw, "fixed": fixed}))
"""


def test_aligned_numpy_input_gives_one_kernel():
    """A gather indexed by numpy data, in a fresh process (kernels an earlier test
    built would hide the ones this one builds): mapped from numpy views at shifted
    addresses it is built once per alignment class (the counter sees it); through
    ``aligned`` it is built once for all."""
    r = run_case(_ALIGN)
    assert sum(r["raw"]) >= 2, r["raw"]          # misaligned and aligned views: different kernels
    assert sum(r["fixed"][1:]) == 0, r["fixed"]
