"""Greedy training to a tolerance: the residual indicator estimates the error it reports next
to, and the trained model meets its tolerance at points it never saw."""

import json
from dataclasses import replace

from mpi4py import MPI

import numpy as np
import pytest
from fem import BOX, PARAMETRIC_SCENE, pushed_block, write_once

from lungmech.errors import ParameterError
from lungmech.fem import BodyForce, LinearElastic, Model, Stepping, Traction, clamp
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.fem.parametric import FullOrderModel
from lungmech.mesh import box
from lungmech.parallel.linalg import apply, gram
from lungmech.rom.ecsw import TANGENT, TANGENT_STATES, Training
from lungmech.rom.greedy import greedy
from lungmech.rom.indicator import ResidualIndicator
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reductor import POD, TrainingSet, errors, reduce


@pytest.fixture(scope="module")
def full():
    return pushed_block()


@pytest.fixture(scope="module")
def trained(full):
    return greedy(full, Parameters(BOX).sample(16, seed=1), 1e-3)


def test_the_trained_model_meets_its_tolerance_where_it_never_looked(full, trained):
    """Six points of another seed: each true energy-norm error is below the tolerance, and the
    indicator of each answer is within a factor 2 of it."""
    assert trained.met and trained.training[0] == full.parameters.defaults
    reduced = ReducedModel(full.model, trained.basis, full.stepping, start=None, training=trained.training)
    indicator = ResidualIndicator(full.model)
    for mu in Parameters(BOX).sample(6, seed=77):
        answer = reduced.solve(mu)
        error = errors(reduced, full.solve(mu), answer).energy
        assert error <= 1e-3
        assert 1 / 2 <= indicator(reduced, answer) / error <= 2
    indicator.destroy()


def test_each_round_reports_its_indicator_next_to_the_true_error(trained):
    """Every full solve measured the error it was chosen for; the indicator is within a factor 2
    of it, the errors fall, and the last round's indicator (with the measured safety) meets the
    tolerance."""
    chosen = trained.rounds[:-1]
    assert len(chosen) == len(trained.training) - 1 >= 2
    for round in chosen:
        assert 1 / 2 <= round.indicator / round.error <= 2
    assert chosen[-1].error < chosen[0].error / 10
    assert trained.rounds[-1].error is None and trained.rounds[-1].indicator * trained.safety <= 1e-3
    near = [r.error / r.indicator for r in chosen if r.error <= 1e-2]
    assert trained.safety == max(1.0, *near[-3:])


def test_the_indicator_is_the_error_itself_for_a_linear_model():
    """K = E for linear elasticity under dead loads: the Newton correction E⁻¹ R(x_r) is x − x_r
    exactly, so the indicator equals the true error (relative to the reduced change, not the
    full one: the two differ by the error's own share)."""
    model = Model(
        box(MPI.COMM_SELF, cells=(6, 2, 2)),
        lambda c: LinearElastic.from_young(c["E"], 0.3),
        constraints=[clamp("x0")],
        loads=[Traction("x1", (0.0, 0.0, -0.1), name="pull"), BodyForce((0.0, 0.05, 0.0), name="weight")],
        parameters=[
            Parameter("E", "material.E", 10.0, (5.0, 20.0)),
            Parameter("g", "loads.weight.amplitude", 0.0, (0.0, 1.0)),
        ],
    )
    full = FullOrderModel(model, Stepping(end=1.0, times=(0.5,)))
    poor = reduce(full, POD(1), TrainingSet([{"E": 5.0}]))  # the traction's response alone
    indicator = ResidualIndicator(model)
    mu = {"E": 17.0, "g": 0.7}
    answer = poor.solve(mu)
    error = errors(poor, full.solve(mu), answer).energy
    assert error > 1e-3  # one vector of one load path: not exact elsewhere
    eta = indicator(poor, answer)
    indicator.destroy()
    # both are largest at the end of the linear path; η is relative to ‖x_r‖_E, the error to ‖x‖_E
    end = len(answer.times) - 1
    states = np.column_stack([full.solve(mu).states[end], poor.reconstruct(answer, end)])
    W = poor.energy_product
    norms = np.sqrt(np.diag(gram(states, apply(W, states, MPI.COMM_SELF), MPI.COMM_SELF)))
    assert eta == pytest.approx(error * norms[0] / norms[1], rel=1e-8)


