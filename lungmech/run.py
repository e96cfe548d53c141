"""Run a scene: build what it declares, solve with load stepping, write the outputs atomically."""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from mpi4py import MPI

from lungmech import lung
from lungmech.errors import ParameterError
from lungmech.geometry import write as write_geometry
from lungmech.inverse import unloaded_reference
from lungmech.model import Model
from lungmech.output import FieldWriter, atomic_folder, write_json
from lungmech.plot import deformed_body, pressure_volume
from lungmech.quantities import Probe, deformed_volume, strain_energy
from lungmech.scene import Scene, build_geometry
from lungmech.solver import NewtonSolver, StepReport, solve


Scale = float | Sequence[float]


def build_model(scene: Scene, comm: MPI.Comm = MPI.COMM_WORLD) -> Model:
    """The model a scene declares, and nothing else."""
    geometry = build_geometry(scene.geometry, comm)
    return Model(
        geometry,
        scene.material,
        degree=scene.degree,
        formulation=scene.formulation,
        loads=scene.loads,
        constraints=scene.constraints,
    )


def load_values(scene: Scene, t: float, scale: Scale = 1.0) -> list[tuple[str, float]]:
    """The current values of the scene's scalar (pressure) loads, named by type and boundary;
    ``scale`` multiplies their change since the start, as in :meth:`Model.set_time`."""
    values = []
    factors = np.broadcast_to(np.asarray(scale, dtype=float), (len(scene.loads),))
    for i, (load, factor) in enumerate(zip(scene.loads, factors)):
        if np.ndim(load.value) == 0:
            where = getattr(load, "boundary", "")
            where = where if isinstance(where, str) else "+".join(where)
            base = load.ramp(scene.stepping.start)
            value = (base + factor * (load.ramp(t) - base)) * load.value
            values.append((f"{type(load).__name__}{'_' + where if where else ''}_{i}", value))
    return values


def check_scale(scene: Scene, scale: Scale) -> Scale:
    """``scale`` as given, if it is one positive factor or one per load of the scene."""
    factors = np.atleast_1d(np.asarray(scale, dtype=float))
    if factors.ndim != 1 or len(factors) not in (1, len(scene.loads)) or not np.all(np.isfinite(factors)):
        raise ParameterError(
            f"load scale: give one factor or one per load ({len(scene.loads)} in this scene), got {scale!r}"
        )
    return scale


def full_order(model: Model, scene: Scene, folder: Path) -> tuple[NewtonSolver, dict | None]:
    """The full-order solver, after unloading the imaged mesh when the scene asks for it."""
    solver = NewtonSolver(model, scene.newton)
    return solver, _unload(model, scene, solver, folder) if scene.inverse is not None else None


def _unload(model: Model, scene: Scene, solver: NewtonSolver, folder: Path) -> dict:
    """Replace the (imaged) mesh by its unloaded reference; write it; report how it went."""
    imaged_volume = model.geometry.volume()
    report = unloaded_reference(model, scene.stepping.start, scene.inverse, solver=solver)
    write_geometry(model.geometry, folder / "reference.xdmf")
    return {
        "iterations": report.iterations,
        "mismatch": report.mismatch,
        "newton_iterations": report.newton_iterations,
        "seconds": report.seconds,
        "imaged_volume": imaged_volume,
        "reference_volume": model.geometry.volume(),
    }


