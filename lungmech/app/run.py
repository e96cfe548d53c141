"""Run a scene: build what it declares, solve with load stepping, write the outputs safely.

A run writes into a staging folder that replaces its output folder only when everything has
succeeded (see :mod:`lungmech.parallel.destination`). Files, with SI units throughout:

* ``summary.json``: the run's numbers, a ``units`` table naming the unit of each, and its
  ``provenance`` (lungmech version, the scene file and its SHA-256, MPI ranks, date);
* ``history.csv``: one row per accepted step, columns ``name [unit]``;
* ``fields.pvd`` with ``.vtu`` files (or ADIOS2 ``.bp`` folders): fields at every step;
* ``deformed.png``: the body at its largest volume, coloured by J;
* ``pressure_volume.png`` when the scene has pressure loads: volume against the transpulmonary
  pressure of a lung (or against the first pressure load of another body);
* ``reference.xdmf`` for a scene with [inverse]: the unloaded reference it found.
"""

from __future__ import annotations

import csv
import datetime
import hashlib
import json
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

import lungmech
from lungmech import lung
from lungmech.app.console import Progress, volume_text
from lungmech.app.console import pressure as show_pressure
from lungmech.app.output import FieldWriter, write_json
from lungmech.app.plot import deformed_body, drawn, pressure_volume
from lungmech.app.scene import Scene, build_geometry
from lungmech.errors import ParameterError
from lungmech.fem.loads import FollowerPressure, is_pressure
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.quantities import Probe, deformed_volume, strain_energy
from lungmech.fem.solver import NewtonSolver, Solver, StepReport, solve
from lungmech.lung.inverse import InverseReport, unloaded_reference
from lungmech.mesh import write as write_geometry
from lungmech.parallel import deferred, on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.rom.indicator import relative

Scale = float | Sequence[float]

# Units of the summary's numbers (dotted paths) and of history.csv's columns.
SUMMARY_UNITS = {
    "dofs": "1",
    "cells": "1",
    "degree": "1",
    "mpi_ranks": "1",
    "steps": "1",
    "cut_steps": "1",
    "newton_iterations": "1",
    "timings_seconds": "s",
    "start_volume": "m^3",
    "reference_volume": "m^3",
    "deformed_volume": "m^3",
    "largest_volume.volume": "m^3",
    "largest_volume.time": "s",
    "strain_energy": "J",
    "load_scale": "1",
    "parameters": "as declared in the scene's [parameters] (see their units there)",
    "probes.points": "m",
    "probes.displacement": "m",
    "inverse.iterations": "1",
    "inverse.mismatch": "1 (fraction of the body's size)",
    "inverse.newton_iterations": "1",
    "inverse.seconds": "s",
    "inverse.imaged_volume": "m^3",
    "inverse.reference_volume": "m^3",
    "error_indicator": "1 (a reduced model's estimate of its relative energy-norm error)",
}
_COLUMN_UNITS = {
    "time": "s",
    "volume": "m^3",
    "strain_energy": "J",
    "newton_iterations": "1",
    "step_seconds": "s",
    "phi_s": "1",
    "phi_f": "1",
    "phi_s_current": "1",
    "green_lagrange_mean": "1",
    "error_indicator": "1",
}


def build_model(scene: Scene, comm: MPI.Comm = MPI.COMM_WORLD) -> Model:
    """The model a scene declares, and nothing else, at the scene's parameter values."""
    geometry = build_geometry(scene.geometry, comm)
    material_parameters = any(p.kind == "material" for p in scene.parameters)
    model = Model(
        geometry,
        scene.law() if material_parameters else scene.material,
        degree=scene.degree,
        plane=scene.plane,
        formulation=scene.formulation,
        loads=scene.loads,
        constraints=scene.constraints,
        parameters=scene.parameters,
    )
    model.set_parameters(scene.values)
    return model


def full_order_model(scene: Scene, comm: MPI.Comm = MPI.COMM_WORLD) -> FullOrderModel:
    """The scene's full-order model as a parametric model (``solve(mu)``). A scene with [inverse]
    first finds the unloaded reference of its imaged mesh, once, at the default parameters; every
    solve then starts from the imaged state. Collective."""
    model = build_model(scene, comm)
    solver = NewtonSolver(model, scene.newton)
    start = None
    if scene.inverse is not None:
        model.set_parameters(model.parameters.defaults)
        unloaded_reference(model, scene.stepping.start, scene.inverse, solver=solver)
        start = model.state.x.array.copy()
        model.set_parameters(scene.values)
    return FullOrderModel(model, scene.stepping, scene.newton, scene.output.probes, start, solver)


