"""Render nodes sharing one cache (slc.distributed): the owner protocol in one process, in
separate processes (Ray actors on a local multi-node cluster), a lost node, latency hiding."""
from __future__ import annotations

import json
import os
import pickle
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from slc import methods
from slc.core import backend
from slc.core.timing import NullTimer
from slc.distributed.cluster import Cluster, InProcess
from slc.distributed.messages import Requests, decode_addresses, decode_bits, encode_addresses, encode_bits
from slc.distributed.node import KINDS, Node
from slc.distributed.rig import Strategy, ViewerPoses, assignment, extrapolated
from slc.distributed.owners import Regions, changed_records, owners
from slc.distributed.records import codec_for
from slc.distributed.seeds import ancestors
from slc.distributed.state import Client, Subscriptions
from slc.methods import FrameContext
from slc.scene.gbuffer import frame_gbuffers
from slc.scene import views
from slc.scene.camera import Camera

W, H, FRAMES = 48, 27, 4


def _plain(scene, spec, vs, frames):
    """The single-process shared cache's images of the last frame (the pipeline's method)."""
    m = methods.create(spec, scene, seed=0)
    for f in range(frames):
        outs = m.render(FrameContext(frame=f), frame_gbuffers(scene, vs, f, W, H), NullTimer())
    return {v: np.array(o) for v, o in enumerate(outs)}


def _in_process(scene, spec, vs, n_nodes, strategy, frames=FRAMES):
    poses = [ViewerPoses.of(v, frames) for v in vs]
    assign = assignment(poses, n_nodes)
    nodes = {n: Node(n, sorted(assign), scene, spec, assign[n], W, H, strategy) for n in assign}
    return Cluster(InProcess(nodes), sorted(assign), strategy.delay)


def _run(cluster, frames=FRAMES, kill=None):
    """Every frame; ``kill``: (frame, node) ended before that frame. Returns the last frame's
    images (viewer -> array), results and the frames' outputs."""
    outs = []
    for f in range(frames):
        if kill is not None and f == kill[0]:
            cluster.kill(kill[1])
        outs.append(cluster.step(f, images=f == frames - 1))
    images = {}
    for r in outs[-1]["results"].values():
        images.update(r["images"])
    return images, outs


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["slc", "adaptive"])
def test_nodes_with_threshold_0_and_delay_0_render_the_single_process_images(scene, spec):
    """Three nodes, each with its own cache and its own viewers' G-buffers only, a moving rig:
    sparse updates at threshold 0 and full replication give the single-process cache's images bit
    for bit (new entries seeded from the finest coarser entry anywhere); sparse sends fewer bytes;
    the bytes by kind add up."""
    s = scene("atrium")
    vs = views.overlap_rig(s, 6, 0.5, aspect=W / H)
    plain = _plain(s, spec, vs, FRAMES)
    sent = {}
    for st in (Strategy("sparse", 0, 0.0, 8), Strategy("full")):
        images, outs = _run(_in_process(s, spec, vs, 3, st))
        assert sorted(images) == list(range(len(vs)))
        for v, img in images.items():
            assert np.array_equal(img, plain[v]), (st.label, v)
        for o in outs:
            assert sum(o["kinds"].values()) == o["bytes"] and o["serialized"] > 0
            assert all(r["missing"] == 0 for r in o["results"].values())
        sent[st.kind] = sum(o["bytes"] for o in outs[1:])
        if spec == "slc":
            assert sum(o["kinds"]["seeds"] for o in outs[1:]) > 0       # the moving rig's new entries have seeds
    assert sent["sparse"] < sent["full"]


