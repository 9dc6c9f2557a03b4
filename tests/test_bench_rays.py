"""`slc bench rays`: the split of RT-N's time (a smoke test of the report: no
timing is asserted, only that every part is measured and reported)."""
import pytest

from slc.run import bench


def test_bench_rays_reports_where_the_time_goes():
    r = bench.bench_rays("cornell", 16, 9, n=2, repeats=1)
    assert set(r["stages"]) == set(bench.STAGES)
    assert all(v > 0 for v in r["stages"].values())
    t = r["samplers"]["table"]
    assert 0 < t["ours_host_ms"] <= t["ours_ms"]
    lines = bench.report_lines(r)
    where = [ln for ln in lines if ln.startswith(" where rt2's time goes")]
    assert len(where) == 1 and "shadow rays" in where[0] and "host (tracing)" in where[0]
    assert r["load"] is None or len(r["load"]) == 3


@pytest.mark.slow
def test_bench_update_traces_the_records_before_the_update():
    """In the first frame every entry is new: its records before the update hold no
    cone, so the shrink test has nothing to test. Reading the records after the
    update (it writes them in place) would count the new entries' cones."""
    r = bench.bench_update("cornell", 24, 14, frames=1, warmup=0, repeats=1)
    assert r["entries"] > 0 and r["shadow_rays"] > 0
    assert r["shrink_rays"] == 0


@pytest.mark.slow
def test_bench_update_reports_frame_and_rays():
    r = bench.bench_update("cornell", 24, 14, frames=6, warmup=3, repeats=1)
    assert 0 < r["shrink_rays"] <= 3 * r["entries"]
    assert r["shadow_rays"] > 0 and r["shadow_ms"] > 0 and r["shrink_ms"] > 0 and r["frame_ms"] > 0
    assert r["rays_ms"] == r["shadow_ms"] + r["shrink_ms"]          # both kinds of the update's rays
    assert r["update_ms"] == r["stages_ms"]["update"] > 0
    lines = bench.update_report_lines(r)
    ratio = [ln for ln in lines if ln.strip().startswith("ratio frame / rays")]
    assert len(ratio) == 1 and f"{r['frame_ms'] / (r['shadow_ms'] + r['shrink_ms']):.2f}x (target <= 1.5x)" in ratio[0], \
        (ratio, r)
