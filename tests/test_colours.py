"""The colour convention: log-symmetric det J ranges and histograms that lose no value."""

import numpy as np
import pytest

from vhm_viz import colours


def test_det_range_is_symmetric_in_log_and_ignores_folds():
    rng = np.random.default_rng(0)
    det = np.exp(rng.normal(0.0, 1.0, 10_000))
    det[:50] = -3.0  # folds: coloured apart, must not widen the range
    lo, hi = colours.det_range(det)
    assert lo * hi == pytest.approx(1.0)
    # 1% of the positive values lie beyond the range (counted apart in histograms)
    pos = det[det > 0]
    beyond = np.count_nonzero((pos > hi) | (pos < lo)) / pos.size
    assert 0.009 <= beyond <= 0.011
    assert colours.det_range(np.full(10, 1.01)) == pytest.approx((0.5, 2.0))


def test_cond_range_starts_at_one():
    cond = np.r_[np.linspace(1.0, 9.0, 1001), np.inf, np.nan]
    lo, hi = colours.cond_range(cond)
    assert lo == 1.0 and hi == pytest.approx(np.percentile(np.linspace(1.0, 9.0, 1001), 99))


@pytest.mark.parametrize("log", [False, True])
def test_histogram_counts_every_value(log):
    rng = np.random.default_rng(1)
    v = np.exp(rng.normal(0.0, 1.5, 5000)) if log else rng.normal(0.0, 3.0, 5000)
    v = np.r_[v, -1.0, np.nan, np.inf]
    lo, hi = (0.5, 2.0) if log else (-2.0, 2.0)
    h = colours.histogram(v, (lo, hi), bins=17, log=log)
    fin = v[np.isfinite(v)]
    assert h.total == v.size
    assert h.nonfinite == 2
    assert h.below == np.count_nonzero(fin < lo) and h.above == np.count_nonzero(fin > hi)
    # each bin against a brute-force count
    for k in range(17):
        a, b = h.edges[k], h.edges[k + 1]
        last = k == 16
        n = np.count_nonzero((fin >= a) & ((fin <= b) if last else (fin < b)))
        assert h.counts[k] == n
    if log:
        assert np.allclose(np.diff(np.log(h.edges)), np.log(hi / lo) / 17)


def test_measure_style_names_the_convention():
    s = colours.measure_style("determinant", [0.5, 1.0, 3.0])
    assert s["cmap"] == "coolwarm" and s["log_scale"]
    assert s["clim"][0] * s["clim"][1] == pytest.approx(1)
    assert colours.measure_style("condition_number", [1, 2, 5])["cmap"] == "viridis"
    with pytest.raises(ValueError, match="unknown measure"):
        colours.measure_style("volume", [1.0])
