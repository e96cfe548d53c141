"""A cohort: many patients personalised, one task of an ensemble each.

The cohort is a CSV file, one row per pair of segmentations, its header naming the columns
``patient``, ``expiration``, ``inspiration`` and, optionally, ``position`` (supine by default).
A patient's rows are its pairs (supine and prone together, say). Image paths are read relative
to the CSV file's folder. Each patient is one task of :mod:`lungmech.parallel.ensemble`
(:func:`personalised`): :func:`lungmech.app.personalise.personalise` on the task's
communicator, into ``OUT/<patient>/`` (with a population's model file,
:func:`lungmech.app.population.personalise`: no model of the patient's own, its shape
coefficients in its row); ``OUT/cohort.csv`` then holds a row per patient (each
estimate with its interval and unit, the fit, the times, or why it failed, in one line), and
``OUT/cohort.json`` the same with the ensemble's description. A patient that fails never stops
the others.

The patient column is the user's own label (never read from an image header): it names the
patient's folder, so it must be a plain name (letters, digits, ``-``, ``_``, ``.``).
"""

from __future__ import annotations

import contextlib
import csv
import logging
import re
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

from lungmech.app import population
from lungmech.app import scene as scenes
from lungmech.app.output import write_json
from lungmech.app.patient_images import Reading
from lungmech.app.personalise import POSITIONS, Setting, personalise
from lungmech.app.recipe import recipe_scene
from lungmech.errors import SceneError
from lungmech.parallel import on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.parallel.ensemble import Ensemble

__all__ = ["Row", "Task", "cohort", "personalised", "read_cohort"]

COLUMNS = ("patient", "expiration", "inspiration", "position")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class Row:
    """One pair of a patient's segmentations (paths as absolute as the CSV's folder makes them)."""

    patient: str
    expiration: str
    inspiration: str
    position: str = "supine"


@dataclass(frozen=True)
class Task:
    """A patient's personalisation, as data an ensemble's worker can receive: the scene file,
    the patient's pairs, the setting, how to read its images, and its output folder."""

    scene: str | None
    patient: str
    pairs: tuple[Row, ...]
    setting: Setting
    out: str
    reading: Reading = Reading()
    model: str | None = None


def read_cohort(path: str | Path) -> dict[str, list[Row]]:
    """The cohort in the CSV file at ``path``: each patient's pairs, in the file's order; one
    clear line on a missing file or column, an unknown position, a patient name that cannot be
    a folder's, or an image that is not there."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"cohort file not found: {path}" if not path.is_dir() else f"cohort file '{path}' is a folder")
    try:
        with open(path, newline="", encoding="utf-8-sig") as stream:
            reader = csv.DictReader(stream)
            rows = [(reader.line_num, row) for row in reader if any((cell or "").strip() for cell in row.values())]
            header = [name.strip() for name in reader.fieldnames or []]
    except (UnicodeDecodeError, csv.Error) as error:
        raise SceneError(f"cohort file '{path}' is not a CSV text file ({error})") from None
    if missing := [name for name in COLUMNS[:3] if name not in header]:
        raise SceneError(
            f"cohort file '{path}' has no column {', '.join(repr(m) for m in missing)}: its header must name "
            "patient, expiration, inspiration (and, optionally, position)"
        )
    if unknown := [name for name in header if name not in COLUMNS]:
        raise SceneError(f"cohort file '{path}': unknown column '{unknown[0]}' (known: {', '.join(COLUMNS)})")
    if not rows:
        raise SceneError(f"cohort file '{path}' holds no patient: give one row per pair of segmentations")
    cohort: dict[str, list[Row]] = {}
    for line, row in rows:
        cells = {name.strip(): (value or "").strip() for name, value in row.items() if name is not None}
        where = f"cohort file '{path}', line {line}"
        patient = cells["patient"]
        if not _NAME.match(patient) or patient in (".", ".."):
            raise SceneError(
                f"{where}: patient '{patient}' must be a plain name (letters, digits, - _ .): it names a folder"
            )
        position = cells.get("position") or "supine"
        if position not in POSITIONS:
            raise SceneError(f"{where}: position must be one of {', '.join(POSITIONS)} (got {position!r})")
        images = []
        for column in ("expiration", "inspiration"):
            if not cells[column]:
                raise SceneError(f"{where}: no {column} image")
            image = (path.parent / cells[column]).resolve()
            if not image.exists():
                raise SceneError(f"{where}: {column} image '{cells[column]}' not found (read from {path.parent})")
            images.append(str(image))
        cohort.setdefault(patient, []).append(Row(patient, images[0], images[1], position))
    return cohort


def personalised(task: Task, comm: MPI.Comm) -> dict:
    """One patient of a cohort on ``comm`` (the work of an ensemble): its report's summary."""

    pairs = [pair for row in task.pairs for pair in task.reading.pairs(row.expiration, row.inspiration, row.position)]
    scene = None if task.scene is None else scenes.load(task.scene)
    with recipe_scene(task.model, scene, comm) if task.model else contextlib.nullcontext((None, scene)) as (_, used):
        assert used is not None  # (a scene, or a model file's own)
        if task.model is not None and population.is_population(used):
            report = population.personalise(task.model, used, pairs, task.out, task.setting, comm)
        else:
            report = personalise(used, pairs, task.out, task.setting, comm)
    shapes = [pair["shape_coefficients"] for pair in report["registration"] if "shape_coefficients" in pair]
    return {
        "parameters": {
            name: {key: found[key] for key in ("value", "unit", "interval", "note")}
            for name, found in report["parameters"].items()
        },
        "surface_rms": report["fit"]["surface_rms"],
        "seconds": sum(report["seconds"].values()),
    } | ({"shape": shapes} if shapes else {})


