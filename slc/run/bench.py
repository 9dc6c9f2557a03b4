"""Benchmarks that check our own overhead.

:func:`bench_rays` times, on the same scene, G-buffer and number of rays,
(a) Mitsuba's raw ``scene.ray_test`` on precomputed shadow rays, (b) our
RT-N kernel (light sample + shadow ray + BSDF evaluation per ray) and (c)
the light sampling alone, once per light sampler: Mitsuba's
``scene.sample_emitter_direction`` (``mitsuba``, the reference) and the
scene's emitter table (``table``, :mod:`slc.scene.emitter_sampling`, the
default). Each sampler's raw rays are the ones it samples, so (b)/(a) says
how much our baseline adds on top of casting the very rays it casts. The
measurements are interleaved round by round (one call of each per round,
medians over ``repeats`` rounds after one warm-up round), so that load
from other processes on a shared machine hits both samplers alike.
"""
from __future__ import annotations

import dataclasses
import hashlib
import statistics
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from slc import methods
from slc.core.errors import MethodError
from slc.core.keys import STREAM_CONE_UPDATE
from slc.lib.cones.packing import gather_words, unpack
from slc.lib.cones.cycle import shrink_test_plan
from slc.lib.cones.update import frame_rng, frame_u32
from slc.methods.rt.method import RandomLightSampling
from slc.run.experiment import runs_in_turn
from slc.run.pipeline import RunConfig, run_sequence
from slc.scene.gbuffer import frame_gbuffers
from slc.scene import scenes, views
from slc.scene.lights import emitter_sampling_as, rng, sample_light, sampler, visible

SAMPLERS = ("mitsuba", "table")


def _timed(fn) -> tuple[float, float]:
    """(wall ms, of which host ms: the time until ``fn`` returned its unevaluated result,
    i.e. Python and Dr.Jit tracing)."""
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    t1 = time.perf_counter()
    dr.eval(out)
    dr.sync_thread()
    t2 = time.perf_counter()
    return (t2 - t0) * 1e3, (t1 - t0) * 1e3


STAGES = ("sample", "sample+ray")


def _partial_loop(sc, gb, n: int, stage: str) -> mi.Color3f:
    """RT-N's loop cut after a stage: the light samples alone (``sample``), or
    with their shadow rays (``sample+ray``); no BSDF. Same samples as RT-N."""
    si, active = gb.si, gb.valid
    smp = rng(gb.size, 0, stream=1)
    n_opaque = dr.opaque(mi.UInt32, n)

    def body(i, L, smp):
        ds, w, ok = sample_light(sc, si, mi.Point2f(smp.next_float32(), smp.next_float32()), active)
        if stage == "sample+ray":
            ok = visible(sc, si, ds, ok)
        return i + 1, L + dr.select(ok, w, 0.0), smp

    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        _, L, _ = dr.while_loop(state=(mi.UInt32(0), mi.Color3f(0.0), smp), cond=lambda i, L, s: i < n_opaque,
                                body=body)
    return L


