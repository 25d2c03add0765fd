"""GUM Supplement 1 statistics and the adaptive stopping rule (xmalign.montecarlo)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from xmalign.montecarlo import AdaptiveStudy, numerical_tolerance, stability, summarize


def test_summary_of_a_normal_sample_matches_the_distribution():
    values = np.random.default_rng(1).normal(10.0, 2.0, 200_000)
    s = summarize(values)
    assert s.mean == pytest.approx(10.0, abs=0.02)
    assert s.standard_uncertainty == pytest.approx(2.0, rel=0.01)
    assert s.low == pytest.approx(10.0 - 1.96 * 2.0, abs=0.05)
    assert s.high == pytest.approx(10.0 + 1.96 * 2.0, abs=0.05)
    assert s.count == 200_000


def test_interval_is_probabilistically_symmetric_for_a_skewed_sample():
    values = np.random.default_rng(2).exponential(1.0, 200_000)
    s = summarize(values)
    assert s.low == pytest.approx(-math.log(0.975), rel=0.03)
    assert s.high == pytest.approx(-math.log(0.025), rel=0.01)


def test_summary_needs_two_values():
    with pytest.raises(ValueError, match="at least 2"):
        summarize([1.0])


@pytest.mark.parametrize(
    ("u", "digits", "tolerance"),
    [
        (0.025428, 2, 0.0005),  # 25 x 10^-3 (GUM S1 7.9.2 pattern)
        (0.025428, 1, 0.005),  # 3 x 10^-2
        (100.0, 1, 50.0),  # 1 x 10^2
        (1.0, 2, 0.05),  # 10 x 10^-1
        (0.0996, 2, 0.005),  # rounds to 10 x 10^-2, not 99.6 x 10^-3
        (0.0, 1, 0.0),
    ],
)
def test_numerical_tolerance(u, digits, tolerance):
    assert numerical_tolerance(u, digits) == pytest.approx(tolerance)


def test_numerical_tolerance_refuses_zero_digits():
    with pytest.raises(ValueError, match="at least 1"):
        numerical_tolerance(1.0, 0)


@given(st.integers(1, 999), st.integers(-6, 6), st.integers(1, 3))
def test_tolerance_scales_with_the_unit(significand, exponent, digits):
    u = significand * 10.0**exponent
    tolerance = numerical_tolerance(u, digits)
    assert numerical_tolerance(10.0 * u, digits) == pytest.approx(10.0 * tolerance)
    # delta is half a unit in the last of ``digits`` digits of u
    assert 10 ** (digits - 1) <= round(u / (2 * tolerance)) < 10**digits


def test_one_batch_is_never_stable():
    values = np.random.default_rng(3).normal(0.0, 1.0, 10_000)
    result = stability([values], digits=1)
    assert not result.stable
    assert np.all(np.isinf(result.spread))


def test_large_batches_are_stable_small_ones_not():
    rng = np.random.default_rng(4)
    large = [rng.normal(5.0, 2.0, 10_000) for _ in range(4)]
    small = [rng.normal(5.0, 2.0, 5) for _ in range(4)]
    settled = stability(large, digits=1)
    assert settled.stable
    assert settled.tolerance == pytest.approx(0.5)  # u ~ 2 = 2 x 10^0
    assert not stability(small, digits=1).stable
    # two digits ask for 20 times smaller spreads than one
    assert stability(large, digits=2).tolerance == pytest.approx(0.05)


def test_spread_is_twice_the_standard_deviation_of_the_batch_average():
    batches = [np.array([0.0, 2.0]), np.array([1.0, 3.0]), np.array([2.0, 4.0])]
    # batch means 1, 2, 3: std 1, of the average 1/sqrt(3)
    result = stability(batches, digits=1)
    assert result.spread[0] == pytest.approx(2.0 / math.sqrt(3.0))
    # every batch has the same standard deviation: no spread
    assert result.spread[1] == pytest.approx(0.0)


def test_adaptive_study_stops_and_ignores_failed_trials():
    rng = np.random.default_rng(5)
    study = AdaptiveStudy(digits=1)
    while not study.stable:
        batch = rng.normal(3.0, 0.4, 2000)
        batch[:10] = np.nan  # failed trials
        study.add_batch({"a": batch, "b": 2.0 * batch})
        assert len(study.batches) < 50
    summaries = study.summaries()
    assert set(summaries) == {"a", "b"}
    assert summaries["a"].count == len(study.batches) * 1990
    assert summaries["a"].standard_uncertainty == pytest.approx(0.4, rel=0.05)
    assert summaries["b"].mean == pytest.approx(6.0, abs=0.05)
    assert len(study.batches) >= 2


def test_a_quantity_not_settled_keeps_the_study_going():
    rng = np.random.default_rng(6)
    study = AdaptiveStudy(digits=1)
    for _ in range(3):
        study.add_batch({"steady": rng.normal(0, 1, 5000), "wild": rng.standard_cauchy(5)})
    settled = study.stability()
    assert settled["steady"].stable
    assert not settled["wild"].stable
    assert not study.stable