def load_values(scene: Scene, t: float, scale: Scale = 1.0) -> dict[str, float]:
    """The current values (Pa) of the scene's scalar (pressure) loads, by label; ``scale``
    multiplies their change since the start, as in :meth:`Model.set_time`."""
    values = {}
    factors = np.broadcast_to(np.asarray(scale, dtype=float), (len(scene.loads),))
    for load, factor in zip(scene.loads, factors):
        if is_pressure(load):
            base = load.ramp(scene.stepping.start)
            values[load.label] = (base + factor * (load.ramp(t) - base)) * load.value
    return values


def pressure_axis(scene: Scene) -> tuple[str, Callable[[dict[str, float]], float], list[str]] | None:
    """The pressure of the P–V curve: its name, its value from the load values by label, and
    what it is made of. For a lung (the lung model, an alveolar pressure, or a follower pressure
    on the pleura), the transpulmonary pressure p_alv − p_pl (p_pl: the follower pressure on the
    pleura, or the first one); otherwise the first pressure load. None without pressure loads."""
    scalars = [load for load in scene.loads if is_pressure(load)]
    if not scalars:
        return None
    alveolar = [load.label for load in scalars if isinstance(load, lung.AlveolarPressure)]
    followers = [load for load in scalars if isinstance(load, FollowerPressure)]
    on_pleura = [
        load
        for load in followers
        if "pleura" in ((load.boundary,) if isinstance(load.boundary, str) else load.boundary)
    ]
    pleural = [load.label for load in (on_pleura or followers)[:1]]
    if alveolar or on_pleura or isinstance(scene.formulation, lung.Poromechanics):
        parts = [f"p_pl: {' + '.join(pleural) or 'none (0)'}", f"p_alv: {' + '.join(alveolar) or 'atmospheric (0)'}"]
        return (
            "transpulmonary pressure p_alv − p_pl",
            lambda v: sum(v[a] for a in alveolar) - sum(v[p] for p in pleural),
            parts,
        )
    first = scalars[0].label
    return first, lambda v: v[first], []


def check_scale(scene: Scene, scale: Scale) -> Scale:
    """``scale`` as given, if it is one finite factor or one per load of the scene."""
    try:
        factors = np.atleast_1d(np.asarray(scale, dtype=float))
    except (TypeError, ValueError):
        factors = np.array([np.nan])
    if factors.ndim != 1 or len(factors) not in (1, len(scene.loads)) or not np.all(np.isfinite(factors)):
        raise ParameterError(
            f"load scale: give one finite factor or one per load ({len(scene.loads)} in this scene), got {scale!r}"
        )
    return scale


@dataclass(frozen=True)
class Prepared:
    """What a run's ``prepare`` step gives: the solver; what it did to the reference (the inverse
    problem's report, or None); and for a reduced model that estimates its error, the estimate
    at the current state, (η̂(t), ‖V q‖_E) (:class:`lungmech.rom.indicator.EnrichedIndicator`)."""

    solver: Solver
    reference: dict | None = None
    estimate: Callable[[], tuple[float, float]] | None = None


def full_order(model: Model, scene: Scene, folder: Path) -> Prepared:
    """The full-order solver, after unloading the imaged mesh when the scene asks for it."""
    solver = NewtonSolver(model, scene.newton)
    return Prepared(solver, _unload(model, scene, solver, folder) if scene.inverse is not None else None)


def _unload(model: Model, scene: Scene, solver: NewtonSolver, folder: Path) -> dict:
    """Replace the (imaged) mesh by its unloaded reference; write it; report how it went."""
    imaged_volume = model.geometry.volume()
    body = "lung" if _is_lung(scene) else "body"
    progress = Progress("unloading the imaged lung" if body == "lung" else "finding the unloaded reference")
    tolerance, most = scene.inverse.tolerance, scene.inverse.max_iterations

    def show(report: InverseReport) -> None:
        first, mismatch = report.mismatch[0], report.mismatch[-1]
        done = np.log(first / max(mismatch, tolerance)) / np.log(first / tolerance) if first > tolerance else 1.0
        progress.update(
            done,
            f"iteration {report.iterations}/{most}: mismatch {mismatch:.2e} of the {body}'s size "
            f"(target {tolerance:.0e})",
        )

    report = unloaded_reference(model, scene.stepping.start, scene.inverse, solver=solver, monitor=show)
    progress.close(
        f"unloaded reference found in {report.iterations} iterations, volume "
        f"{volume_text(model.geometry.volume(), model.plane is not None)} (imaged {volume_text(imaged_volume, model.plane is not None)})"
    )
    write_geometry(model.geometry, folder / "reference.xdmf")
    return {
        "iterations": report.iterations,
        "mismatch": report.mismatch,
        "newton_iterations": report.newton_iterations,
        "seconds": report.seconds,
        "imaged_volume": imaged_volume,
        "reference_volume": model.geometry.volume(),
    } | ({"porosity_mismatch": report.porosity} if report.porosity else {})


