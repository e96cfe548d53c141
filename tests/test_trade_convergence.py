"""The observed order of three nested levels, and Richardson's estimate of the finest's error."""

import math

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.trade.convergence import observed_order, order_of_differences


def levels(order: float, h: float = 0.1, ratio: float = 2.0, higher: float = 0.0):
    """q(h) = 1 + 3 hᵖ + higher · hᵖ⁺¹ on h, h/r, h/r², and the finest level's true error."""
    sizes = [h, h / ratio, h / ratio**2]
    values = [1.0 + 3.0 * s**order + higher * s ** (order + 1) for s in sizes]
    return values, values[2] - 1.0


@pytest.mark.parametrize("order, ratio", [(1.0, 2.0), (2.0, 2.0), (2.0, 3.0), (4.0, 2.0)])
def test_a_pure_power_gives_its_order_and_the_finest_error_exactly(order, ratio):
    values, error = levels(order, ratio=ratio)
    found = observed_order(*values, expected=order, ratio=ratio)
    assert found.observed == pytest.approx(order, rel=1e-9) and found.agree
    assert found.estimate == pytest.approx(abs(error), rel=1e-8)


def test_a_higher_order_term_leaves_the_estimate_close():
    """q = 1 + 3h² + 10h³ from h = 0.1: p ≈ 2.2 (within ½ of 2), the estimate within 20 % (9 %)."""
    values, error = levels(2.0, higher=10.0)
    found = observed_order(*values, expected=2.0)
    assert 2.0 < found.observed < 2.5 and found.agree
    assert found.estimate == pytest.approx(abs(error), rel=0.2)


def test_an_order_far_from_the_expected_one_gives_no_estimate():
    values, _ = levels(1.0)
    found = observed_order(*values, expected=2.0)
    assert found.observed == pytest.approx(1.0) and not found.agree and found.estimate is None


def test_an_oscillating_sequence_gives_no_estimate():
    """Differences of opposite signs: |d₁|/|d₂| = 4 reads as order 2, but there is no limit to
    extrapolate to from one side."""
    found = observed_order(1.0, 1.04, 1.03, expected=2.0)
    assert found.observed == pytest.approx(2.0) and not found.agree and found.estimate is None


def test_a_curve_takes_its_worst_time_and_one_sign_at_every_time():
    """A curve over output times: the order from the largest differences; a time whose
    differences change sign withdraws the estimate."""
    t = np.linspace(0.1, 1.0, 5)
    curve = [t + 3 * t * h**2 for h in (0.1, 0.05, 0.025)]
    found = observed_order(*curve, expected=2.0)
    assert found.observed == pytest.approx(2.0) and found.agree
    assert found.estimate == pytest.approx(3 * 1.0 * 0.025**2, rel=1e-8)  # its worst time, t = 1
    curve[2] = curve[2].copy()
    curve[2][0] = curve[1][0] + 1e-9  # the first time's last difference of the other sign
    assert observed_order(*curve, expected=2.0).estimate is None


def test_levels_that_agree_exactly_report_so():
    converged = observed_order(2.0, 2.0, 2.0, expected=2.0)
    assert math.isnan(converged.observed) and converged.estimate is None
    finest_equal = observed_order(1.0, 2.0, 2.0, expected=2.0)
    assert finest_equal.observed == math.inf and finest_equal.estimate is None
    diverging = observed_order(2.0, 2.0, 3.0, expected=2.0)
    assert diverging.observed == -math.inf and not diverging.agree


@pytest.mark.parametrize(
    "arguments, message",
    [
        (((1.0, 2.0, 3.0), {"expected": 2.0, "ratio": 1.0}), "refinement ratio must be > 1"),
        (((1.0, 2.0, 3.0), {"expected": 0.0}), "expected order must be > 0"),
        (((1.0, [2.0, 1.0], 3.0), {"expected": 2.0}), "different shapes"),
        (((1.0, math.nan, 3.0), {"expected": 2.0}), "not finite"),
        (((1.0, 2.0, 3.0), {"expected": 2.0, "ratio": "2"}), "refinement ratio"),
    ],
)
def test_bad_levels_are_refused_in_one_line(arguments, message):
    values, options = arguments
    with pytest.raises(ParameterError, match=message):
        observed_order(*values, **options)


def test_the_norms_of_two_differences_give_the_order_of_a_field():
    """‖x_h − x_h/2‖ = C hᵖ (1 − 2⁻ᵖ) and ‖x_h/2 − x_h/4‖ = C (h/2)ᵖ (1 − 2⁻ᵖ) of a field whose error
    is C hᵖ along one direction: the order p, and the finest level's error C (h/4)ᵖ exactly."""
    C, h, p = 0.7, 0.2, 1.0
    large, small = (C * s**p * (1 - 2**-p) for s in (h, h / 2))
    found = order_of_differences(large, small, expected=p)
    assert found.observed == pytest.approx(p) and found.agree
    assert found.estimate == pytest.approx(C * (h / 4) ** p)
    assert not order_of_differences(large, small, expected=3.0).agree


@pytest.mark.parametrize("sizes", [(-1.0, 0.5), (math.nan, 0.5), (1.0, math.inf)])
def test_differences_that_are_no_sizes_are_refused_in_one_line(sizes):
    with pytest.raises(ParameterError, match="finite sizes"):
        order_of_differences(*sizes, expected=1.0)