def bench_rays(scene_name: str = "atrium", width: int = 320, height: int = 180, n: int = 16,
               repeats: int = 5) -> dict:
    s = scenes.load(scene_name)
    gb = frame_gbuffers(s, views.single(s), 0, width, height)[0]
    sc = s.mi_scene

    # --------------- per-ray shading points: n rays per pixel ---------------
    count = gb.size * n
    idx = dr.arange(mi.UInt32, count)
    pix = idx // n
    si = dr.gather(mi.SurfaceInteraction3f, gb.si, pix)
    active = dr.gather(mi.Bool, gb.valid, pix)
    dr.eval(si, active)

    def light_samples():
        smp = rng(count, 1, stream=5)
        ds, w, ok = sample_light(sc, si, mi.Point2f(smp.next_float32(), smp.next_float32()), active)
        return ds.p, w, ok

    # --------------- the same shadow rays, precomputed, for raw ray_test ---------------
    calls, info = {}, {}
    for mode in SAMPLERS:
        with emitter_sampling_as(mode):
            tab = sampler(sc)
            info[mode] = tab.describe() if tab is not None else {"entries": 0}
            smp = rng(count, 1, stream=5)
            ds, _, ok = sample_light(sc, si, mi.Point2f(smp.next_float32(), smp.next_float32()), active)
            rays = si.spawn_ray_to(ds.p)
            dr.eval(rays, ok)
        m = RandomLightSampling(s, n=n)

        def raw(rays=rays, ok=ok):
            return sc.ray_test(rays, ok)

        def ours(m=m, mode=mode):
            with emitter_sampling_as(mode):
                return m.shade(methods.FrameContext(0), None, 0, gb)

        def sample_only(mode=mode):
            with emitter_sampling_as(mode):
                return light_samples()

        calls[mode] = {"raw": raw, "ours": ours, "sample": sample_only}
    # where the default sampler's rt-N time goes: its loop cut after each stage
    for st in STAGES:
        def part(st=st):
            with emitter_sampling_as("table"):
                return _partial_loop(sc, gb, n, st)
        calls["table"]["loop:" + st] = part

    # --------------- interleaved rounds ---------------
    times = {(mode, k): [] for mode in SAMPLERS for k in calls[mode]}
    host = {key: [] for key in times}
    for r in range(repeats + 1):
        for mode in SAMPLERS:
            for k, fn in calls[mode].items():
                t, h = _timed(fn)
                if r > 0:
                    times[(mode, k)].append(t)
                    host[(mode, k)].append(h)
    med = {key: statistics.median(v) for key, v in times.items()}

    out = {"scene": s.name, "rays": count, "n": n, "width": width, "height": height, "samplers": {}}
    for mode in SAMPLERS:
        raw_ms, ours_ms, smp_ms = med[(mode, "raw")], med[(mode, "ours")], med[(mode, "sample")]
        out["samplers"][mode] = {"raw_ms": raw_ms, "ours_ms": ours_ms, "sample_ms": smp_ms,
                                 "raw_mrays": count / raw_ms / 1e3, "ours_mrays": count / ours_ms / 1e3,
                                 "ratio": ours_ms / raw_ms, "table": info[mode],
                                 "ours_host_ms": statistics.median(host[(mode, "ours")])}
    out["stages"] = {st: med[("table", "loop:" + st)] for st in STAGES}
    out["load"] = _loadavg()
    # the default sampler's figures at the top level
    out.update({k: out["samplers"]["table"][k] for k in ("raw_ms", "ours_ms", "raw_mrays", "ours_mrays", "ratio")})
    return out


def _loadavg() -> list[float] | None:
    try:
        with open("/proc/loadavg") as f:
            return [float(x) for x in f.read().split()[:3]]
    except (OSError, ValueError):
        return None


def report_lines(r: dict) -> list[str]:
    """The lines ``slc bench rays`` prints."""
    n = r["n"]
    lines = [f"scene {r['scene']} {r['width']}x{r['height']}, {r['rays']} shadow rays per pass "
             f"(medians of interleaved rounds):"]
    for mode in SAMPLERS:
        x = r["samplers"][mode]
        what = ("Mitsuba's sample_emitter_direction (reference)" if mode == "mitsuba"
                else f"emitter table ({x['table'].get('entries', 0)} entries, default)")
        lines += [f" light sampler: {what}",
                  f"  raw scene.ray_test      : {x['raw_ms']:8.2f} ms  {x['raw_mrays']:7.1f} Mrays/s",
                  f"  light sampling alone    : {x['sample_ms']:8.2f} ms",
                  f"  rt{n} (sample+ray+BSDF) : {x['ours_ms']:8.2f} ms  {x['ours_mrays']:7.1f} Mrays/s",
                  f"  ratio ours/raw          : {x['ratio']:.2f}x (target <= 1.5x)"]
    t = r["samplers"]["table"]
    raw, st = t["raw_ms"], r.get("stages", {})
    if st:
        lines.append(f" where rt{n}'s time goes (table; rt{n}'s loop cut after each stage, / raw ray_test): "
                     f"samples {st['sample'] / raw:.2f}x, + shadow rays {st['sample+ray'] / raw:.2f}x, "
                     f"+ BSDF (rt{n}) {t['ratio']:.2f}x, of which host (tracing) {t['ours_host_ms'] / raw:.2f}x")
    a, b = r["samplers"]["mitsuba"], r["samplers"]["table"]
    lines.append(f" table / mitsuba: rt{n} {b['ours_ms'] / a['ours_ms']:.2f}x, "
                 f"light sampling {b['sample_ms'] / a['sample_ms']:.2f}x")
    if r.get("load"):
        lines.append(" load average (1, 5, 15 min) after the run: " + ", ".join(f"{x:.2f}" for x in r["load"]))
    return lines