def _is_lung(scene: Scene) -> bool:
    return isinstance(scene.formulation, lung.Poromechanics) or any(
        isinstance(load, lung.AlveolarPressure) for load in scene.loads
    )


def run(
    scene: Scene,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    *,
    scale: Scale = 1.0,
    prepare: Callable[[Model, Scene, Path], Prepared] = full_order,
    inputs: Sequence[str | Path] = (),
) -> dict:
    """Solve ``scene`` and write its results into the folder ``out`` (see the module's doc).

    A scene with [inverse] first moves its (imaged) mesh to the unloaded reference; stepping
    then starts from the imaged state. ``scale`` multiplies the loads' change from the start
    (one factor, or one per load): a deeper breath from the same end-expiration.
    ``prepare(model, scene, folder)`` returns the :class:`Prepared` solver (default
    :func:`full_order`; a reduced model's is in :mod:`lungmech.app.reduce`, whose error
    estimate, if it has one, becomes the history's ``error_indicator`` column and the summary's). ``inputs`` are further files the run reads (beyond the scene's
    own), which ``out`` must not hold.

    ``out`` is checked before any work (see :func:`lungmech.parallel.destination.output_folder`) and
    replaced only when the run succeeds. Collective. Returns the summary.
    """
    check_scale(scene, scale)
    timings = {}
    command = f"lungmech run {scene.source}" if scene.source else "lungmech.app.run.run"
    with output_folder(out, comm, inputs=[*scene.inputs, *inputs], command=command) as staging:
        tic = time.perf_counter()
        model = build_model(scene, comm)
        timings["build"] = time.perf_counter() - tic
        tic = time.perf_counter()
        prepared = prepare(model, scene, staging)
        solver, inverse = prepared.solver, prepared.reference
        timings["prepare"] = time.perf_counter() - tic
        tic = time.perf_counter()
        volume, energy = deformed_volume(model), strain_energy(model)
        fractions = lung.averages(model) if "phi_s" in model.fields else {}
        probe = Probe(model.geometry.mesh, scene.output.probes) if scene.output.probes else None
        writer = FieldWriter(model, staging, scene.output.format) if scene.output.fields else None
        timings["compile"] = time.perf_counter() - tic

        axis = pressure_axis(scene)
        stepping = scene.stepping
        progress = Progress("breathing" if axis and axis[0].startswith("transpulmonary") else "loading")
        history = []
        largest = {"volume": -np.inf, "state": None, "time": 0.0}  # pictured at the end
        estimates = []  # (η̂(t), change(t)) of a reduced model that estimates its error

        def record(step: StepReport | None) -> None:
            solver.update_model()  # a hyper-reduced solver iterates on q: the fields written need x
            row = {"time": model.time, "volume": volume(), "strain_energy": energy()}
            loads = load_values(scene, model.time, scale)
            row |= loads
            row |= {name: mean() for name, mean in fractions.items()}
            if step is not None:
                row |= {"newton_iterations": step.iterations, "step_seconds": step.seconds}
            if prepared.estimate is not None:
                estimates.append(prepared.estimate())
                row["error_indicator"] = relative(estimates)  # of the path so far
            if probe is not None:
                for i, value in enumerate(probe(model.displacement())):
                    row |= {f"probe{i}_u{letter}": component for letter, component in zip("xyz", value)}
            history.append(row)
            if row["volume"] > largest["volume"]:
                largest.update(volume=row["volume"], state=model.state.x.array.copy(), time=model.time)
            if writer is not None:
                with deferred(comm):  # a collective write: not cut on one rank only
                    writer.write(model.time)
            shown = (
                f"  {'P_L' if axis[0].startswith('transpulmonary') else 'p'} {show_pressure(axis[1](loads))}"
                if axis
                else ""
            )
            newton = f"  {step.iterations} Newton" if step is not None else ""
            progress.update(
                (model.time - stepping.start) / (stepping.end - stepping.start),
                f"step {len(history) - 1}  t = {model.time:.3g}/{stepping.end:g} s{shown}  "
                f"volume {volume_text(row['volume'], model.plane is not None)}{newton}",
            )

        def cut(step: StepReport) -> None:
            if not step.converged:
                progress.note(
                    f"t = {step.time:.4g} s: Newton did not converge ({step.reason}); step cut back to "
                    f"dt = {step.step / 2:.3g} s (normal adaptivity)"
                )

        try:
            record(None)
            report = solve(
                model,
                stepping,
                solver=solver,
                on_step=record,
                monitor=cut,
                drive=lambda t: model.set_time(t, load_factor=scale, about=stepping.start),
                breakpoints=model.breakpoints,
            )
        finally:  # ADIOS2 must let go of its files before a failed staging folder is removed
            if writer is not None:
                writer.close()
        progress.close(
            f"{len(report.accepted)} steps ({report.failures} cut back), {report.newton_iterations} Newton iterations"
        )
        timings["solve"] = report.seconds

        # Outputs are collective writes: a signal now waits, and stops every rank together.
        hold_signals_until_swap()
        mesh = model.geometry.mesh
        summary = {
            "title": scene.title,
            "parameters": model.parameter_values,
            "provenance": provenance(scene, comm),
            "mpi_ranks": comm.size,
            "dofs": model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs,
            "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
            "law": scene.material.name,
            "degree": scene.degree,
            "formulation": type(scene.formulation).__name__,
            "steps": len(report.accepted),
            "cut_steps": report.failures,
            "newton_iterations": report.newton_iterations,
            "timings_seconds": timings,
            "start_volume": history[0]["volume"],
            "reference_volume": model.geometry.volume(),
            "deformed_volume": history[-1]["volume"],
            "largest_volume": {"volume": largest["volume"], "time": largest["time"]},
            "strain_energy": history[-1]["strain_energy"],
            "inverse": inverse,
            "load_scale": np.asarray(scale, dtype=float).tolist(),
            "solver": solver.description,
            "error_indicator": relative(estimates) if prepared.estimate is not None else None,
            "linear_solver": getattr(solver, "linear_solver", None),  # what "auto" chose, or was pushed to
            "probes": {
                "points": [list(p) for p in scene.output.probes],
                "displacement": probe(model.displacement()).tolist() if probe is not None else [],
            },
            "plane": model.plane,
            "units": per_thickness(SUMMARY_UNITS) if model.plane else SUMMARY_UNITS,
        }
        write_json(staging / "summary.json", summary, comm)
        on_root(comm, lambda: _write_history(scene, history, staging))
        with model.kept_state():
            model.state.x.array[:] = largest["state"]
            model.state.x.scatter_forward()
            shown = volume_text(largest["volume"], model.plane is not None)
            title = f"{scene.title}\nlargest volume {shown}, t = {largest['time']:.3g} s"
            drawn(comm, staging / "deformed.png", lambda: deformed_body(model, staging / "deformed.png", title))
        if axis is not None:
            label, value, parts = axis
            pressures, volumes = [value(row) for row in history], [row["volume"] for row in history]
            drawn(
                comm,
                staging / "pressure_volume.png",
                lambda: on_root(
                    comm,
                    lambda: pressure_volume(
                        pressures,
                        volumes,
                        staging / "pressure_volume.png",
                        label,
                        title=scene.title,
                        note=parts,
                        planar=model.plane is not None,
                    ),
                ),
            )
    return summary


