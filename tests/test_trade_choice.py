"""The trade's answer: the cheapest model that meets the tolerance on the measured points."""

import math

import pytest

from lungmech.errors import ParameterError
from lungmech.trade.choice import Measured, choose

FULL = Measured("full P1", "full", 2e-4, 0, online=3.7)
GALERKIN = Measured("Galerkin k=20", "galerkin", 3e-4, 0, online=1.2, offline=200.0)
FAST = Measured("ECSW τ=1e-4", "ecsw", 3e-3, 0, online=0.007, offline=260.0)
ACCURATE = Measured("ECSW τ=1e-5", "ecsw", 8e-4, 0, online=0.009, offline=270.0)
BROKEN = Measured("ECSW τ=1e-3", "ecsw", 1e-4, 2, online=0.005, offline=250.0)


def test_the_cheapest_that_meets_the_tolerance_online():
    """Without queries the online time decides: τ = 1e-5's 9 ms meets 1e-3, τ = 1e-4's 7 ms
    does not; a model failing at a point is never chosen, however accurate it reads."""
    choice = choose([FULL, GALERKIN, FAST, ACCURATE, BROKEN], 1e-3, "volume")
    assert choice.chosen is ACCURATE
    assert "ECSW τ=1e-5: 8.0e-04 ≤ 1.0e-03 on volume" in choice.reason and "of 3 that meet it" in choice.reason
    assert choose([FULL, GALERKIN, FAST, ACCURATE], 5e-3, "volume").chosen is FAST


def test_few_queries_let_the_offline_cost_decide():
    """Over 10 queries ECSW's 270 s build costs 27 s a query: the full model (3.7 s) wins; over
    a thousand, 0.28 s against 3.7: ECSW."""
    candidates = [FULL, GALERKIN, ACCURATE]
    assert choose(candidates, 1e-3, "volume", queries=10).chosen is FULL
    assert choose(candidates, 1e-3, "volume", queries=1000).chosen is ACCURATE
    assert "over 1000 queries" in choose(candidates, 1e-3, "volume", queries=1000).reason


def test_none_that_meets_it_is_said_with_the_most_accurate():
    choice = choose([FAST, ACCURATE], 1e-4, "pv")
    assert choice.chosen is None
    assert choice.reason == "none meets 1.0e-04 on pv: the most accurate, ECSW τ=1e-5, is off by 8.0e-04"
    failing = choose([BROKEN, Measured("x", "ecsw", math.nan, 0, 0.01)], 1e-2, "pv")
    assert failing.chosen is None and "every candidate failed" in failing.reason


def test_a_tolerance_below_the_references_accuracy_is_refused_with_the_number():
    with pytest.raises(ParameterError, match=r"1\.0e-05 on volume is below the reference's own accuracy \(3\.2e-05\)"):
        choose([FULL], 1e-5, "volume", reference_accuracy=3.2e-5)
    assert choose([FULL], 1e-3, "volume", reference_accuracy=3.2e-5).chosen is FULL


@pytest.mark.parametrize(
    "options, message",
    [
        ({"tolerance": 0.0}, "must lie in"),
        ({"tolerance": 1.5}, "must lie in"),
        ({"tolerance": "1e-3"}, "tolerance"),
        ({"tolerance": 1e-3, "queries": 0}, "queries"),
        ({"tolerance": 1e-3, "queries": 2.5}, "queries"),
    ],
)
def test_bad_choices_are_refused_in_one_line(options, message):
    with pytest.raises(ParameterError, match=message):
        choose([FULL], quantity="volume", **options)
    with pytest.raises(ParameterError, match="no candidate"):
        choose([], 1e-3, "volume")