@pytest.mark.slow
def test_a_delay_leaves_pixels_waiting_and_bootstrap_and_prediction_fill_them(scene):
    """Messages 2 frames late on a moving rig: without hiding, pixels of entries whose record is
    on its way are black; bootstrap rays give every such pixel a value; requests from the
    cameras' extrapolated motion leave fewer of them waiting."""
    s = scene("atrium")
    vs = views.overlap_rig(s, 4, 0.5, aspect=W / H)
    missing = {}
    for st in (Strategy("sparse", 2, 0.065, 8), Strategy("sparse", 2, 0.065, 8, bootstrap=4),
               Strategy("sparse", 2, 0.065, 8, predict=True)):
        _, outs = _run(_in_process(s, "slc", vs, 2, st, frames=8), frames=8)
        missing[st.hiding] = sum(r["missing"] for o in outs[1:] for r in o["results"].values())
        if st.bootstrap:
            assert sum(r["boot_rays"] for o in outs for r in o["results"].values()) > 0
    assert missing["none"] > 0 and missing["bootstrap"] == 0, missing
    assert missing["predict"] < missing["none"], missing


@pytest.mark.slow
def test_a_lost_node_in_process_moves_only_its_entries_and_the_run_goes_on(scene):
    s = scene("atrium")
    vs = views.overlap_rig(s, 6, 0.5, aspect=W / H)
    cluster = _in_process(s, "slc", vs, 3, Strategy("sparse", 0, 0.0, 8))
    images, outs = _run(cluster, kill=(2, 1))
    assert cluster.live == [0, 2] and cluster.lost == [1]
    assert sorted(images) == [0, 2, 3, 5]                 # the survivors' viewers go on
    assert all(r["missing"] == 0 for r in outs[-1]["results"].values())    # every entry has a value again
    plain = _plain(s, "slc", vs, FRAMES)
    assert any(not np.array_equal(images[v], plain[v]) for v in images)   # re-owned entries started anew


def _cone_record(L: float, C: float, n: int = 1):
    from slc.lib.cones.packing import pack
    D = [mi.Vector3f(0, 0, 1), mi.Vector3f(0, 1, 0), mi.Vector3f(1, 0, 0)]
    return pack(D, [mi.Float(0.1)] * 3, [mi.Color3f(L)] * 3, mi.Float(C), mi.UInt32(n), 3)


def test_a_record_change_counts_against_the_entry_noise_and_any_change_counts_at_threshold_0(scene):
    m = codec_for(methods.create("slc", scene("atrium"), seed=0))
    # the same 20% change of the radiance: at 255 samples of memory 0.2, at 32 samples sqrt(32/255) of it
    full = float(m.change(_cone_record(1.0, 255), _cone_record(1.2, 255))[0])
    young = float(m.change(_cone_record(1.0, 32), _cone_record(1.2, 32))[0])
    assert abs(full - 0.2 / 1.2) < 1e-3 and abs(young / full - (32 / 255) ** 0.5) < 1e-3
    # a cone that appears counts with its share of the radiance (a third of it here)
    grown = float(m.change(_cone_record(1.0, 255, 2), _cone_record(1.0, 255, 3))[0])
    assert abs(grown - 1 / 3) < 1e-3
    # only C differs: no change of the light, yet a change of the words at threshold 0
    a, b = _cone_record(1.0, 100), _cone_record(1.0, 101)
    assert float(m.change(a, b)[0]) == 0.0
    assert bool(changed_records(m, a, b, 0.0)[0]) and not bool(changed_records(m, a, b, 0.01)[0])
    assert not bool(changed_records(m, a, a, 0.0)[0])


