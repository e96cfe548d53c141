"""A patient's model by a recipe: the measured recipes of the bundled lung's trade, packaged as
written from the committed trade, and the one a tolerance picks."""

import json
from pathlib import Path

import pytest

from lungmech.app.recipe import MEASURED, measured_recipes, recipe_for
from lungmech.errors import ParameterError

TRADE = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "trade.json"


def test_the_packaged_recipes_are_the_committed_trades():
    """The package data is what `python -m lungmech.app.recipe benchmarks/results/trade.json`
    writes: rerun it when the trade is measured again."""
    packaged = json.loads(MEASURED.read_text())
    packaged.pop("from")
    assert packaged == measured_recipes(json.loads(TRADE.read_text()))
    assert {r["family"] for r in packaged["recipes"]} <= {"galerkin", "ecsw"}


@pytest.mark.parametrize("tolerance", [1e-1, 1e-2, 3e-3, 1.5e-3, 1e-3])
def test_a_tolerance_takes_the_cheapest_recipe_that_met_it(tolerance):
    recipes = json.loads(MEASURED.read_text())["recipes"]
    met = [r for r in recipes if r["worst_error"] <= tolerance]
    if not met:
        with pytest.raises(ParameterError, match="no reduced model of the bundled lung's trade"):
            recipe_for(tolerance)
        return
    chosen = recipe_for(tolerance)
    cheapest = min(met, key=lambda r: r["online_ms"])
    assert (chosen.size, chosen.training, chosen.tau) == (cheapest["size"], cheapest["training"], cheapest["tau"])
    assert cheapest["name"] in chosen.source


def test_a_tolerance_no_recipe_met_names_the_most_accurate():
    best = min(r["worst_error"] for r in json.loads(MEASURED.read_text())["recipes"])
    with pytest.raises(ParameterError, match=rf"is off by {best:.1e}"):
        recipe_for(best / 2)
