"""A VISIBILITY record's listed-light visible fraction as stored between updates
(slc/methods/adaptive/visibility/record.py): its running mean over ``VIS_WINDOW``
samples, quantized to ``VIS_BITS`` bits at every update, against closed forms."""
import drjit as dr
import mitsuba as mi
import numpy as np

from slc.methods.adaptive.visibility import record as rc

LANES = 4096


def _stored(v, cnt, rng):
    """The fraction and count after one pack and unpack of a one-slot record (the update's
    dither: a random word per lane)."""
    r = rc.empty(LANES, 1)
    r.idx, r.vis, r.cnt = [dr.arange(mi.UInt32, LANES)], [mi.Float(v)], [mi.UInt32(cnt)]
    out = rc.unpack(rc.pack(r, 1, dither=rng.next_uint32()), 1)
    dr.eval(out.vis[0], out.cnt[0], rng.state)
    return out.vis[0], out.cnt[0]


def _update(v, cnt, V):
    """The update's step for a sample of the listed light (visibility/update.py, ``take``)."""
    a = dr.rcp(mi.Float(dr.minimum(cnt + 1, rc.VIS_WINDOW)))
    return dr.fma(a, mi.Float(V) - v, v), dr.minimum(cnt + 1, rc.VIS_COUNT_MAX)


def _run(v, cnt, rng, samples):
    for V in samples:
        v, cnt = _stored(*_update(v, cnt, V), rng)
    return v, cnt


def test_fraction_returns_to_one_after_an_occluded_sample():
    """A fully lit entry whose count is settled takes one occluded sample, then lit ones only:
    its stored fraction must come back to 1 (rounded to nearest, the steps (1 - v)/n fall
    below half a quantum and the fraction stays 1 - n/(2 q) below, 3% at 8 bits and n = 16)."""
    rng = mi.PCG32(LANES, dr.arange(mi.UInt64, LANES))
    v, cnt = _stored(dr.full(mi.Float, 1.0, LANES), dr.full(mi.UInt32, rc.VIS_COUNT_MAX, LANES), rng)
    v, cnt = _run(v, cnt, rng, [False] + [True] * (2 * rc.VIS_WINDOW))
    mean = np.array(v).mean()
    assert mean > 0.995, mean


def test_fraction_is_an_unbiased_running_mean_with_a_window_of_64():
    """Bernoulli(p) samples per lane: the stored fraction's mean is p and its spread the
    exponential running mean's, sqrt(p (1 - p) a / (2 - a)) with a = 1/64 (0.044 at p = 1/2;
    a window of 16 gives 0.090)."""
    rng = mi.PCG32(LANES, dr.arange(mi.UInt64, LANES))
    p = 0.5
    v, cnt = dr.zeros(mi.Float, LANES), dr.zeros(mi.UInt32, LANES)
    for _ in range(4 * rc.VIS_WINDOW):
        V = rng.next_float32() < p
        v, cnt = _stored(*_update(v, cnt, V), rng)
    x = np.array(v)
    a = 1.0 / rc.VIS_WINDOW
    assert abs(x.mean() - p) < 0.005, x.mean()
    assert x.std() < 1.1 * np.sqrt(p * (1 - p) * a / (2 - a)), x.std()
    assert x.std() < 0.06, x.std()