def test_owners_move_only_the_regions_of_a_lost_node_and_a_region_holds_the_coarser_entries(scene):
    """Rendezvous hashing: balanced over the nodes, and a node that leaves moves only its own
    regions. On a real cache, a block's entries share their region, and so do an entry and its
    coarser entries up to the region level (its LOD seeds stay with its owner)."""
    regions = np.arange(40960, dtype=np.uint64) * 2654435761 % 2 ** 32
    before, after = owners(regions, [0, 1, 2]), owners(regions, [0, 2])
    assert set(np.unique(before)) == {0, 1, 2} and abs(np.mean(before == 1) - 1 / 3) < 0.02
    moved = before != after
    assert np.all(before[moved] == 1) and np.all(after[before == 1] != 1)
    s = scene("atrium")
    m = methods.create("slc", s, seed=0)
    m.render(FrameContext(frame=0), frame_gbuffers(s, views.overlap_rig(s, 2, 0.5, aspect=W / H), 0, W, H), NullTimer())
    cache, level = m.cache, 6
    keys = np.array(cache.entry_address(m.requests.active), np.uint32)
    of = Regions(cache.layout, level)
    r = of(keys)
    for b in np.unique(keys >> 6)[:200]:
        assert len(set(r[(keys >> 6) == b])) == 1
    up, ok = ancestors(cache, m.requests.active)
    lvl = np.array(cache.entry_texels(m.requests.active)[1])
    tested = 0
    for d in range(up.shape[0]):
        near = ok[d] & (lvl + d + 1 <= level)
        assert np.array_equal(of(up[d][near]), r[near]), d
        tested += int(near.sum())
    assert tested > len(keys) // 2


def test_subscriptions_and_the_owner_agree_on_the_needs_with_a_lease():
    """A node's subscriptions at an owner and the owner's view of them (the need bits over the
    sorted subscription list) agree frame after frame; an entry unneeded for more than the lease
    is cancelled; a frame that changes nothing sends nothing; re-subscriptions name the entries the
    node holds a record of."""
    rng = np.random.default_rng(1)
    sub, client = Subscriptions(), Client()
    universe = np.arange(100, 300, dtype=np.uint32)
    holds = lambda k: k % 2 == 0      # noqa: E731
    for f in range(30):
        need = np.unique(rng.choice(universe, 40)).astype(np.uint32) if f % 7 else np.zeros(0, np.uint32)
        msg = sub.frame(5, 1, f, need, lease=3, holds=holds)
        if msg is not None:
            assert isinstance(msg, Requests) and np.all(holds(msg.resubscribe)) and not np.any(holds(msg.subscribe))
            msg = pickle.loads(pickle.dumps(msg))          # as it travels between processes: encoded
            client.apply(msg)
        assert np.array_equal(client.needed(), need)
        assert np.array_equal(client.keys, sub.keys)
        assert np.all(f - sub.last <= 3)
    for f in range(30, 35):                  # the same needs frame after frame: the others expire, then quiet
        msg = sub.frame(5, 1, f, need, lease=3, holds=holds)
        if msg is not None:
            client.apply(msg)
    assert sub.frame(5, 1, 35, need, lease=3, holds=holds) is None
    assert np.array_equal(client.keys, need) and np.array_equal(client.needed(), need)


def test_addresses_and_need_bits_travel_encoded_and_come_back_the_same():
    """Ascending addresses go as varint differences (an entry beside the last one: one byte),
    need bits packed (deflated when shorter); a pickled message decodes to the same arrays and
    its byte count is its encoded fields'."""
    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 500):
        keys = np.unique(rng.integers(0, 2 ** 32, n)).astype(np.uint32)
        assert np.array_equal(decode_addresses(encode_addresses(keys)), keys)
    block = np.arange(64 * 1000, 64 * 1000 + 64, dtype=np.uint32)
    assert len(encode_addresses(block)) == 3 + 63                    # the first difference takes 3 bytes
    bits = np.packbits(np.ones(4000, bool))
    assert len(encode_bits(bits)) < 20 and np.array_equal(decode_bits(encode_bits(bits)), bits)
    msg = Requests(0, 1, 5, subscribe=block[:10], cancel=block[20:], need=bits)
    back = pickle.loads(pickle.dumps(msg))
    assert all(np.array_equal(getattr(back, k), getattr(msg, k)) for k in ("subscribe", "resubscribe", "cancel", "need"))
    assert msg.nbytes == len(encode_addresses(block[:10])) + len(encode_addresses(block[20:])) + len(encode_bits(bits))