# ---------------------------------------------------------------------------
# slc's frame next to the rays of its own update
# ---------------------------------------------------------------------------

def _update_rays(sc, cap: dict, p, seed: int):
    """The rays one slc update traces, precomputed (nothing else left to do):
    ``rays[i]`` shadow rays per active entry toward light samples drawn with
    the update's own sampler (:func:`slc.scene.lights.sample_light`, the scene's emitter
    table; independent random numbers instead of the entry's R2 sequence: the same
    distribution of rays), and the shrink test's closest-hit rays, made by the
    update's own :func:`slc.lib.cones.cycle.shrink_test_plan` (directions and
    schedule) on the entries' cone records before the update.
    Returns (shadow rays, their mask, shrink rays, their mask)."""
    si, rays, words = cap["si"], cap["rays"], cap["words"]
    N = dr.width(rays)
    # --------------- shadow rays: entry i repeated rays[i] times ---------------
    idx = mi.UInt32(np.repeat(np.arange(N, dtype=np.uint32), rays.numpy().astype(np.int64)))
    si_r = dr.gather(mi.SurfaceInteraction3f, si, idx)
    smp = rng(dr.width(idx), seed, stream=7)
    ds, _, ok = sample_light(sc, si_r, mi.Point2f(smp.next_float32(), smp.next_float32()), si_r.is_valid())
    shadow = si_r.spawn_ray_to(ds.p)
    # --------------- shrink-test rays: one per tested cone ---------------
    D, A, _, _, n = unpack(words, p.max_cones)
    sampler = frame_rng(cap["keys"], seed, frame_u32(cap["frame"]), STREAM_CONE_UPDATE)
    dirs, tested = shrink_test_plan(D, A, n, cap["keys"], si.is_valid(), cap["unsettled"], sampler, cap["frame"], p)
    o, d, m = [], [], []
    for i in range(p.max_cones):
        r = si.spawn_ray(si.sh_frame.to_world(dirs[i]))
        o.append(r.o.numpy()), d.append(r.d.numpy()), m.append(tested[i].numpy())
    shrink = mi.Ray3f(mi.Point3f(np.concatenate(o, axis=1)),
                      mi.Vector3f(np.concatenate(d, axis=1)))
    shrink_ok = mi.Bool(np.concatenate(m))
    dr.eval(shadow, ok, shrink, shrink_ok)
    return shadow, ok, shrink, shrink_ok


