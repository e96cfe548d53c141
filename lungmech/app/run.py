"""Run a scene: build what it declares, solve with load stepping, write the outputs safely.

A run writes into a staging folder that replaces its output folder only when everything has
succeeded (see :mod:`lungmech.parallel.destination`). Files, with SI units throughout:

* ``summary.json``: the run's numbers — what the start was (``start``), the answer at the
  output times (``outputs``) —, a ``units`` table naming the unit of each, and its
  ``provenance`` (lungmech version, the scene file and its SHA-256, MPI ranks, date);
* ``history.csv``: one row per accepted state (the start, then every load step), columns
  ``name [unit]``: the model's outputs (volume, strain energy, the loads as applied, the
  formulation's averages, probes) and the step's work;
* ``fields.pvd`` with ``.vtu`` files (or ADIOS2 ``.bp`` folders): fields at every step;
* ``deformed.png``: the body at its largest volume, coloured by J;
* ``pressure_volume.png`` when the scene has pressure loads: volume against the transpulmonary
  pressure of a lung (or against the first pressure load of another body);
* ``reference.vtu`` for a scene with [inverse]: the unloaded reference it found (a mesh file
  meshio, pyvista and ParaView open, and a [geometry] file for the next scene).

The run talks to the model only through ``solve(mu, on_step=...)`` and ``fields(state, t)``
(:class:`~lungmech.fem.parametric.ParametricModel`): full-order, reduced and hyper-reduced runs
write the same files the same way.
"""

from __future__ import annotations

import csv
import datetime
import hashlib
import json
import logging
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, cast

from mpi4py import MPI

import numpy as np

import lungmech
from lungmech import lung
from lungmech.app.console import Progress, volume_text
from lungmech.app.console import pressure as show_pressure
from lungmech.app.output import FieldWriter, write_json, write_reference
from lungmech.app.plot import deformed_body, drawn, pressure_volume
from lungmech.app.scene import Scene
from lungmech.app.template import body_modes, build_template
from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.model import Model
from lungmech.fem.parametric import FullOrderModel, ParametricModel, Solution, Step
from lungmech.fem.placement import Image
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.start import Equilibrium, Start, StartReport
from lungmech.mesh.geometry import Geometry
from lungmech.parallel import deferred, on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder

log = logging.getLogger("lungmech")

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
    "start.volume": "m^3",
    "start.imaged_volume": "m^3",
    "start.from_image": "m^3 (the start's volume minus the image's)",
    "start.reference_volume": "m^3",
    "start.seconds": "s",
    "start.newton_iterations": "1",
    "outputs": "time s, volume m^3, strain_energy J, probes m, loads/<label> Pa, averages/<name> as in history.csv",
    "error_indicator": "1 (a reduced model's estimate of its relative energy-norm error)",
    "full_fields": "1 (whether fields and the pictures were written)",
}
_COLUMN_UNITS = {
    "time": "s",
    "volume": "m^3",
    "strain_energy": "J",
    "newton_iterations": "1",
    "step_seconds": "s",
    "error_indicator": "1",
}


def build_model(
    scene: Scene, comm: MPI.Comm = MPI.COMM_WORLD, geometry: Geometry | None = None, image: Image | None = None
) -> Model:
    """The model a scene declares, and nothing else, at the scene's parameter values; on
    ``geometry`` when given (a hyper-reduced model's body: :func:`lungmech.rom.store.load_body`
    places its values, shape modes too), else on the scene's (:mod:`lungmech.app.template`);
    ``image``: its mesh placed as an image says (:mod:`lungmech.fem.placement`)."""
    geometry, shape = build_template(scene, comm) if geometry is None else (geometry, body_modes(scene, geometry))
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
        image=image,
        shape=shape,
    )
    model.set_parameters(scene.values)
    return model