def test_an_extrapolated_camera_continues_a_steady_walk_and_turn():
    def cam(t):
        a = np.radians(2.0 * t)
        o = np.array([0.1 * t, 1.5, 0.0])
        return Camera(o, o + 3.0 * np.array([np.sin(a), 0.0, np.cos(a)]), fov=60.0)
    for ahead in (1, 4):
        c = extrapolated(cam(9), cam(10), ahead)
        want = cam(10 + ahead)
        assert np.allclose(c.origin, want.origin) and np.allclose(c.target, want.target, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# separate processes: Ray actors on a 2-node local cluster
# ---------------------------------------------------------------------------------------------

@pytest.fixture
def ray_nodes(ray_cluster):
    """The session's two-node Ray cluster (tests/conftest.py), this process connected to it for
    the test (the nodes' processes import this checkout) and disconnected afterwards."""
    import ray
    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[1]), "SLC_VARIANT": backend.variant(),
           "SLC_CACHE": os.environ["SLC_CACHE"]}
    ray.init(address=ray_cluster.address, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": env})
    # the actors of an earlier test's driver end after it disconnects: wait for their CPUs
    t_end = time.monotonic() + 60.0
    while ray.available_resources().get("CPU", 0.0) < ray.cluster_resources().get("CPU", 0.0) \
            and time.monotonic() < t_end:
        time.sleep(0.2)
    try:
        yield ray_cluster
    finally:
        ray.shutdown()


@pytest.mark.slow
@pytest.mark.fresh_process   # in its own process: after its connections, a later connection of the
@pytest.mark.parametrize("spec", ["slc", "adaptive"])   # same process had its actors cancelled by Ray
def test_node_processes_give_the_single_process_images_and_survive_a_killed_process(ray_nodes, scene, spec):
    import ray
    from slc.distributed.actors import RayNodes, node_actors
    s = scene("atrium")
    vs = views.overlap_rig(s, 4, 0.5, aspect=W / H)
    assign = assignment([ViewerPoses.of(v, FRAMES + 2) for v in vs], 2)
    actors = dict(enumerate(node_actors("atrium", 2, threads=1)))
    st = Strategy("sparse", 0, 0.0, 8)
    pids = ray.get([actors[n].start.remote(n, [0, 1], spec, assign[n], W, H, st) for n in (0, 1)])
    assert len(set(pids)) == 2 and os.getpid() not in pids
    cluster = Cluster(RayNodes(actors), [0, 1], 0)
    images, _ = _run(cluster)
    plain = _plain(s, spec, vs, FRAMES)
    assert sorted(images) == [0, 1, 2, 3]
    for v, img in images.items():
        assert np.array_equal(img, plain[v]), v
    if spec != "slc":
        return
    cluster.kill(1)                                   # the process ends; the next frame finds it gone
    for f in range(FRAMES, FRAMES + 2):
        out = cluster.step(f, images=True)
    assert cluster.lost == [1] and list(out["results"]) == [0]
    assert sorted(out["results"][0]["images"]) == [0, 2] and out["results"][0]["missing"] == 0


@pytest.mark.parametrize("args,what", [
    (["--viewers", "2", "--nodes", "3"], "--nodes must be between 1"),
    (["--method", "rt16", "--viewers", "2", "--nodes", "2"], "has none"),
    (["--viewers", "2", "--nodes", "2", "--gt"], "--gt is not available"),
    (["--viewers", "2", "--nodes", "2", "--threshold", "-1"], "--threshold must be >= 0"),
    (["--method", "slc:bias=abc", "--viewers", "2", "--nodes", "2"], "bias must be a number"),
])
def test_render_on_nodes_refuses_bad_input(tmp_path, args, what):
    """``slc render --nodes``: bad input is one line and exit status 2, before Ray starts."""
    from helpers import slc_cli
    base = ["render", "--scene", "atrium", "--method", "slc", "--res", "16x9", "--frames", "1", "--out", str(tmp_path)]
    p = slc_cli(base + args)
    assert p.returncode == 2 and what in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_a_method_spec_is_checked_without_a_scene_and_made_as_create_makes_it(scene):
    """``slc.methods.parse``: a spec checked once without a scene or an instance (its settings and
    cross-checks, with the one-line errors of making the method), as data a process ships to
    another (pickled); the method a node makes from it is the one ``create`` makes of the spec."""
    ms = methods.parse("slc:bias=2,block=4")
    assert ms.settings == {"bias": 2.0, "block": 4} and ms.output == "direct" and ms.cls.name == "slc"
    s = scene("cornell")
    a = pickle.loads(pickle.dumps(ms)).create(s, seed=3)
    b = methods.create("slc:bias=2,block=4", s, seed=3)
    assert type(a) is type(b) and a.settings() == b.settings() and (a.label, a.seed) == (b.label, b.seed)
    assert methods.parse("osc-gi:output=indirect").output == "indirect"
    for bad, what in (("slc:bias=abc", "bias must be a number"), ("slc:nope=1", "unknown setting nope"),
                      ("osc-gi:hemi=4,texel_rays=3", "texel_rays must divide"), ("nope", "unknown method")):
        with pytest.raises(methods.MethodError, match=what):
            methods.parse(bad)


@pytest.mark.slow
def test_render_on_nodes_writes_the_one_process_images(tmp_path):
    """``slc render --nodes 2 --threshold 0`` on a local Ray instance (a process per node) writes
    every viewer's image, bit for bit the one-process render's."""
    import ray
    from helpers import slc_cli
    base = ["render", "--scene", "atrium", "--method", "slc", "--viewers", "2", "--rig", "overlap", "--overlap", "0.5",
            "--res", "32x18", "--frames", "3"]
    p = slc_cli(base + ["--nodes", "2", "--threshold", "0", "--out", str(tmp_path / "n")])
    assert p.returncode == 0, p.stderr
    assert not ray.is_initialized()                      # the command shut its instance down
    info = json.loads((tmp_path / "n" / "nodes.json").read_text())
    assert info["processes"] == 2 and len(info["bytes_per_frame"]) == 3
    q = slc_cli(base + ["--out", str(tmp_path / "one")])
    assert q.returncode == 0, q.stderr
    for node, v in ((0, "o00"), (1, "o01")):
        a = np.array(mi.Bitmap(str(tmp_path / "n" / f"atrium_slc_node{node}_{v}.exr")))
        b = np.array(mi.Bitmap(str(tmp_path / "one" / f"atrium_slc_{v}.exr")))
        assert a.shape == b.shape == (18, 32, 3) and np.array_equal(a, b), v


@pytest.mark.slow
def test_the_experiment_writes_rows_of_node_processes(tmp_path):
    """``slc run distributed`` on two node processes: every row of a sharing strategy says two
    processes rendered it and each rendered one viewer's G-buffer; results.json, results.md and
    the figure are written."""
    from helpers import slc_cli
    p = slc_cli(["run", "distributed", "--quick", "--nodes", "2", "--viewers", "2", "--delays", "0",
                 "--res", "16x9", "--frames", "3", "--out", str(tmp_path)])
    assert p.returncode == 0, p.stderr
    rows = json.loads((tmp_path / "distributed" / "results.json").read_text())["rows"]
    shared = [r for r in rows if r["strategy"] != "single"]
    assert shared and all(r["processes"] == 2 and r["gbuffer_viewers_per_node"] == 1 for r in shared)
    assert all(r["processes"] == 1 and r["gbuffer_viewers_per_node"] == 2 for r in rows if r["strategy"] == "single")
    assert {r["strategy"] for r in rows} == {"single", "independent", "full", "sparse"}
    for r in rows:
        assert set(KINDS) <= {k[len("bytes_"):] for k in r if k.startswith("bytes_")}
        assert np.isfinite(r["flip"]) and r["time_ms"] > 0
    assert (tmp_path / "distributed" / "results.md").exists() and (tmp_path / "distributed" / "flip_vs_delay.png").exists()


def test_the_experiment_refuses_bad_input(tmp_path):
    from helpers import slc_cli
    p = slc_cli(["run", "distributed", "--quick", "--delays", "-1", "--out", str(tmp_path)])
    assert p.returncode == 2 and "--delays must be >= 0" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "distributed").exists()
