"""Many parameter points at once: a model's answers for a CSV file of points.

``lungmech rom solve model.npz --sweep points.csv -o OUT`` (a reduced model, :func:`sweep`) and
``lungmech run scene.toml --sweep points.csv -o OUT`` (the full model, :func:`sweep_full`) read
one parameter point per row:
a header of parameter names (a name may carry its unit in brackets, ``stiffness [Pa]``: it must
be the parameter's own, values are not converted), values in the parameters' units; a parameter without a column keeps the scene's value (``--set``
included). A bad file is refused in one line that names the file, the row and the column: an
unknown name, a value that is not a finite number, a point outside the trained box. Every point
is solved from its start: by the reduced model in this process (its outputs from reduced
operators, no full field), or as one full solve of an ensemble
(:mod:`lungmech.parallel.ensemble`: this process, groups of ranks or an engine's workers; each
answer kept in lungmech's cache, so an interrupted sweep resumes; a point whose solve failed
is a row that says why, and the others go on). The folder gets:

- ``sweep.csv``: one row per point and output time: the point, the time, the volume, the
  strain energy, the probes' displacements, the scalar loads, the formulation's averages (a
  lung's fractions and mean stresses) and the answer's error indicator, every column named with
  its unit;
- ``summary.json``: the model, the points, the solve time of each (s), the largest indicator,
  the points that failed;
- ``sweep.png``: the volume of every point against time.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from functools import partial
from pathlib import Path
from typing import cast

from mpi4py import MPI

import numpy as np

from lungmech.app.answers import answer
from lungmech.app.output import write_json
from lungmech.app.plot import drawn, sweep_volumes
from lungmech.errors import ParameterError, SceneError
from lungmech.fem.parameters import Parameters
from lungmech.parallel import on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.parallel.ensemble import Ensemble

__all__ = ["read_points", "sweep", "sweep_full"]

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
        found = [answer(reduced, point, times) for point in grid]
        described = {"model": str(Path(model).resolve()), **reduced.describe()}
        title = f"{len(grid)} points of {Path(model).name}"
        summary = _summary(found, grid, described)
        _written(staging, reduced.parameters, grid, found, summary, title, reduced.model.plane is not None, comm)
    return summary


def sweep_full(
    scene: str | Path,
    points: str | Path,
    out: str | Path,
    ensemble: Ensemble,
    cache: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    values: dict[str, float] | None = None,
    times: list[float] | None = None,
) -> dict:
    """Solve the scene in the file ``scene`` with its full model at every point of the CSV file
    ``points`` (parameters without a column at ``values``, else the scene's), one solve of
    ``ensemble`` a point, the answers kept in lungmech's cache folder ``cache``, and write the
    folder ``out`` (see the module's doc). ``times`` as :func:`sweep`'s. Collective over the
    ensemble's ranks; returns the summary."""
    from lungmech.app import answers as full
    from lungmech.app import scene as scenes
    from lungmech.app.ladder import Discretisation

    path = Path(scene).resolve()
    read = scenes.load(path)
    parameters = Parameters(read.parameters)
    command = f"lungmech run {scene} --sweep {points}"
    with output_folder(out, comm, inputs=[path, points, *read.inputs], command=command) as staging:
        grid = read_points(points, parameters, parameters.values(values or {}))
        steps = None if times is None else tuple(times)
        tasks = [full.Task(str(path), point, Discretisation.of(read), steps) for point in grid]
        say = logging.getLogger("lungmech").info
        outcomes = ensemble.map(partial(full.solved, cache=str(cache)), tasks, lambda line: say("sweep: %s", line))
        full.forget()
        found = [o.value if o.value is not None else {"failed": o.failed, "seconds": None} for o in outcomes]
        described = {"scene": str(path), "title": read.title, "full solves on": ensemble.description}
        title = f"{len(grid)} points of {path.name} (full model)"
        summary = _summary(found, grid, described)
        _written(staging, parameters, grid, found, summary, title, read.plane is not None, comm)
    return summary


def _summary(found: list[dict], grid: list[dict[str, float]], described: dict) -> dict:
    """summary.json's content (see the module's doc)."""
    solved = [a for a in found if a["failed"] is None]
    indicators = [a["indicator"] for a in solved]
    seconds = [a["seconds"] for a in solved]
    start = solved[0]["start"] if solved else None
    return described | {
        "start": start,
        "points": len(grid),
        "parameters": grid,
        "seconds_per_point": [a["seconds"] for a in found],
        "median_seconds_per_point": float(np.median(seconds)) if seconds else None,
        "error_indicator_largest": None
        if not indicators or None in indicators
        else float(max(cast(list[float], indicators))),
        "failed": [{"point": index, "why": a["failed"]} for index, a in enumerate(found) if a["failed"] is not None],
        "units": {
            "parameters": "as declared in the scene's [parameters]",
            "seconds_per_point": "s",
            "median_seconds_per_point": "s",
            "error_indicator_largest": "1 (relative energy-norm error estimate)",
        },
    }


def _written(
    staging: Path,
    parameters: Parameters,
    grid: list[dict[str, float]],
    found: list[dict],
    summary: dict,
    title: str,
    planar: bool,
    comm: MPI.Comm,
) -> None:
    """``summary`` (summary.json), sweep.csv and sweep.png into ``staging`` (collective)."""
    if all(a["failed"] is not None for a in found):
        raise ParameterError(f"the sweep's every solve failed; the first: {found[0]['failed']}")
    hold_signals_until_swap()  # the outputs are collective writes
    write_json(staging / "summary.json", summary, comm)
    on_root(comm, lambda: _write_table(parameters, grid, found, staging / "sweep.csv"))
    solved = [(point, a) for point, a in zip(grid, found) if a["failed"] is None]
    drawn(
        comm,
        staging / "sweep.png",
        lambda: on_root(
            comm,
            lambda: sweep_volumes(
                solved[0][1]["times"],
                [a["volume"] for _, a in solved],
                [parameters.text(point) for point, _ in solved],
                staging / "sweep.png",
                title,
                planar=planar,
                against=_varying(parameters, [point for point, _ in solved]),
            ),
        ),
    )


def _varying(parameters: Parameters, points: list[dict[str, float]]) -> list[tuple[str, list[float]]]:
    """(axis label, values) of the parameters that vary over ``points``, most (in the unit box)
    first."""
    if not len(parameters):
        return []
    spread = np.ptp([parameters.to_unit(p) for p in points], axis=0)
    chosen = [parameters[int(i)] for i in np.argsort(-spread) if spread[i] > 0]
    return [(f"{p.name} [{p.unit or '1'}]", [point[p.name] for point in points]) for p in chosen]


def _write_table(parameters: Parameters, points: list[dict], found: list[dict], path: Path) -> None:
    """sweep.csv (rank 0): one row per point and output time, every column with its unit; a
    point whose solve failed is one row saying why (a ``failed`` column, where any did)."""
    first = next(a for a in found if a["failed"] is None)
    header = ["point [1]"] + [f"{p.name} [{p.unit or '1'}]" for p in parameters] + ["time [s]"]
    outputs = [name for name in ("volume", "strain_energy") if name in first["units"]]
    header += [f"{name} [{first['units'][name]}]" for name in outputs]
    probes = len(first["probes"][0]) if first["probes"] else 0
    header += [f"probe{i}_u{c} [m]" for i in range(probes) for c in "xyz"]
    others = list(first["outputs"])
    header += [f"{name.split('/', 1)[1]} [{first['units'][name]}]" for name in others]
    header += ["error_indicator [1]"]
    failures = any(a["failed"] is not None for a in found)
    header += ["failed"] if failures else []
    width = len(header) - len(parameters) - 2 - failures
    with open(path, "w", newline="") as stream:
        table = csv.writer(stream)
        table.writerow(header)
        for index, (point, found_here) in enumerate(zip(points, found)):
            given = [index, *(point[p.name] for p in parameters)]
            if found_here["failed"] is not None:
                table.writerow([*given, "", *([""] * width), found_here["failed"]])
                continue
            for t, time_ in enumerate(found_here["times"]):
                row = [*given, time_, *(found_here[name][t] for name in outputs)]
                row += list(np.asarray(found_here["probes"][t]).reshape(-1)) if probes else []
                row += [found_here["outputs"][name][t] for name in others]
                row += ["" if found_here["indicator"] is None else found_here["indicator"]]
                table.writerow(row + ([""] if failures else []))