def body_name(model: Model) -> str:
    """ "lung" for a body whose P–V pressure is a lung's (see :mod:`lungmech.lung.pressure`), else "body"."""
    axis = lung.pressure_axis(model.loads, model.formulation)
    return "lung" if axis is not None and axis.lung else "body"


STARTS = ("imaged", "inverse_motion", "defaults")  # how full_order_model starts a scene with [inverse]
IMAGED_AT_DEFAULTS = (
    "the imaged {body} unloaded at the default parameters, then moved to these parameters (not the image at them)"
)


def full_order_model(
    scene: Scene,
    comm: MPI.Comm = MPI.COMM_WORLD,
    *,
    start: str = "imaged",
    model: Model | None = None,
    probes: Sequence[Sequence[float]] | None = None,
) -> FullOrderModel:
    """The scene's full-order model (``solve(mu)``). A scene with [inverse] solves the problem of
    an imaged body: its mesh is the loaded state at the start for every μ, and each solve finds
    the unloaded reference at its μ; probe points are then points of the image. ``start``
    chooses how: "imaged" (:class:`lungmech.lung.inverse.Imaged`, the mesh moved to the
    reference by a fixed point), "inverse_motion" (:class:`~lungmech.fem.inverse_motion.
    InverseMotion`, the mesh kept as the image: what reduced models are trained from), or
    "defaults", a model of another problem: the reference found once, at the default
    parameters, and its loaded state moved to each μ (:class:`~lungmech.fem.start.Equilibrium`).
    ``model``: the scene's :func:`build_model`, if built already (on its mesh as built; for
    "inverse_motion", of the image's motion). ``probes``: points of the mesh (of the image)
    whose displacement is an output (default: the scene's). Collective."""
    if start not in STARTS:
        raise ParameterError(f"start must be one of {', '.join(STARTS)} (got {start!r})")
    if scene.inverse is not None and start == "inverse_motion":
        model = build_model(scene, comm, image=Image.motion(scene.stepping.start)) if model is None else model
        inverse = InverseMotion(model, scene.newton, body=body_name(model))
        return FullOrderModel(model, scene.stepping, scene.newton, _probe(model, scene, probes), inverse)
    model = build_model(scene, comm) if model is None else model
    located = _probe(model, scene, probes)  # in the image
    first: Start | None = None
    if scene.inverse is not None:
        imaged = lung.Imaged(model, scene.inverse, body_name(model))
        first = imaged
        if start == "defaults":
            solver = NewtonSolver(model, scene.newton)
            placed = imaged.place(model, solver, model.parameters.defaults, scene.stepping.start)
            details = {"imaged_volume": imaged.volume, "reference_volume": placed.details["reference_volume"]}
            first = Equilibrium(model.state.x.array.copy(), IMAGED_AT_DEFAULTS.format(body=imaged.body), details)
            return FullOrderModel(model, scene.stepping, scene.newton, located, first, solver)
    return FullOrderModel(model, scene.stepping, scene.newton, located, first)


def _probe(model: Model, scene: Scene, points: Sequence[Sequence[float]] | None) -> Probe | tuple:
    """The probe of ``points`` (default: the scene's), located on the model's mesh as it is."""
    chosen = scene.output.probes if points is None else points
    return Probe(model.geometry.mesh, chosen) if len(chosen) else ()


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


def start_text(start: StartReport, planar: bool) -> str:
    """One line on what a solve started from: the start's description, its volume, and where the
    start is an imaged body's, the image's volume and how far the start lies from it."""
    details = start.details
    text = f"start: {start.description}"
    if "volume" in details:
        text += f"; volume {volume_text(details['volume'], planar)}"
    if "from_image" in details:
        apart, imaged = details["from_image"], details["imaged_volume"]
        if abs(apart) <= 1e-6 * abs(imaged):
            text += ", the image's"
        else:
            sign = "+" if apart >= 0 else "−"
            text += f" (the image {volume_text(imaged, planar)}; {sign}{volume_text(abs(apart), planar)} from it)"
    return text


