"""A hyper-reduced lung's averages (lungmech.fem.averages, lungmech.rom.outputs): the numerators
sampled by ECSW, the denominators exact (the reference volume, the current volume's cubic). They
are the full model's averages of the hyper-reduced model's own state to a few τ, on 1 and on 2
ranks; a sample without their cells (a file of an earlier build) gives the other outputs."""

from mpi4py import MPI

import numpy as np
import pytest
from test_hyper_reduced import PROBES, STEPPING, TOLERANCE, hyper_reduced

from lungmech.fem.constraints import clamp
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.model import Model
from lungmech.fem.parametric import Outputs
from lungmech.fem.ramp import Ramp
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.mesh import box
from lungmech.rom.ecsw import AVERAGE, Sample
from lungmech.rom.reduced import ReducedModel


def clamped_lung(comm=MPI.COMM_WORLD) -> Model:
    """A block of lung tissue clamped at x = 0, inflated by a pleural pressure on its far end
    and an alveolar pressure: a state far from homogeneous (every average a true mean)."""
    return Model(
        box(comm, lengths=(3.0, 1.0, 1.0), cells=(9, 3, 3)),
        skeleton(0.16, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, phi_s0=0.3),
        constraints=[clamp("x0")],
        loads=[FollowerPressure("x1", -300.0), AlveolarPressure(100.0, Ramp())],
    )


def assert_averages_reduce(comm) -> None:
    _, galerkin, hyper = hyper_reduced(clamped_lung, comm)
    solution = hyper.solve()
    names = [name for name in solution.outputs if name.startswith("averages/")]
    assert len(names) == 7
    assert all(AVERAGE + name.removeprefix("averages/") in hyper.sample.cells for name in names)
    exact_outputs = Outputs(hyper.model, PROBES)
    exact = {name: [] for name in names}
    for index in range(len(solution.times)):
        hyper.reconstruct(solution, index)
        for name, value in exact_outputs()["averages"].items():
            exact[f"averages/{name}"].append(value)
    for name in names:
        reference = np.array(exact[name])
        scale = np.abs(reference).max()
        assert scale > 0, name
        assert np.abs(solution.outputs[name] - reference).max() <= 5 * TOLERANCE * scale, name
        assert solution.units[name] == ("Pa" if "stress" in name else "1")
    # the Galerkin model's averages are the full ones of its state; the two models agree to a few τ
    g = galerkin.solve()
    for name in names:
        scale = np.abs(g.outputs[name]).max()
        assert np.abs(g.outputs[name] - solution.outputs[name]).max() <= 10 * TOLERANCE * scale, name
    # a sample of an earlier build, without the averages' cells: the other outputs, unchanged
    kept = {k: v for k, v in hyper.sample.cells.items() if not k.startswith(AVERAGE)}
    earlier = Sample(kept, {k: hyper.sample.weights[k] for k in kept}, TOLERANCE)
    older = ReducedModel(clamped_lung(comm), hyper.basis, STEPPING, probes=PROBES, sample=earlier).solve()
    assert not [name for name in older.outputs if name.startswith("averages/")]
    assert (
        np.abs(older.outputs["volume"] - solution.outputs["volume"]).max() <= 1e-12 * solution.outputs["volume"].max()
    )


@pytest.mark.slow
def test_a_hyper_reduced_lung_has_the_averages_of_its_state():
    assert_averages_reduce(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_a_hyper_reduced_lung_has_the_averages_of_its_state_on_two_ranks():
    assert_averages_reduce(MPI.COMM_WORLD)


@pytest.mark.slow
def test_rom_solve_of_a_hyper_reduced_lung_reports_what_run_reports(tmp_path):
    """Through the commands: `rom solve` of a hyper-reduced lung writes every column `run`
    writes (the averages with their units), near the full answer at the defaults (the same
    start); `--sweep` gives the same averages at the output times."""
    import csv

    from test_one_path import IMAGED, _history, _scene

    from lungmech.app.cli import main

    scene, model = _scene(tmp_path, IMAGED), tmp_path / "m.npz"
    build = ["rom", "build", str(scene), "-o", str(model), "--hyper", "ecsw", "--ecsw-tolerance", "1e-4"]
    assert main([*build, "--samples", "2", "--size", "6", "-q"]) == 0
    assert main(["rom", "solve", str(model), "-o", str(tmp_path / "rom"), "-q"]) == 0
    assert main(["run", str(scene), "-o", str(tmp_path / "full"), "-q"]) == 0
    reduced, full = _history(tmp_path / "rom"), _history(tmp_path / "full")
    averages = ["phi_f [1]", "green_lagrange_mean [1]", "mean_stress_skeleton [Pa]", "mean_stress_total [Pa]"]
    assert set(averages) <= set(full[0]) and set(full[0]) - {"error_indicator [1]"} <= set(reduced[0])
    for name in averages:
        mine, theirs = (np.array([float(r[name]) for r in rows]) for rows in (reduced, full))
        assert np.abs(mine - theirs).max() <= 1e-3 * np.abs(theirs).max(), name
    points = _scene(tmp_path, "stiffness [Pa]\n200\n", "points.csv")
    assert main(["rom", "solve", str(model), "--sweep", str(points), "-o", str(tmp_path / "swept"), "-q"]) == 0
    with open(tmp_path / "swept" / "sweep.csv") as stream:
        table = list(csv.DictReader(stream))
    at_outputs = [r for r in reduced if float(r["time [s]"]) in (0.5, 1.0)]
    for name in averages:
        assert [float(r[name]) for r in table] == pytest.approx([float(r[name]) for r in at_outputs], rel=1e-12)
