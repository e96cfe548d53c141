"""The trade on a small scene (lungmech.app.trade): failures at the box's extremes reported,
never dropped; bad requests in one line. The choice by tolerance, the cache and the outputs:
tests/test_trade_cli.py."""

import pytest
from trades import written

from lungmech.app import scene as scenes
from lungmech.app.cache import Cache
from lungmech.app.ladder import Discretisation, at
from lungmech.app.reduce import family_files
from lungmech.app.trade import Candidate, Family, candidates, peak_time, trade
from lungmech.errors import ParameterError

pytestmark = pytest.mark.serial  # each candidate runs in a process of its own


def test_the_peak_load_time_is_where_the_ramps_peak(tmp_path):
    assert peak_time(scenes.load(written(tmp_path))) == 1.0  # the ramp rises to 1 at t = 1, then falls


def test_a_model_failing_at_a_corner_is_reported_there(tmp_path):
    """At E = 0.05 Pa the pressure is far past the sphere's limit point: every model fails
    there, and says so, and no candidate is chosen on the others."""
    scene = written(tmp_path, low=0.05, min_step=0.25)  # a failure found after few step cuts
    full = [Candidate.full(Discretisation(0, 1))]
    found = trade(scene, 5e-2, count=1, cache=tmp_path / "cache", levels=1, full=full)
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


def test_a_tolerance_below_the_references_own_error_is_refused(tmp_path):
    """Three nested levels converging at exactly the expected order (2 for a P1 volume): the
    reference's own error is Richardson's estimate, and a tolerance below it is refused with
    the number; one above it is judged."""
    from lungmech.app.trade import Trade, _judge
    from lungmech.trade.points import ValidationPoints

    scene = scenes.load(written(tmp_path))
    levels = [Candidate.full(Discretisation(level, 1)) for level in range(3)]

    def judged(tolerance: float) -> Trade:
        found = Trade("sphere.toml", tolerance, "volume", ValidationPoints([{}], ["interior"]), [1.0], levels[2].name)
        for candidate, h in zip(levels, (1.0, 0.5, 0.25), strict=True):
            volume = 2.0 + 0.01 * h**2  # → 2 at order 2, from a start of 1
            answer = {"failed": None, "volume": [volume], "start_volume": 1.0, "probes": [[[0.0, 0.0, 0.0]]]}
            found.results[candidate.name] = {"answers": [answer], "online_seconds": 1 / h, "offline_seconds": 0.0}
        _judge(found, scene, levels, 2)
        return found

    own = 0.01 * (0.5**2 - 0.25**2) / 3 / (2.000625 - 1.0)  # Richardson: the finest difference / (2² − 1)
    found = judged(1e-2)
    assert found.convergence["volume"].observed == pytest.approx(2.0)
    assert found.convergence["volume"].estimate == pytest.approx(own)
    assert found.choice.chosen.name == "full P1 h"  # 9.4e-3 ≤ 1e-2, the cheapest
    with pytest.raises(ParameterError, match=r"below the reference's own accuracy \(6\.2e-04\)"):
        judged(5e-4)


def test_the_candidates_of_a_scene_and_what_is_not_made(tmp_path):
    """The sphere (a builder's mesh, a law with a volumetric split): a 2h remesh, h and h/2, P2
    and Taylor–Hood P2–P1 on h, the reference h/4. The bundled lung (poromechanics) has no
    mixed version, and a mesh file no coarser level: both said in a note."""
    from lungmech.scenes import bundled

    made, reference, notes = candidates(scenes.load(written(tmp_path)), levels=2)
    assert [c.name for c in made] == ["full P1 2h", "full P1 h", "full P1 h/2", "full P2 h", "full P2–P1 h"]
    assert reference.name == "full P1 h/4" and not notes
    assert made[-1].request["discretisation"] == {"level": 0, "degree": 2, "mixed": True}
    lung = scenes.load(bundled("lung_breathing_parameters"))
    made, _, notes = candidates(lung, levels=1)
    assert "full P2–P1 h" not in [c.name for c in made]
    assert notes == [
        "no mixed full model: formulation.type: the poromechanics formulation has no Taylor–Hood (mixed) version"
    ]
    with pytest.raises(ParameterError, match="Taylor–Hood: its displacement degree is ≥ 2"):
        Discretisation(0, 1, mixed=True)
    mixed = written(tmp_path, name="mixed.toml")
    mixed.write_text(mixed.read_text().replace("nu = 0.3\n", 'nu = 0.3\n[formulation]\ntype = "mixed"\ndegree = 2\n'))
    own = scenes.load(mixed)
    made, reference, notes = candidates(own, levels=2)  # its own ladder stays mixed, and has no P1
    assert [c.name for c in made] == ["full P2–P1 2h", "full P2–P1 h", "full P2–P1 h/2"] and not notes
    assert reference.name == "full P2–P1 h/4"
    assert at(own, Discretisation.of(own), Cache(tmp_path / "cache")).formulation is own.formulation


def test_a_family_names_its_models_by_tau_and_size_and_refuses_repeats():
    """One size: the names and files of before; several: each ends in its size k; no τ, no size
    twice; Galerkin alone without τ."""
    assert family_files((1e-3,)) == {"POD Galerkin": "galerkin.npz", "POD ECSW τ=0.001": "ecsw-0.001.npz"}
    assert family_files((1e-3,), (5, 10)) == {
        "POD Galerkin k=5": "galerkin-5.npz",
        "POD Galerkin k=10": "galerkin-10.npz",
        "POD ECSW τ=0.001 k=5": "ecsw-0.001-5.npz",
        "POD ECSW τ=0.001 k=10": "ecsw-0.001-10.npz",
    }
    assert Family(taus=(), sizes=(4, 8)).taus == ()
    for family, said in (
        (lambda: Family(taus=(1e-3, 1e-3)), "given twice"),
        (lambda: Family(sizes=(5, 5)), "the basis sizes are given twice"),
        (lambda: Family(sizes=()), "--sizes: give at least one basis size"),
        (lambda: Family(sizes=(0,)), "--sizes: a basis size"),
        (lambda: Family(taus=(1.5,)), "lies in"),
    ):
        with pytest.raises(ParameterError, match=said):
            family()
