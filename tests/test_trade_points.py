"""Where a trade is measured: interior points no model was trained on, and the box's extremes."""

import itertools

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.trade.points import CORNERS, failure_bound, validation_points


def box(dimension: int) -> Parameters:
    """A box of ``dimension`` parameters, the first on a log scale."""
    return Parameters(
        [Parameter(f"p{i}", f"material.c{i}", 200.0, (100.0, 400.0), log=i == 0) for i in range(dimension)]
    )


@pytest.mark.parametrize("dimension", [1, 2, 3, 5])
def test_every_corner_while_there_are_at_most_32(dimension):
    """2^d corners, each once, after the interior points, and the interior inside the box."""
    parameters = box(dimension)
    found = validation_points(parameters, 7, seed=3)
    assert len(found) == 7 + 2**dimension
    assert found.kinds == ["interior"] * 7 + ["corner"] * 2**dimension
    units = np.array([parameters.to_unit(p) for p in found.points])
    corners = {tuple(u) for u in np.round(units[7:], 12)}
    assert corners == set(itertools.product((0.0, 1.0), repeat=dimension))
    assert np.all((units[:7] > 0) & (units[:7] < 1))


def test_beyond_32_corners_a_seeded_choice_and_the_face_centres():
    """d = 6: 32 distinct corners of 64, drawn the same for the same seed, and the 12 face
    centres (one coordinate at an end, the others at ½)."""
    parameters = box(6)
    found = validation_points(parameters, 4, seed=9)
    assert found.kinds == ["interior"] * 4 + ["corner"] * CORNERS + ["face"] * 12
    units = np.round([parameters.to_unit(p) for p in found.points], 12)
    corners = {tuple(u) for u, kind in zip(units, found.kinds) if kind == "corner"}
    assert len(corners) == CORNERS and all(set(c) <= {0.0, 1.0} for c in corners)
    faces = [u for u, kind in zip(units, found.kinds) if kind == "face"]
    assert all(np.sum(np.isin(u, (0.0, 1.0))) == 1 and np.sum(u == 0.5) == 5 for u in faces)
    assert {tuple(u) for u in faces} == {
        tuple(np.where(np.arange(6) == axis, end, 0.5)) for axis in range(6) for end in (0.0, 1.0)
    }
    again = validation_points(parameters, 4, seed=9)
    assert again.points == found.points
    other = validation_points(parameters, 4, seed=10)
    assert {tuple(np.round(parameters.to_unit(p), 12)) for p in other.points[4 : 4 + CORNERS]} != corners


def test_the_interior_is_the_box_sample_of_its_seed_less_the_training():
    """Without training points the interior points are ``Parameters.sample``'s of the same seed;
    a training point among them is left out and the next Sobol' point taken instead."""
    parameters = box(3)
    plain = validation_points(parameters, 6, seed=5)
    assert plain.points[:6] == parameters.sample(6, seed=5)
    trained = [plain.points[2], {"p0": 150.0, "p1": 200.0, "p2": 300.0}]
    kept = validation_points(parameters, 6, seed=5, trained=trained)
    assert plain.points[2] not in kept.points[:6]
    assert kept.points[:6] == [p for p in parameters.sample(7, seed=5) if p != plain.points[2]]


def test_a_box_without_parameters_has_the_defaults_alone():
    found = validation_points(Parameters(), 5)
    assert found.points == [{}] and found.kinds == ["interior"]


def test_the_failure_bound_is_the_rule_of_three():
    """1 − 0.05^(1/N): 5 % of passing every point at that share; ≈ 3/N for large N."""
    for count in (1, 10, 59, 300):
        share = failure_bound(count)
        assert (1 - share) ** count == pytest.approx(0.05, rel=1e-12)
    assert failure_bound(300) == pytest.approx(3 / 300, rel=0.01)
    assert failure_bound(1) == pytest.approx(0.95)


@pytest.mark.parametrize("count", [0, -1, 2.5, True])
def test_a_count_that_is_no_positive_integer_is_refused_in_one_line(count):
    with pytest.raises(ParameterError, match="test point count"):
        validation_points(box(2), count)
    with pytest.raises(ParameterError, match="test point count"):
        failure_bound(count)