@pytest.fixture(scope="module")
def online(full, trained):
    """The Galerkin and hyper-reduced models of the trained basis, each answer with the online
    indicator of the next four POD directions (the ECSW sample trained on them too)."""
    from lungmech.rom import ecsw
    from lungmech.rom.pod import snapshots

    model, k = full.model, trained.basis.size
    W = trained.modes.vectors[:, k : k + 4]
    extended = replace(trained.basis, vectors=np.hstack([trained.basis.vectors, W]))
    runs = lambda: snapshots(model, full.stepping, solver=full.solver, parameters=trained.training)  # noqa: E731
    sample = ecsw.train(model, extended, full.solver, runs, 1e-5)
    galerkin = ReducedModel(model, trained.basis, full.stepping, training=trained.training, enrichment=W)
    hyper = ReducedModel(model, trained.basis, full.stepping, training=trained.training, sample=sample, enrichment=W)
    return galerkin, hyper


def test_every_online_answer_carries_its_indicator(full, online):
    """At six unseen points the online indicator (the Newton correction along the next POD
    directions) lies between a third of the true error and 1.5 times it, for the Galerkin and
    the hyper-reduced model alike; the hyper-reduced one never reads the full state."""
    galerkin, hyper = online
    for mu in Parameters(BOX).sample(6, seed=77):
        reference = full.solve(mu)
        for reduced in (galerkin, hyper):
            answer = reduced.solve(mu)
            error = errors(reduced, reference, answer).energy
            assert error / 3 <= answer.indicator <= 1.5 * error, (reduced.solver.description, mu)
    state = hyper.model.state.x.array
    state[:] = np.nan
    assert np.isfinite(hyper.solve({"E": 7.0}).indicator) and np.isnan(state).all()
    hyper.model.reset()


def test_the_online_indicator_reuses_the_last_newton_assembly(online, monkeypatch):
    """Right after a solve the indicator assembles nothing: it takes Newton's last residual (at
    the answer: the numbers a new assembly gives) and its last tangent (at the iterate before:
    within the last step's size of the answer's); at new loads both are assembled anew."""
    from dolfinx import fem

    _, hyper = online
    solver = hyper.solver
    hyper.solve({"E": 7.0})
    hyper.model.set_time(1.0)  # the peak of the push
    assert solver.solve().converged
    hyper.outputs()  # as an answer records them first (on the reduced mesh, at these loads)
    assembled = []
    for name in ("assemble_matrix", "assemble_vector"):
        original = getattr(fem, name)
        monkeypatch.setattr(fem, name, lambda *a, _f=original, _n=name, **k: assembled.append(_n) or _f(*a, **k))
    q, reused, tangent = solver.enriched_terms()
    assert assembled == [] and np.abs(reused).max() > 0
    solver.linear_step()  # the loads set anew, and a Newton step from the answer: a round-off one
    q_again, fresh, fresh_tangent = solver.enriched_terms()
    assert assembled.count("assemble_matrix") >= 2 and assembled.count("assemble_vector") >= 2
    np.testing.assert_allclose(q_again, q, rtol=1e-9, atol=1e-9 * np.abs(q).max())
    np.testing.assert_allclose(fresh, reused, rtol=1e-6, atol=1e-6 * np.abs(reused).max())
    np.testing.assert_allclose(fresh_tangent, tangent, rtol=1e-4, atol=1e-6 * np.abs(tangent).max())


@pytest.mark.slow
def test_a_hyper_reduced_greedy_judges_and_meets_its_tolerance_as_itself(full):
    """With hyper = τ each round judges the hyper-reduced model by its own online indicator (an
    ECSW sample per round from the full solves' Newton iterates): the model it returns, basis,
    enrichment and sample, meets the tolerance at unseen points, its indicator within [1/3, 1.5]
    of its error."""
    from lungmech.rom.indicator import enrichment

    trained = greedy(full, Parameters(BOX).sample(16, seed=1), 1e-3, hyper=1e-5)
    assert trained.met and trained.sample is not None
    W = enrichment(trained.basis, trained.modes)
    hyper = ReducedModel(full.model, trained.basis, full.stepping, sample=trained.sample, enrichment=W)
    for mu in Parameters(BOX).sample(6, seed=77):
        answer = hyper.solve(mu)
        error = errors(hyper, full.solve(mu), answer).energy
        assert error <= 1e-3 and error / 3 <= answer.indicator <= 1.5 * error
    # the Newton iterates it kept give its sample again, and another τ's, without a full solve
    training = Training(full.model, np.hstack([trained.basis.vectors, W]))
    training.replay(trained.iterates)
    steps = len({(t, tuple(mu.values())) for _, t, mu in trained.iterates})  # each load step's
    assert training.added["internal" + TANGENT] == min(TANGENT_STATES, steps)  # tangents at a few
    again, coarser = training.sample(1e-5), training.sample(1e-2)
    training.destroy()
    for family, cells in trained.sample.cells.items():
        np.testing.assert_array_equal(again.cells[family], cells)
        np.testing.assert_allclose(again.weights[family], trained.sample.weights[family], rtol=1e-12)
        assert len(coarser.cells[family]) <= len(cells)
    assert sum(map(len, coarser.cells.values())) < sum(map(len, trained.sample.cells.values()))
    loads = {(t, tuple(mu.values())) for _, t, mu in trained.iterates}
    assert len(loads) < len(trained.iterates)  # several iterates per load: not only the converged ones
    with pytest.raises(ParameterError, match="the ECSW tolerance must lie in"):
        greedy(full, Parameters(BOX).sample(2), 1e-3, hyper=0.0)