def run(
    scene: Scene,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    *,
    scale: Scale = 1.0,
    model: Callable[[Scene, MPI.Comm], ParametricModel] = full_order_model,
    inputs: Sequence[str | Path] = (),
    times: Sequence[float] | None = None,
    full_fields: bool = True,
) -> dict:
    """Solve ``scene`` and write its results into the folder ``out`` (see the module's doc).

    ``model(scene, comm)`` gives the parametric model that answers it (default: the scene's
    :func:`full_order_model`; a reduced one is :func:`lungmech.app.reduce.reduced_order`), solved
    once at the scene's parameter values (``--set`` included) with ``solve(mu, on_step=...)``:
    the history holds every accepted state, the summary the answer at the output times — or at
    ``times`` (s): a static answer, the equilibrium at T. ``scale`` multiplies the loads' change
    from the start (one factor, or one per load): a deeper breath from the same end-expiration.
    ``inputs`` are further files the run reads (beyond the scene's own), which ``out`` must not
    hold. Without ``full_fields`` the run writes the model's numbers only (summary.json,
    history.csv): no fields (whatever the scene's [output] says), no deformed.png (they need
    the full field of a state) and no pressure_volume.png.

    ``out`` is checked before any work (see :func:`lungmech.parallel.destination.output_folder`) and
    replaced only when the run succeeds. Collective. Returns the summary.
    """
    check_scale(scene, scale)
    timings = {}
    command = f"lungmech run {scene.source}" if scene.source else "lungmech.app.run.run"
    with output_folder(out, comm, inputs=[*scene.inputs, *inputs], command=command) as staging:
        tic = time.perf_counter()
        parametric = model(scene, comm)
        fem_model = parametric.model
        timings["build"] = time.perf_counter() - tic
        planar = fem_model.plane is not None
        axis = lung.pressure_axis(fem_model.loads, fem_model.formulation)
        fields = (staging, scene.output.format) if scene.output.fields and full_fields else None
        recorder = _Recorder(parametric, axis, fields, comm)
        tic = time.perf_counter()
        try:
            solution = parametric.solve(
                scene.values, scale=scale, times=times, on_step=recorder, progress=recorder.start_progress
            )
        finally:  # ADIOS2 must let go of its files before a failed staging folder is removed
            recorder.close_fields()
        timings["solve"] = time.perf_counter() - tic
        recorder.close()

        # Outputs are collective writes: a signal now waits, and stops every rank together.
        hold_signals_until_swap()
        history, start = recorder.history, solution.start
        assert start is not None  # every solve reports its start (trajectory)
        if start.kind == "imaged" and full_fields:  # (a body of sampled cells holds a few cells of it)
            write_reference(fem_model, staging / "reference.vtu")
        mesh = fem_model.geometry.mesh
        summary = {
            "title": scene.title,
            "parameters": solution.parameters,
            "provenance": provenance(scene, comm),
            "mpi_ranks": comm.size,
            "dofs": fem_model.space.dofmap.index_map.size_global * fem_model.space.dofmap.index_map_bs,
            "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
            "law": scene.material.name,
            "degree": scene.degree,
            "formulation": type(scene.formulation).__name__,
            "steps": recorder.steps,
            "cut_steps": recorder.cuts,
            "newton_iterations": recorder.newton_iterations,
            "timings_seconds": timings,
            "start": {"kind": start.kind, "description": start.description, **start.details},
            "start_volume": history[0]["volume"],
            # the start's where it found one (on a fixed imaged mesh the mesh is the image)
            "reference_volume": start.details.get("reference_volume", fem_model.geometry.volume()),
            "deformed_volume": history[-1]["volume"],
            "largest_volume": {"volume": recorder.largest["volume"], "time": recorder.largest["time"]},
            "strain_energy": history[-1]["strain_energy"],
            "inverse": start.details if start.kind == "imaged" else None,
            "load_scale": np.asarray(scale, dtype=float).tolist(),
            "outputs": answer(solution),
            "error_indicator": solution.indicator,
            "full_fields": full_fields,
            "probes": {
                "points": [list(p) for p in scene.output.probes],
                "displacement": recorder.probes.tolist() if recorder.probes is not None else [],
            },
            "plane": fem_model.plane,
            "units": per_thickness(SUMMARY_UNITS) if planar else SUMMARY_UNITS,
        } | parametric.describe()
        write_json(staging / "summary.json", summary, comm)
        on_root(comm, lambda: _write_history(scene, history, solution.units, staging))
        if full_fields:  # the body at its largest volume: a full field
            with fem_model.kept_state():
                largest = recorder.largest
                parametric.fields(largest["state"], largest["time"])
                shown = volume_text(largest["volume"], planar)
                title = f"{scene.title}\nlargest volume {shown}, t = {largest['time']:.3g} s"
                drawn(comm, staging / "deformed.png", lambda: deformed_body(fem_model, staging / "deformed.png", title))
        if axis is not None and full_fields:  # (matplotlib's start-up alone is half a real-time solve)
            pressures, volumes = recorder.pressures, [row["volume"] for row in history]
            drawn(
                comm,
                staging / "pressure_volume.png",
                lambda: on_root(
                    comm,
                    lambda: pressure_volume(
                        pressures,
                        volumes,
                        staging / "pressure_volume.png",
                        axis.label,
                        title=scene.title,
                        note=list(axis.parts),
                        planar=planar,
                    ),
                ),
            )
    return summary


