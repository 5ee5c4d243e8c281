"""The tracking path's array helpers give numpy's own answers, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.arrays import median_of_few, unique_integers


@pytest.mark.parametrize("values", [
    np.zeros(0, np.int64),
    np.array([7]),
    np.array([3, 1, 3, 2, -5, 1]),
    np.array([[2, 1], [2, 0]]),
    np.array([True, False, True]),
    np.array([4, 4, 4], np.uint8),
    [5, 3, 5],
    np.array([2.5, np.nan, 1.0, np.nan]),  # not integers: np.unique itself (NaNs merged)
])
def test_unique_integers_is_np_unique(values):
    ours, theirs = unique_integers(values), np.unique(values)
    assert ours.dtype == theirs.dtype
    np.testing.assert_array_equal(ours, theirs)


def test_unique_integers_random_against_np_unique():
    rng = np.random.default_rng(0)
    for _ in range(500):
        values = rng.integers(-20, 20, size=int(rng.integers(0, 40)))
        np.testing.assert_array_equal(unique_integers(values), np.unique(values))


@pytest.mark.parametrize("values", [
    [1.0], [2.0, 1.0], [3.0, 1.0, 2.0], [1e-12, 3.0, 1e12, -4.0], [0.1, 0.2, 0.3, 0.4],
])
def test_median_of_few_is_np_median(values):
    assert median_of_few(np.array(values)) == float(np.median(values))


def test_median_of_few_random_and_nan_against_numpy():
    rng = np.random.default_rng(1)
    for _ in range(500):
        values = rng.normal(size=int(rng.integers(1, 12))) * 10.0 ** rng.integers(-6, 6)
        assert median_of_few(values) == float(np.median(values))
        holes = values.copy()
        holes[rng.random(len(values)) < 0.3] = np.nan
        known = holes[~np.isnan(holes)]
        if len(known):  # how clock.py replaces np.nanmedian
            assert median_of_few(known) == float(np.nanmedian(holes))
    assert np.isnan(median_of_few(np.array([1.0, np.nan])))


def test_median_of_few_with_ties_is_numpys():
    # (moved from the clock model's tests with the helper, cblrs.matching.clock._median)
    generator = np.random.default_rng(5)
    for count in range(1, 12):
        for _ in range(300):
            values = generator.normal(size=count) * generator.choice([1e-4, 1e-2, 1.0])
            values[generator.integers(count)] = values[0]  # ties
            assert median_of_few(values) == float(np.median(values))
