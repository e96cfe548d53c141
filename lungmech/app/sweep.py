"""Many parameter points at once: a reduced model's answers for a CSV file of points.

``lungmech rom solve model.npz --sweep points.csv -o OUT`` reads one parameter point per row:
a header of parameter names (a name may carry its unit in brackets, ``stiffness [Pa]``: it must
be the parameter's own, values are not converted), values in the parameters' units; a parameter without a column keeps the scene's value (``--set``
included). A bad file is refused in one line that names the file, the row and the column: an
unknown name, a value that is not a finite number, a point outside the trained box. Every point
is solved by the reduced model from its start (:meth:`ReducedModel.solve`: its outputs from
reduced operators, no full field), and the folder gets:

- ``sweep.csv``: one row per point and output time: the point, the time, the volume, the
  strain energy, the probes' displacements, the scalar loads, the formulation's averages (a
  lung's fractions and mean stresses) and the answer's error indicator, every column named with
  its unit;
- ``summary.json``: the model, the points, the solve time of each (s), the largest indicator;
- ``sweep.png``: the volume of every point against time.
"""

from __future__ import annotations

import csv
import math
import re
import time
from pathlib import Path
from typing import cast

from mpi4py import MPI

import numpy as np

from lungmech.app.output import write_json
from lungmech.app.plot import drawn, sweep_volumes
from lungmech.errors import ParameterError, SceneError
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import Solution
from lungmech.parallel import on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.rom.reduced import ReducedModel

__all__ = ["read_points", "sweep"]

_UNIT = re.compile(r"^(?P<name>.*?)\s*\[(?P<unit>[^\]]*)\]\s*$")  # "stiffness [Pa]"


