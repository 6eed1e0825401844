"""The vectorisable atan2 and log1p against the C library, in units in the last place."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from vhm_viz.core import vecmath


@numba.njit(cache=True)
def _atan2_all(y, x, out):
    for i in range(y.shape[0]):
        out[i] = vecmath.atan2(y[i], x[i])


@numba.njit(cache=True)
def _log1p_all(x, out):
    for i in range(x.shape[0]):
        out[i] = vecmath.log1p(x[i])


def _ulps(got, ref):
    return np.abs(got - ref) / np.spacing(np.abs(ref))


def _random_signed(rng, n, lo, hi):
    return rng.choice([-1.0, 1.0], n) * np.exp(rng.uniform(lo, hi, n))


def test_atan2_is_within_three_ulp_over_the_plane():
    rng = np.random.default_rng(0)
    n = 400_000
    # magnitudes over 26 decades, both signs, both orders of |y| and |x|
    y = _random_signed(rng, n, -30, 30)
    x = _random_signed(rng, n, -30, 30)
    # ... and ratios right at the reduction's switch points tan((2k + 1) pi / 32)
    k = rng.integers(0, 4, 2000)
    x2 = _random_signed(rng, 2000, -5, 5)
    y2 = x2 * np.tan((2 * k + 1) * np.pi / 32) * (1 + rng.uniform(-1e-12, 1e-12, 2000))
    y, x = np.concatenate([y, y2]), np.concatenate([x, x2])
    got = np.empty_like(y)
    _atan2_all(y, x, got)
    ulps = _ulps(got, np.arctan2(y, x))
    assert ulps.max() <= 3.0
    assert ulps.mean() <= 0.3


def test_atan2_special_values_follow_c():
    cases = [
        (0.0, 1.0),
        (-0.0, 1.0),
        (0.0, -1.0),
        (-0.0, -1.0),
        (1.0, 0.0),
        (-1.0, 0.0),
        (0.0, 0.0),
        (-0.0, 0.0),
        (0.0, -0.0),
        (-0.0, -0.0),
        (1e-300, 1.0),
        (1.0, 1e-300),
        (1.0, 1.0),
        (-1.0, -1.0),
        (5e-324, -1.0),
    ]
    y = np.array([c[0] for c in cases])
    x = np.array([c[1] for c in cases])
    got = np.empty_like(y)
    _atan2_all(y, x, got)
    for (yy, xx), g in zip(cases, got, strict=True):
        ref = math.atan2(yy, xx)
        assert g == pytest.approx(ref, rel=4e-16, abs=0.0), (yy, xx)
        assert math.copysign(1.0, g) == math.copysign(1.0, ref), (yy, xx)


def test_log1p_is_within_one_ulp():
    rng = np.random.default_rng(1)
    x = np.concatenate(
        [
            np.exp(rng.uniform(-700, 700, 400_000)),  # 1e-304 .. 1e304
            rng.uniform(0.0, 2.0, 100_000),  # around the sqrt(2) switch of the mantissa
            np.sqrt(2.0) - 1.0 + rng.uniform(-1e-9, 1e-9, 1000),
            np.array([0.0, 5e-324, 1e-17, 2.0**-53, 1.0, np.finfo(float).max / 2]),
        ]
    )
    got = np.empty_like(x)
    _log1p_all(x, got)
    ref = np.log1p(x)
    nonzero = ref != 0
    assert np.all(got[~nonzero] == 0.0)
    ulps = _ulps(got[nonzero], ref[nonzero])
    assert ulps.max() <= 1.0
    assert ulps.mean() <= 0.3