def bench_update(scene_name: str = "atrium", width: int = 320, height: int = 180, frames: int = 24,
                 warmup: int = 10, repeats: int = 5, method: str = "slc") -> dict:
    """slc's frame time next to the time of the rays its update traces, alone.

    One viewer on the scene's first camera path (the single-viewer experiment's rig)
    renders ``frames`` frames; the update's inputs of the last frame are kept (the
    active entries' surface points, their ray counts, shrink-test schedule and cone
    records before the update). Its rays are then traced alone, ``repeats`` times:
    ``scene.ray_test`` on the shadow rays and ``scene.ray_intersect_preliminary``
    on the shrink test's rays (Mitsuba's raw traversal, no surface interaction).
    The ratios frame / rays and update / rays say how much the method adds on top
    of the rays it must cast (the target: frame <= 1.5x its update's rays)."""
    s = scenes.load(scene_name)
    m = methods.create(method, s, seed=0)
    if not hasattr(m, "cone_params"):
        raise MethodError(f"bench update: method {method!r} has no cone update (use slc or slc:...)")
    cap: dict = {}
    own_update = m.update
    last = frames - 1

    def update(ctx, fr, policy):
        if ctx.frame == last:     # no kernel in a timed frame: references, and a host copy of the
            # records before the update (the update writes them in place)
            cap.update(storage=np.array(m.storage.numpy()), active=fr.active, si=fr.si, rays=mi.UInt32(policy.rays),
                       unsettled=mi.Bool(policy.unsettled), keys=mi.UInt32(fr.keys), frame=ctx.frame)
        return own_update(ctx, fr, policy)

    m.update = update
    res = run_sequence(s, m, views.single(s), RunConfig(width=width, height=height, frames=frames, warmup=warmup,
                                                        eval_frames=[], keep_images=False,
                                                        measure_overlap=False))
    sc = s.mi_scene
    cap["words"] = gather_words(mi.UInt32(cap.pop("storage")), cap.pop("active"), m.max_cones)
    shadow, ok, shrink, shrink_ok = _update_rays(sc, cap, m.cone_params, 0)

    # --------------- the rays alone, interleaved rounds ---------------
    calls = {"shadow": lambda: sc.ray_test(shadow, ok),
             "shrink": lambda: sc.ray_intersect_preliminary(shrink, shrink_ok).t}
    times = {k: [] for k in calls}
    for r in range(repeats + 1):
        for k, fn in calls.items():
            t, _ = _timed(fn)
            if r > 0:
                times[k].append(t)
    med = {k: statistics.median(v) for k, v in times.items()}
    rays_ms = med["shadow"] + med["shrink"]
    st = res.stages
    frame_ms = res.time_ms
    return {"scene": s.name, "method": m.label or m.name, "width": width, "height": height, "frames": frames,
            "warmup": warmup, "entries": dr.width(cap["rays"]),
            "shadow_rays": int(dr.count(ok)[0]), "shrink_rays": int(dr.count(shrink_ok)[0]),
            "shadow_ms": med["shadow"], "shrink_ms": med["shrink"], "rays_ms": rays_ms,
            "frame_ms": frame_ms, "update_ms": st.get("update", 0.0), "stages_ms": dict(st),
            "stages_kernel_ms": dict(res.stages_kernel),
            "frame_vs_rays": frame_ms / max(rays_ms, 1e-9), "update_vs_rays": st.get("update", 0.0) / max(rays_ms, 1e-9),
            "compiled_after_warmup": res.compiled_after_warmup,
            "recordings_after_warmup": res.recordings_after_warmup, "load": _loadavg()}


def update_report_lines(r: dict) -> list[str]:
    """The lines ``slc bench update`` prints."""
    st = ", ".join(f"{k} {v:.1f}" for k, v in r["stages_ms"].items())
    lines = [f"scene {r['scene']} {r['width']}x{r['height']}, {r['method']}, one viewer, {r['frames']} frames "
             f"({r['warmup']} warm-up; frame = median ms per frame after warm-up):",
             f"  frame                     : {r['frame_ms']:8.2f} ms  ({st})",
             f"  its update's rays alone   : {r['rays_ms']:8.2f} ms  ({r['shadow_rays']} shadow rays "
             f"{r['shadow_ms']:.2f} ms + {r['shrink_rays']} shrink-test rays {r['shrink_ms']:.2f} ms, "
             f"{r['entries']} entries; last frame's update)",
             f"  ratio frame / rays        : {r['frame_vs_rays']:.2f}x (target <= 1.5x)",
             f"  ratio update / rays       : {r['update_vs_rays']:.2f}x",
             f"  kernels after warm-up     : {r['compiled_after_warmup']}",
             f"  recordings after warm-up  : {r.get('recordings_after_warmup', 0)}"]
    if r.get("load"):
        lines.append(" load average (1, 5, 15 min) after the run: " + ", ".join(f"{x:.2f}" for x in r["load"]))
    return lines


# ---------------------------------------------------------------------------
# Two method settings timed in turn
# ---------------------------------------------------------------------------

def image_md5(img) -> str:
    """md5 of an image's float32 values (bit-identical images give the same digest)."""
    return hashlib.md5(np.ascontiguousarray(np.asarray(img, np.float32)).tobytes()).hexdigest()


