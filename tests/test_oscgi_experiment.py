"""experiments/osc_gi.py: PT at equal time from PT's fitted cost (a + b spp) and its exact FLIP
against spp, robust to one PT row timed under another load."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import osc_gi  # noqa: E402


def _in_measured_time(rows, t):
    """PT's FLIP at time t interpolated log-log in the PT rows' own measured times."""
    return osc_gi._loglog(sorted((r["time_ms"], r["flip"]) for r in rows), t)


def _rows(slow=None):
    # PT's time 2 + 3 spp ms, FLIP 0.1 spp^-0.3 (a power law: log-log interpolation is exact)
    return [{"spp": n, "time_ms": (2.0 + 3.0 * n) * (2.0 if n == slow else 1.0), "flip": 0.1 * n ** -0.3}
            for n in (1, 2, 4, 8, 16, 32, 64)]


def test_equal_time_reads_the_fitted_cost_and_interpolates_flip_in_spp():
    assert osc_gi._pt_cost(_rows()) == pytest.approx((2.0, 3.0))
    assert osc_gi._equal_time(_rows(), 2.0 + 3.0 * 12) == pytest.approx(0.1 * 12 ** -0.3, rel=1e-6)
    assert _in_measured_time(_rows(), 2.0 + 3.0 * 12) == pytest.approx(0.1 * 12 ** -0.3, rel=0.02)
    assert osc_gi._equal_time(_rows(), 1.0) is None                     # below PT at 1 spp
    assert osc_gi._equal_time(_rows(), 1e5) is None                     # beyond PT at 64 spp


def test_one_pt_row_timed_slow_moves_the_fitted_figure_less():
    """PT at 4 spp timed 2x slow (measured: fitted 1.2% off, the interpolation in measured times 11.7%)."""
    exact = 0.1 * 12 ** -0.3
    fit = osc_gi._equal_time(_rows(slow=4), 2.0 + 3.0 * 12)
    direct = _in_measured_time(_rows(slow=4), 2.0 + 3.0 * 12)
    assert abs(fit / exact - 1.0) < 0.02, fit
    assert abs(direct / exact - 1.0) > 2 * abs(fit / exact - 1.0), (direct, fit)
