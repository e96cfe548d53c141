"""The trade on a small scene (lungmech.app.trade): every full model measured against a finer
reference on the same points, each in a process of its own; the choice by tolerance; the
reference solves kept in the cache for the next trade; failures at the box's extremes
reported, never dropped."""

import math
from pathlib import Path

import numpy as np
import pytest

from lungmech.app import scene as scenes
from lungmech.app.trade import peak_time, trade
from lungmech.errors import ParameterError
from lungmech.trade.points import failure_bound

pytestmark = pytest.mark.serial  # each candidate runs in a process of its own

SCENE = """
title = "a thick sphere octant inflated from inside"
[geometry]
builder = "sphere"
inner_radius = 0.5
outer_radius = 1.0
mesh_size = 0.4
[material]
law = "neo_hookean"
E = 10.0
nu = 0.3
[[constraints]]
type = "symmetry"
boundary = "x0"
component = 0
[[constraints]]
type = "symmetry"
boundary = "y0"
component = 1
[[constraints]]
type = "symmetry"
boundary = "z0"
component = 2
[[loads]]
type = "follower_pressure"
name = "inner"
boundary = "inner"
value = 0.5
ramp = {{ times = [0.0, 1.0, 2.0], values = [0.0, 1.0, 0.5] }}
[stepping]
end = 2.0
max_step = 0.5
min_step = {min_step}
[parameters.stiffness]
target = "material.E"
range = [{low}, 20.0]
[output]
probes = [[0.5, 0.0, 0.0]]
"""


def written(folder: Path, low: float = 5.0, min_step: float = 1e-3) -> Path:
    path = folder / "sphere.toml"
    path.write_text(SCENE.format(low=low, min_step=min_step))
    return path


def test_the_peak_load_time_is_where_the_ramps_peak(tmp_path):
    assert peak_time(scenes.load(written(tmp_path))) == 1.0  # the ramp rises to 1 at t = 1, then falls


def test_a_loose_tolerance_chooses_a_cheap_model_and_a_tight_one_a_finer_one(tmp_path):
    scene, cache = written(tmp_path), tmp_path / "cache"
    loose = trade(scene, 5e-2, count=2, cache=cache, levels=2)
    assert loose.reference == "full P1 h/4"
    names = {m.name for m in loose.measured}
    assert {"full P1 h", "full P1 h/2", "full P2 h"} <= names
    assert len(loose.points) == 4 and loose.points.kinds.count("corner") == 2
    for m in loose.measured:  # measured, against an independent finer reference: never zero
        assert m.failed == 0 and 0 < m.error < 0.2 and m.online > 0
    by_name = {m.name: m for m in loose.measured}
    assert by_name["full P1 h/2"].error < by_name["full P1 h"].error  # refinement converges
    assert loose.choice is not None and loose.choice.chosen is not None
    cheapest = min((m for m in loose.measured if m.error <= 5e-2), key=lambda m: m.online)
    assert loose.choice.chosen.name == cheapest.name
    assert set(loose.convergence) == {"volume", "probes"}
    assert math.isfinite(loose.convergence["volume"].observed)
    kept = loose.results["full P1 h/4"]["kept"]
    assert not any(kept)
    # a second trade, tighter: the same solves come from the cache, and a finer model is chosen
    tight_tolerance = 0.5 * (by_name["full P1 h/2"].error + by_name["full P2 h"].error)
    tight = trade(scene, tight_tolerance, count=2, cache=cache, levels=2)
    assert all(all(result["kept"]) for result in tight.results.values())
    assert tight.choice is not None and tight.choice.chosen is not None
    assert tight.choice.chosen.error <= tight_tolerance < by_name["full P1 h"].error
    for name in ("full P1 h", "full P2 h"):
        assert np.array_equal(tight.errors[name]["volume"], loose.errors[name]["volume"])
    assert failure_bound(len(loose.points)) == pytest.approx(1 - 0.05 ** (1 / 4))


def test_a_model_failing_at_a_corner_is_reported_there(tmp_path):
    """At E = 0.05 Pa the pressure is far past the sphere's limit point: every model fails
    there, and says so, and no candidate is chosen on the others."""
    scene = written(tmp_path, low=0.05, min_step=0.25)  # a failure found after few step cuts
    found = trade(scene, 5e-2, count=1, cache=tmp_path / "cache", levels=2)
    corner = found.points.points.index({"stiffness": 0.05})
    for m in found.measured:
        assert m.failed >= 1
        assert found.results[m.name]["answers"][corner]["failed"]
    assert any("the reference failed at" in note for note in found.notes)
    assert found.choice is not None and found.choice.chosen is None


def test_bad_requests_are_one_line(tmp_path):
    with pytest.raises(ParameterError, match="quantity must be one of"):
        trade(written(tmp_path), 1e-2, quantity="speed", cache=tmp_path / "cache")
    with pytest.raises(ParameterError, match="--levels"):
        trade(written(tmp_path), 1e-2, levels=0, cache=tmp_path / "cache")