def cohort(
    scene: str | Path | None,
    path: str | Path,
    out: str | Path,
    setting: Setting,
    ensemble: Ensemble,
    comm: MPI.Comm = MPI.COMM_WORLD,
    reading: Reading = Reading(),
    model: str | None = None,
) -> list[dict]:
    """Personalise every patient of the cohort file ``path`` with the scene file ``scene`` (or
    the ``model`` file's own scene, when None) and ``setting`` on ``ensemble`` (see the
    module's doc); write ``out`` and return a row per patient (its summary, or ``failed``).
    Collective over the ensemble's ranks."""
    path = Path(path).resolve()
    patients = read_cohort(path)
    images = sorted({file for rows in patients.values() for row in rows for file in (row.expiration, row.inspiration)})
    command = f"lungmech personalise --cohort {path}"
    inputs = [path, *(file for file in (scene, model) if file is not None), *images]
    with output_folder(out, comm, inputs=inputs, command=command) as staging:
        tasks = [
            Task(
                None if scene is None else str(scene),
                patient,
                tuple(rows),
                setting,
                str(staging / patient),
                reading,
                model,
            )
            for patient, rows in patients.items()
        ]
        say = logging.getLogger("lungmech").info
        outcomes = ensemble.map(personalised, tasks, lambda line: say("cohort: %s", line))
        found = [
            {"patient": task.patient, "pairs": len(task.pairs)}
            | (outcome.value if outcome.value is not None else {"failed": outcome.failed})
            for task, outcome in zip(tasks, outcomes)
        ]
        hold_signals_until_swap()
        write_json(staging / "cohort.json", {"patients": found, "ensemble": ensemble.description}, comm)
        on_root(comm, lambda: _write_table(found, staging / "cohort.csv"))
    return found


def _write_table(found: list[dict], target: Path) -> None:
    """cohort.csv: a row per patient, a value, low and high column per parameter (with its
    unit in the header), the fit's surface RMS (mm), the time (s), and why a patient failed; on a
    population's model, each pair's shape coefficients (sd of the library; pairs apart by ";")."""
    names: dict[str, str] = {}
    for row in found:
        for name, value in row.get("parameters", {}).items():
            names.setdefault(name, value["unit"])
    header = ["patient", "pairs"]
    for name, unit in names.items():
        header += [f"{name} [{unit}]", f"{name} low [{unit}]", f"{name} high [{unit}]", f"{name} note"]
    shaped = any("shape" in row for row in found)
    header += ["shape [sd]"] if shaped else []
    header += ["surface rms [mm]", "seconds [s]", "failed"]
    with open(target, "w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        for row in found:
            cells: list[object] = [row["patient"], row["pairs"]]
            for name in names:
                value = row.get("parameters", {}).get(name)
                interval = (value or {}).get("interval") or ["", ""]
                cells += [value["value"] if value else "", *interval, (value or {}).get("note") or ""]
            if shaped:
                cells.append("; ".join(" ".join(f"{a:+.3f}" for a in pair) for pair in row.get("shape", [])))
            rms = row.get("surface_rms")
            cells += ["" if rms is None else f"{1e3 * rms:.4g}", row.get("seconds", ""), row.get("failed") or ""]
            writer.writerow(cells)