def _write_history(scene: Scene, history: list[dict], folder: Path) -> None:
    """history.csv, its columns named with their units (rank 0)."""
    labels = {load.label for load in scene.loads}
    columns = list(dict.fromkeys(k for row in history for k in row))
    units = {k: _column_unit(k, labels) for k in columns}
    if scene.plane:
        units = per_thickness(units)
    header = [f"{k} [{units[k]}]" for k in columns]
    with open(folder / "history.csv", "w", newline="") as stream:
        table = csv.writer(stream)
        table.writerow(header)
        table.writerows([[row.get(k, "") for k in columns] for row in history])


def per_thickness(units: dict[str, str]) -> dict[str, str]:
    """The units of a 2-D body's results: volumes and energies are per metre of thickness."""
    return {key: {"m^3": "m^3/m", "J": "J/m"}.get(unit, unit) for key, unit in units.items()}


def _column_unit(key: str, loads: set[str]) -> str:
    if key in _COLUMN_UNITS:
        return _COLUMN_UNITS[key]
    if key in loads or key.startswith("mean_stress"):
        return "Pa"
    if key.startswith("probe"):
        return "m"
    return "1"


def provenance(scene: Scene, comm: MPI.Comm) -> dict:
    """Where a result comes from: versions, the scene and its SHA-256, ranks, host and date."""
    import dolfinx

    if scene.source is not None and Path(scene.source).is_file():
        digest = hashlib.sha256(Path(scene.source).read_bytes()).hexdigest()
    else:
        digest = hashlib.sha256(json.dumps(scene.table, sort_keys=True, default=str).encode()).hexdigest()
    return {
        "lungmech": lungmech.__version__,
        "dolfinx": dolfinx.__version__,
        "python": platform.python_version(),
        "scene": str(Path(scene.source).resolve()) if scene.source else None,
        "scene_sha256": digest,
        "mpi_ranks": comm.size,
        "host": platform.node(),
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    }
