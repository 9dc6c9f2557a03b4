"""Benchmarks that check our own overhead.

:func:`bench_rays` times, on the same scene, G-buffer and number of rays,
(a) Mitsuba's raw ``scene.ray_test`` on precomputed shadow rays and (b) our
RT-N kernel (light sample + shadow ray + BSDF evaluation per ray). The
ratio (b)/(a) says how much our baseline adds on top of ray casting.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import scenes, views
from .baselines.rt import RandomLightSampling
from .lights import rng, sample_light
from .pipeline import gbuffers_for
from .timing import time_call


def bench_rays(scene_name: str = "atrium", width: int = 320, height: int = 180, n: int = 16,
               repeats: int = 5) -> dict:
    s = scenes.load(scene_name)
    gb = gbuffers_for(s, views.single(s), 0, width, height)[0]
    sc = s.mi_scene

    # --------------- the same shadow rays, precomputed, for raw ray_test ---------------
    count = gb.size * n
    idx = dr.arange(mi.UInt32, count)
    pix = idx // n
    si = dr.gather(mi.SurfaceInteraction3f, gb.si, pix)
    active = dr.gather(mi.Bool, gb.valid, pix)
    sampler = rng(count, 1, stream=5)
    ds, _, ok = sample_light(sc, si, mi.Point2f(sampler.next_float32(), sampler.next_float32()), active)
    rays = si.spawn_ray_to(ds.p)
    dr.eval(rays, ok)
    dr.sync_thread()
    raw_ms, _ = time_call(lambda: sc.ray_test(rays, ok), repeats=repeats)

    m = RandomLightSampling(s, n=n)
    ours_ms, _ = time_call(lambda: m.shade(gb, 0, 0), repeats=repeats)
    return {"scene": s.name, "rays": count, "raw_ms": raw_ms, "ours_ms": ours_ms,
            "raw_mrays": count / raw_ms / 1e3, "ours_mrays": count / ours_ms / 1e3,
            "ratio": ours_ms / raw_ms}