def run(
    scene: Scene,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    *,
    scale: Scale = 1.0,
    prepare: Callable[[Model, Scene, Path], tuple[NewtonSolver, dict | None]] = full_order,
) -> dict:
    """Solve ``scene`` and write summary.json, history.csv, (optionally) VTX fields,
    deformed.png (the body at its largest volume, coloured by J) and, when the scene has
    pressure loads, pressure_volume.png (volume against the first of them) to ``out``.
    A scene with [inverse] first moves its (imaged) mesh to the unloaded reference and writes
    it to reference.xdmf; stepping then starts from the imaged state.

    ``scale`` multiplies the loads' change from the start (one factor, or one per load): a
    deeper breath from the same end-expiration. ``prepare(model, scene, folder)`` returns the
    solver (default :func:`full_order`; a reduced model's is in :mod:`lungmech.rom.scene`) and
    what it did to the reference (the inverse problem's report, or None).

    ``out`` is replaced only when the run succeeds. Returns the summary.
    """
    check_scale(scene, scale)
    timings = {}
    tic = time.perf_counter()
    model = build_model(scene, comm)
    timings["build"] = time.perf_counter() - tic

    with atomic_folder(Path(out), comm) as staging:
        tic = time.perf_counter()
        solver, inverse = prepare(model, scene, staging)
        timings["prepare"] = time.perf_counter() - tic
        tic = time.perf_counter()
        volume, energy = deformed_volume(model), strain_energy(model)
        fractions = lung.averages(model) if "phi_s" in model.fields else {}
        probe = Probe(model.geometry.mesh, scene.output.probes) if scene.output.probes else None
        writer = FieldWriter(model, staging) if scene.output.fields else None
        timings["compile"] = time.perf_counter() - tic

        history = []
        largest = {"volume": -np.inf, "state": None, "time": 0.0}  # pictured at the end

        def record(step: StepReport | None) -> None:
            row = {"time": model.time, "volume": volume(), "energy": energy()}
            row |= {name: value for name, value in load_values(scene, model.time, scale)}
            row |= {name: mean() for name, mean in fractions.items()}
            if step is not None:
                row |= {"newton_iterations": step.iterations, "step_seconds": step.seconds}
            if probe is not None:
                for i, value in enumerate(probe(model.displacement())):
                    row |= {f"probe{i}_u{axis}": value[c] for c, axis in enumerate("xyz")}
            history.append(row)
            if row["volume"] > largest["volume"]:
                largest.update(volume=row["volume"], state=model.state.x.array.copy(), time=model.time)
            if writer is not None:
                writer.write(model.time)

        try:
            record(None)
            stepping = replace(scene.stepping, times=(*scene.stepping.times, *model.breakpoints))
            report = solve(
                model, stepping, solver=solver, on_step=record,
                drive=lambda t: model.set_time(t, load_factor=scale, about=scene.stepping.start),
            )
        finally:  # ADIOS2 must let go of its files before a failed staging folder is removed
            if writer is not None:
                writer.close()
        timings["solve"] = report.seconds

        mesh = model.geometry.mesh
        summary = {
            "title": scene.title,
            "mpi_ranks": comm.size,
            "dofs": model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs,
            "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
            "law": scene.material.name,
            "degree": scene.degree,
            "formulation": type(scene.formulation).__name__,
            "steps": len(report.accepted),
            "failed_steps": report.failures,
            "newton_iterations": report.newton_iterations,
            "timings_seconds": timings,
            "reference_volume": model.geometry.volume(),
            "deformed_volume": history[-1]["volume"],
            "largest_volume": {"volume": largest["volume"], "time": largest["time"]},
            "strain_energy": history[-1]["energy"],
            "inverse": inverse,
            "load_scale": np.asarray(scale, dtype=float).tolist(),
            "solver": getattr(solver, "description", "full order"),
            "probes": {
                "points": [list(p) for p in scene.output.probes],
                "displacement": probe(model.displacement()).tolist() if probe is not None else [],
            },
        }
        write_json(staging / "summary.json", summary, comm)
        final = model.state.x.array.copy()
        model.state.x.array[:] = largest["state"]
        deformed_body(model, staging / "deformed.png", f"{scene.title}\nlargest volume, t = {largest['time']:.3g}")
        model.state.x.array[:] = final
        pressures = [name for name, _ in load_values(scene, 0.0)]
        if pressures and comm.rank == 0:
            pressure_volume(
                [row[pressures[0]] for row in history], [row["volume"] for row in history],
                staging / "pressure_volume.png", pressures[0],
            )
        if comm.rank == 0:
            with open(staging / "history.csv", "w", newline="") as stream:
                columns = list(dict.fromkeys(k for row in history for k in row))
                writer_csv = csv.DictWriter(stream, fieldnames=columns)
                writer_csv.writeheader()
                writer_csv.writerows(history)
    return summary