def read_points(path: str | Path, parameters: Parameters, base: dict[str, float]) -> list[dict[str, float]]:
    """The parameter points of the CSV file at ``path``: every parameter's value, from its
    column or else from ``base``; each checked against its range. One clear error otherwise."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"sweep file not found: {path}" if not path.is_dir() else f"sweep file '{path}' is a folder")
    try:
        with open(path, newline="", encoding="utf-8-sig") as stream:
            reader = csv.reader(stream)  # (line number, cells) of the lines that hold something
            rows = [(reader.line_num, row) for row in reader if any(cell.strip() for cell in row)]
    except (UnicodeDecodeError, csv.Error) as error:
        raise SceneError(f"sweep file '{path}' is not a CSV text file ({error})") from None
    if len(rows) < 2:
        raise SceneError(f"sweep file '{path}' holds no points: give a header of parameter names and one row per point")
    names = []
    for cell in rows[0][1]:
        named = _UNIT.match(cell.strip())
        name = (named["name"] if named else cell).strip()
        if name not in parameters:
            known = ", ".join(parameters.names) or "none"
            raise SceneError(f"sweep file '{path}': column '{name}' is not a parameter of the model ({known})")
        unit = parameters.named(name).unit or "1"
        if named and named["unit"].strip() != unit:  # values are not converted: refuse, not misread
            raise SceneError(
                f"sweep file '{path}': column '{cell.strip()}': parameter '{name}' is given in [{unit}]; "
                f"write its values in {unit}"
            )
        names.append(name)
    if len(set(names)) < len(names):
        raise SceneError(f"sweep file '{path}': a parameter has two columns")
    points = []
    for number, row in rows[1:]:
        if len(row) != len(names):
            raise SceneError(f"sweep file '{path}', line {number}: {len(row)} values for {len(names)} columns")
        given = {}
        for name, cell in zip(names, row):
            try:
                given[name] = float(cell)
            except ValueError:
                given[name] = math.nan
            if not math.isfinite(given[name]):
                raise SceneError(
                    f"sweep file '{path}', line {number}, column '{name}': {cell!r} is not a finite number"
                )
        try:
            points.append(parameters.values(given, start=base))
        except ParameterError as error:
            raise SceneError(f"sweep file '{path}', line {number}: {error}") from None
    return points


def sweep(
    model: str | Path,
    points: str | Path,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    values: dict[str, float] | None = None,
    times: list[float] | None = None,
) -> dict:
    """Solve the reduced model in the file ``model`` at every point of the CSV file ``points``
    (parameters without a column at ``values``, else the scene's) and write the folder ``out``
    (see the module's doc; checked before any work, replaced only when the sweep succeeds).
    ``times`` (s): the answers at those times only (a static answer), else at the model's output
    times. Collective; returns the summary."""
    from lungmech.app.reduce import load

    command = f"lungmech rom solve {model} --sweep {points}"
    with output_folder(out, comm, inputs=[model, points], command=command) as staging:
        reduced = load(model, comm)
        base = reduced.parameters.values(values or {}, start=reduced.model.parameter_values)
        grid = read_points(points, reduced.parameters, base)
        answers, seconds = [], []
        for point in grid:
            tic = time.perf_counter()
            answers.append(reduced.solve(point, times=times))
            seconds.append(time.perf_counter() - tic)
        indicators = [a.indicator for a in answers]
        start = answers[0].start
        assert start is not None  # every solve reports its start (trajectory)
        summary = {
            "model": str(Path(model).resolve()),
            **reduced.describe(),
            "start": {"kind": start.kind, "description": start.description},
            "points": len(grid),
            "parameters": grid,
            "seconds_per_point": seconds,
            "median_seconds_per_point": float(np.median(seconds)),
            "error_indicator_largest": None if None in indicators else float(max(cast(list[float], indicators))),
            "units": {
                "parameters": "as declared in the scene's [parameters]",
                "seconds_per_point": "s",
                "median_seconds_per_point": "s",
                "error_indicator_largest": "1 (relative energy-norm error estimate)",
            },
        }
        hold_signals_until_swap()  # the outputs are collective writes
        write_json(staging / "summary.json", summary, comm)
        on_root(comm, lambda: _write_table(reduced, grid, answers, staging / "sweep.csv"))
        drawn(
            comm,
            staging / "sweep.png",
            lambda: on_root(
                comm,
                lambda: sweep_volumes(
                    answers[0].times,
                    [a.outputs["volume"] for a in answers],
                    [reduced.parameters.text(p) for p in grid],
                    staging / "sweep.png",
                    f"{len(grid)} points of {Path(model).name}",
                    planar=reduced.model.plane is not None,
                    against=_varying(reduced.parameters, grid),
                ),
            ),
        )
    return summary


def _varying(parameters: Parameters, points: list[dict[str, float]]) -> list[tuple[str, list[float]]]:
    """(axis label, values) of the parameters that vary over ``points``, most (in the unit box)
    first."""
    if not len(parameters):
        return []
    spread = np.ptp([parameters.to_unit(p) for p in points], axis=0)
    chosen = [parameters[int(i)] for i in np.argsort(-spread) if spread[i] > 0]
    return [(f"{p.name} [{p.unit or '1'}]", [point[p.name] for point in points]) for p in chosen]


def _write_table(reduced: ReducedModel, points: list[dict], answers: list[Solution], path: Path) -> None:
    """sweep.csv (rank 0): one row per point and output time, every column with its unit."""
    parameters = reduced.parameters
    header = ["point [1]"] + [f"{p.name} [{p.unit or '1'}]" for p in parameters] + ["time [s]"]
    first = answers[0].outputs
    outputs = [name for name in ("volume", "strain_energy") if name in first]
    header += [f"{name} [{answers[0].units[name]}]" for name in outputs]
    probes = first["probes"].shape[1] if "probes" in first else 0
    header += [f"probe{i}_u{c} [m]" for i in range(probes) for c in "xyz"]
    loads = [name for name in first if name.startswith("loads/")]
    header += [f"{name.removeprefix('loads/')} [Pa]" for name in loads]
    averages = [name for name in first if name.startswith("averages/")]
    header += [f"{name.removeprefix('averages/')} [{answers[0].units[name]}]" for name in averages]
    header += ["error_indicator [1]"]
    with open(path, "w", newline="") as stream:
        table = csv.writer(stream)
        table.writerow(header)
        for index, (point, answer) in enumerate(zip(points, answers)):
            for t, time_ in enumerate(answer.times):
                row = [index, *(point[p.name] for p in parameters), time_]
                row += [answer.outputs[name][t] for name in outputs]
                row += list(np.asarray(answer.outputs["probes"][t]).reshape(-1)) if probes else []
                row += [answer.outputs[name][t] for name in (*loads, *averages)]
                row += ["" if answer.indicator is None else answer.indicator]
                table.writerow(row)