def bench_ab(scene_name: str, spec_a: str, spec_b: str, width: int = 160, height: int = 90, frames: int = 24,
             warmup: int | None = None, repeats: int = 3, seed: int = 0, ref_spp: int | None = None) -> dict:
    """Two method settings on one viewer (the scene's first camera path), timed in turn in one
    process (:func:`slc.run.experiment.runs_in_turn`: A, B; B, A; ...), each repetition a whole
    :func:`slc.run.pipeline.run_sequence` of ``frames`` frames with a new method instance.

    Per setting: the median over repetitions of the median ms per frame after ``warmup``
    (default ``frames // 3``), the median stage times, the most kernels any timed frame built,
    the metrics of the last frame against the reference of the method's output kind (first
    repetition only; ``ref_spp``: samples of an indirect reference, default
    :data:`slc.reference.references.INDIRECT_SAMPLES`) and the md5 of the last frame's image in every
    repetition (equal digests of A and B: bit-identical images). ``ratio``: the median of B / A
    taken within each repetition, the ratio a drifting load on a shared machine moves least."""
    if frames < 1 or repeats < 1:
        raise ValueError("bench ab: frames and repeats must be at least 1")
    warmup = frames // 3 if warmup is None else warmup
    if not 0 <= warmup < frames:
        raise ValueError(f"bench ab: warm-up ({warmup}) must be below the frame count ({frames})")
    s = scenes.load(scene_name)
    for spec in (spec_a, spec_b):      # bad settings stop the run before anything is timed
        methods.create(spec, s, seed=seed)
    v = views.single(s)
    first = RunConfig(width=width, height=height, frames=frames, warmup=warmup, eval_frames=[frames - 1],
                      seed=seed, ref_spp=ref_spp, measure_overlap=False)
    rest = dataclasses.replace(first, eval_frames=[])
    runs = runs_in_turn(s, [(spec_a, v), (spec_b, v)], rest, repeats, seed, first_cfg=first)
    out = {"scene": s.name, "width": width, "height": height, "frames": frames, "warmup": warmup,
           "repeats": repeats, "seed": seed, "settings": []}
    for spec, rs in zip((spec_a, spec_b), runs):
        stages = {k: statistics.median(r.stages.get(k, 0.0) for r in rs) for k in rs[0].stages}
        out["settings"].append({
            "setting": spec, "time_ms": statistics.median(r.time_ms for r in rs), "times_ms": [r.time_ms for r in rs],
            "stages_ms": stages, "metrics": dict(rs[0].metrics),
            "compiled_after_warmup": max(r.compiled_after_warmup for r in rs),
            "md5": [image_md5(next(iter(r.last.values()))) for r in rs]})
    a, b = out["settings"]
    out["ratios"] = [tb / max(ta, 1e-9) for ta, tb in zip(a["times_ms"], b["times_ms"])]
    out["ratio"] = statistics.median(out["ratios"])
    out["load"] = _loadavg()
    return out


def ab_report_lines(r: dict) -> list[str]:
    """The lines ``slc bench ab`` prints."""
    lines = [f"scene {r['scene']} {r['width']}x{r['height']}, one viewer, {r['frames']} frames ({r['warmup']} "
             f"warm-up), {r['repeats']} repetitions in turn; time = median over repetitions of the median ms "
             f"per frame after warm-up; metrics of the last frame against its reference (first repetition)"]
    for tag, x in zip("AB", r["settings"]):
        st = ", ".join(f"{k} {v:.2f}" for k, v in x["stages_ms"].items())
        me = ", ".join(f"{k} {v:.4f}" for k, v in x["metrics"].items())
        same = "" if len(set(x["md5"])) == 1 else " (differs between repetitions)"
        lines += [f"  {tag} {x['setting']}",
                  f"    time {x['time_ms']:.2f} ms ({st}); kernels after warm-up {x['compiled_after_warmup']}",
                  f"    {me or 'no metrics'}; md5 {x['md5'][0]}{same}"]
    a, b = r["settings"]
    lines.append(f"  B / A time: {r['ratio']:.3f}x (per repetition: "
                 + ", ".join(f"{x:.3f}" for x in r["ratios"]) + ")")
    lines.append("  images: " + ("bit-identical" if a["md5"][0] == b["md5"][0] else "differ"))
    if r.get("load"):
        lines.append(" load average (1, 5, 15 min) after the run: " + ", ".join(f"{x:.2f}" for x in r["load"]))
    return lines