def answer(solution: Solution) -> dict[str, list]:
    """A solution's outputs at its output times as plain lists by name (the summary's
    ``outputs``; ``loads/<label>`` in Pa, ``averages/<name>`` in their units)."""
    return {"time": solution.times.tolist()} | {name: np.asarray(v).tolist() for name, v in solution.outputs.items()}


class _Recorder:
    """What a run keeps of every state a solve shows (:class:`~lungmech.fem.parametric.Step`):
    the history rows and the pressures of the P–V curve, the progress on the console, the fields
    written (``fields``: the folder and format, or None), the largest volume."""

    def __init__(
        self, model: ParametricModel, axis: lung.PressureAxis | None, fields: tuple[Path, str] | None, comm: MPI.Comm
    ) -> None:
        self.model, self.axis, self.fields, self.comm = model, axis, fields, comm
        self.planar = model.model.plane is not None
        self.body = "lung" if axis is not None and axis.lung else "body"
        self.history: list[dict] = []
        self.pressures: list[float] = []
        self.probes: np.ndarray | None = None  # at the last state, (points, 3)
        self.largest: dict[str, Any] = {"volume": -np.inf, "state": None, "time": 0.0}
        self.steps = self.cuts = self.newton_iterations = 0
        self.progress: Progress | None = None
        self.writer: FieldWriter | None = None

    def start_progress(self, fraction: float, text: str) -> None:
        """The start's own long work (an inverse problem's iterations)."""
        if self.progress is None:
            self.progress = Progress(
                f"unloading the imaged {self.body}" if self.body == "lung" else "finding the unloaded reference"
            )
        self.progress.update(fraction, text)

    def __call__(self, step: Step) -> None:
        if step.phase == "approach":
            return
        if step.phase == "cut":
            assert self.progress is not None and step.report is not None  # a load step's, after the start
            self.cuts += 1
            self.progress.note(
                f"t = {step.time:.4g} s: Newton did not converge ({step.report.reason}); step cut back to "
                f"dt = {step.report.step / 2:.3g} s (normal adaptivity)"
            )
            return
        if step.phase == "start":
            assert step.start is not None  # the start's step says what it is
            said = start_text(step.start, self.planar)
            if self.progress is not None:
                self.progress.close(said)
            elif self.comm.rank == 0 and log.isEnabledFor(logging.INFO):
                print(f"lungmech: {said}", flush=True)
            self.progress = Progress("breathing" if self.body == "lung" else "loading")
        else:
            assert self.progress is not None and step.report is not None  # a load step's, after the start
            self.steps += 1
            self.newton_iterations += step.report.iterations
        outputs = step.outputs()
        row = self._row(step, outputs)
        self.history.append(row)
        if row["volume"] > self.largest["volume"]:
            self.largest.update(volume=row["volume"], state=step.state(), time=step.time)
        if self.fields is not None:
            self._write(step)
        stepping = self.model.stepping
        shown = ""
        if self.axis is not None:
            self.pressures.append(self.axis(cast(dict[str, float], outputs["loads"])))  # Model.scalar_loads()
            shown = f"  {'P_L' if self.axis.lung else 'p'} {show_pressure(self.pressures[-1])}"
        newton = f"  {step.report.iterations} Newton" if step.report is not None else ""
        self.progress.update(
            (step.time - stepping.start) / (stepping.end - stepping.start),
            f"step {len(self.history) - 1}  t = {step.time:.3g}/{stepping.end:g} s{shown}  "
            f"volume {volume_text(row['volume'], self.planar)}{newton}",
        )

    def _row(self, step: Step, outputs: dict) -> dict:
        """One history row: the model's outputs at this state, flat, and the step's work."""
        row: dict = {"time": step.time, "volume": outputs["volume"], "strain_energy": outputs["strain_energy"]}
        row |= outputs["loads"]
        row |= outputs.get("averages", {})
        if step.report is not None:
            row |= {"newton_iterations": step.report.iterations, "step_seconds": step.report.seconds}
        if (indicator := step.indicator()) is not None:
            row["error_indicator"] = indicator
        if "probes" in outputs:
            self.probes = np.asarray(outputs["probes"])
            for i, value in enumerate(self.probes):
                row |= {f"probe{i}_u{letter}": component for letter, component in zip("xyz", value)}
        return row

    def _write(self, step: Step) -> None:
        """This state's fields, on the mesh as it is now (after the start: the reference)."""
        self.model.fields(step.state(), step.time)
        if self.writer is None:
            assert self.fields is not None  # written only when fields were asked for
            self.writer = FieldWriter(self.model.model, *self.fields)
        with deferred(self.comm):  # a collective write: not cut on one rank only
            self.writer.write(step.time)

    def close_fields(self) -> None:
        if self.writer is not None:
            self.writer.close()

    def close(self) -> None:
        assert self.progress is not None  # made at the start, which every solve shows
        self.progress.close(f"{self.steps} steps ({self.cuts} cut back), {self.newton_iterations} Newton iterations")


