"""`slc bench rays`: the split of RT-N's time (a smoke test of the report: no
timing is asserted, only that every part is measured and reported)."""
from slc import bench


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