def test_a_model_without_enrichment_gives_no_indicator(full, trained):
    """Without directions beyond its basis the model does not pretend to know its error; an
    enrichment of another space is refused."""
    plain = ReducedModel(full.model, trained.basis, full.stepping)
    assert plain.solve({"E": 7.0}).indicator is None and full.solve({"E": 7.0}).indicator is None
    with pytest.raises(ParameterError, match="the enrichment must have the basis'"):
        ReducedModel(full.model, trained.basis, full.stepping, enrichment=np.ones((3, 2)))


def test_a_tolerance_out_of_reach_is_reported_not_met(full):
    """Allowed two full solves, the training cannot reach 1e-6: it says so, and the rounds show
    the indicator it stopped at."""
    stopped = greedy(full, Parameters(BOX).sample(8, seed=1), 1e-6, most=2)
    assert not stopped.met and len(stopped.training) == 2
    assert stopped.rounds[-1].indicator > 1e-6


def test_when_the_candidates_run_out_the_training_points_are_judged(full):
    """At a tolerance out of reach every candidate becomes a full solve. The last round's
    indicator, which the build prints, is then the largest over the model's own training
    points, recomputed here: not the 0 of an empty candidate list called 'met'."""
    stopped = greedy(full, Parameters(BOX).sample(3, seed=1), 1e-12)
    assert not stopped.met and len(stopped.training) == 4
    reduced = ReducedModel(full.model, stopped.basis, full.stepping, start=None, training=stopped.training)
    indicator = ResidualIndicator(full.model)
    recomputed = [indicator(reduced, reduced.solve(point)) for point in stopped.training]
    indicator.destroy()
    assert max(recomputed) > 0
    assert stopped.rounds[-1].indicator == pytest.approx(max(recomputed), rel=1e-6)
    assert stopped.rounds[-1].point == stopped.training[int(np.argmax(recomputed))]


@pytest.mark.parametrize(
    ("tolerance", "candidates", "said"),
    [
        (float("nan"), None, "greedy tolerance must be a finite number"),
        (2.0, None, "must lie in \\(0, 1\\)"),
        (1e-3, [], "at least one candidate"),
    ],
)
def test_bad_greedy_inputs_are_refused(full, tolerance, candidates, said):
    with pytest.raises(ParameterError, match=said):
        greedy(full, Parameters(BOX).sample(2) if candidates is None else candidates, tolerance)


SCENE = PARAMETRIC_SCENE


def test_rom_build_to_a_tolerance_from_the_command_line(tmp_path, capsys):
    """rom build --tolerance: greedy over the box, each round's indicator next to its true error
    (with units for the points), the model file records it, and rom solve answers within it."""
    from lungmech.app.cli import main
    from lungmech.rom import store

    scene = tmp_path / "scene.toml"
    write_once(scene, SCENE)
    model = tmp_path / "m.npz"
    assert main(["rom", "build", str(scene), "-o", str(model), "--tolerance", "1e-3", "--samples", "8", "-q"]) == 0
    said = capsys.readouterr().out
    assert "greedy training: tolerance 0.001 met with" in said and "true error" in said and " Pa, pull = " in said
    recorded = store.read(model, arrays=False)[0]["extra"]["reduced"]["built"]["greedy"]
    assert recorded["met"] and recorded["full_solves"] == len(recorded["rounds"]) >= 2
    assert all(r["error"] is not None for r in recorded["rounds"][:-1])
    out = tmp_path / "answer"
    assert main(["rom", "solve", str(model), "-o", str(out), "--set", "stiffness=700", "--set", "pull=4", "-q"]) == 0
    assert "estimated error" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert 0 < summary["error_indicator"] < 1e-2
    header = (out / "history.csv").read_text().splitlines()[0]
    assert "error_indicator [1]" in header
    for refused, said in (
        (["--scales", "0.5,1"], "put a load's amplitude in [parameters] instead of giving --scales"),
        (["--basis", "modal"], "--tolerance trains a POD basis (got --basis modal)"),
    ):
        assert main(["rom", "build", str(scene), "-o", str(tmp_path / "n.npz"), "--tolerance", "0.01", *refused]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "n.npz").exists()