def _write_history(scene: Scene, history: list[dict], units: dict[str, str], folder: Path) -> None:
    """history.csv, its columns named with their units (rank 0): ``units`` are the solution's
    (``loads``, ``averages/<name>``)."""
    labels = {load.label for load in scene.loads}
    columns = list(dict.fromkeys(k for row in history for k in row))
    named = {k: _column_unit(k, labels, units) for k in columns}
    if scene.plane:
        named = per_thickness(named)
    header = [f"{k} [{named[k]}]" for k in columns]
    with open(folder / "history.csv", "w", newline="") as stream:
        table = csv.writer(stream)
        table.writerow(header)
        table.writerows([[row.get(k, "") for k in columns] for row in history])


def per_thickness(units: dict[str, str]) -> dict[str, str]:
    """The units of a 2-D body's results: volumes and energies are per metre of thickness."""
    return {key: {"m^3": "m^3/m", "J": "J/m"}.get(unit, unit) for key, unit in units.items()}


def _column_unit(key: str, loads: set[str], units: dict[str, str]) -> str:
    if key in _COLUMN_UNITS:
        return _COLUMN_UNITS[key]
    if key in loads:
        return units["loads"]
    if f"averages/{key}" in units:
        return units[f"averages/{key}"]
    if key.startswith("probe"):
        return units["probes"]
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
