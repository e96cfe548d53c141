"""The recipe of a patient's reduced model, from a model file or a tolerance: rebuilt for the patient.

A reduced model is built for one mesh, and a patient's lung is a new mesh (the reference lung
registered onto its image), so ``lungmech personalise --model FILE`` does not reuse the file's
basis: it reads how the file was made — a POD basis of ``size`` vectors from ``training`` full
breaths, hyper-reduced by ECSW at τ (or not); or a PGD of at most ``size`` terms fitted to
``training`` full breaths (its splines' intervals and the fit's tolerance chosen for the
patient as by default) — and on which scene (its physics, its reference lung at its mesh
size h), and builds the same for the patient. The file is what ``lungmech trade`` chose for a
tolerance (its ``model.npz``), any ``lungmech rom build`` of the scene, or its ``lungmech pgd
build --samples``.

``--tolerance TOL`` takes the recipe that ``lungmech trade``, run once on the bundled lung
(``make bench-trade``: its scene ``lung_breathing_parameters``, the physics and mesh of
``lung_personalise``), measured as the cheapest reduced model whose worst error on the volume
at end-inspiration (of the breath's volume change) met TOL: :data:`MEASURED`, package data
written from that run's ``trade.json`` by :func:`measured_recipes` (``python -m
lungmech.app.recipe benchmarks/results/trade.json``; a test keeps the two equal). The
patient's own model is then checked at 3 points, as any.

Refused in one line: a file that is not a reduced model, a basis kind other than POD or a
fitted PGD (the patient's model is trained on its own breaths: an a priori PGD is not, and
answers no imaged lung), a file built for other physics than the scene given beside it, and a
tolerance no measured recipe met.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

from lungmech.app.model_file import embedded_scene
from lungmech.app.reduce import check_physics
from lungmech.app.scene import Scene, physics
from lungmech.errors import ModelFileError, ParameterError
from lungmech.pgd.store import is_pgd
from lungmech.rom import store

__all__ = ["MEASURED", "Recipe", "measured_recipes", "recipe_for", "recipe_scene"]

MEASURED = Path(__file__).resolve().parents[1] / "scenes" / "lung_breathing_parameters.trade.json"


@dataclass(frozen=True)
class Recipe:
    """How a reduced model was made, read from ``source``: by ``method`` "pod", a POD basis of
    ``size`` vectors from ``training`` full solves, ECSW at ``tau`` (None: Galerkin on the whole
    mesh); by "pgd", a PGD of at most ``size`` terms fitted to ``training`` full solves."""

    size: int
    training: int
    tau: float | None
    source: str
    method: str = "pod"


@contextlib.contextmanager
def recipe_scene(
    path: str | Path, scene: Scene | None, comm: MPI.Comm = MPI.COMM_WORLD
) -> Iterator[tuple[Recipe, Scene]]:
    """The recipe of the model file ``path`` and the scene to personalise with it: ``scene``
    (which must model the file's physics), or else the file's own (its reference lung at its
    mesh size), for the duration of the block. Collective."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model file '{path}' not found")
    content = store.read_on_root(path, comm)
    recipe = _recipe(path, content[0])
    with embedded_scene(path, comm, content=content) as built:
        if scene is None:
            yield recipe, built
            return
        check_physics(path, physics(built), scene)
    yield recipe, scene


def _recipe(path: Path, metadata: dict) -> Recipe:
    """The recipe of the model file ``path`` from its ``metadata``, or its refusal in one line."""
    if is_pgd(metadata):
        built = metadata["extra"]["pgd"].get("built", {})
        if not built.get("samples"):
            raise ModelFileError(
                f"'{path}' is an a priori PGD; a patient's model is fitted to its own breaths: give a PGD built with "
                "--samples (lungmech pgd build), or leave out --model and give --method pgd"
            )
        terms = built.get("options", {}).get("max_terms")
        if terms is None:
            raise ModelFileError(f"'{path}' is damaged: its PGD record has no most terms; rebuild it")
        return Recipe(int(terms), int(built["samples"]), None, str(path), "pgd")
    record = metadata.get("extra", {}).get("reduced")
    if record is None or not record.get("training"):
        raise ModelFileError(f"'{path}' is not a reduced model built from training solves (lungmech rom build, trade)")
    if metadata["kind"] != "pod":
        raise ModelFileError(
            f"'{path}' holds a {metadata['kind']} basis; a patient's model is a POD or a PGD of its own breaths: give "
            "a POD model, or a fitted PGD"
        )
    hyper = record.get("hyper") or {}
    return Recipe(int(metadata["size"]), len(record["training"]), hyper.get("tolerance"), str(path))


def measured_recipes(trade: dict) -> dict:
    """The reduced candidates of a ``lungmech trade`` summary (its ``trade.json``) as recipes:
    name, family, basis size, ECSW τ, training solves (the Galerkin candidate's full solves:
    the family is one reductor's), worst and mean error and the online time, with the trade's
    scene, quantity, date and command."""
    models = [m for m in trade["models"] if m["family"] in ("galerkin", "ecsw")]
    training = next((m["full solves"] for m in models if m["family"] == "galerkin"), None)
    if not models or not training:
        raise ParameterError("the trade holds no POD Galerkin candidate, whose full solves are its training")
    quantity = trade["quantity"]
    return {
        "scene": Path(trade["scene"]).name,
        "quantity": quantity,
        "denominator": trade.get("denominator"),
        "date": trade["date"],
        "command": trade.get("command") or "",
        "recipes": [
            {
                "name": m["model"],
                "family": m["family"],
                "size": m["basis size"],
                "tau": m["ECSW τ"],
                "training": training,
                "worst_error": m[f"{quantity} error max [-]"],
                "online_ms": m["online [ms]"],
            }
            for m in models
        ],
    }


def recipe_for(tolerance: float, measured: Path = MEASURED) -> Recipe:
    """The cheapest (online) measured recipe whose worst error met ``tolerance``."""
    table = json.loads(measured.read_text())
    met = [r for r in table["recipes"] if r["worst_error"] is not None and r["worst_error"] <= tolerance]
    if not met:
        best = min((r for r in table["recipes"] if r["worst_error"] is not None), key=lambda r: r["worst_error"])
        raise ParameterError(
            f"--tolerance {tolerance:g}: no reduced model of the bundled lung's trade ({table['date'][:10]}) met it; "
            f"the most accurate, {best['name']}, is off by {best['worst_error']:.1e} on the {table['quantity']} "
            f"({table['denominator']})"
        )
    chosen = min(met, key=lambda r: r["online_ms"])
    source = f"{chosen['name']} ({chosen['worst_error']:.1e} ≤ {tolerance:g}), lungmech trade of {table['scene']}"
    return Recipe(int(chosen["size"]), int(chosen["training"]), chosen["tau"], source)


if __name__ == "__main__":  # python -m lungmech.app.recipe TRADE_JSON: the measured recipes, as package data
    table = measured_recipes(json.loads(Path(sys.argv[1]).read_text())) | {"from": sys.argv[1]}
    MEASURED.write_text(json.dumps(table, indent=1) + "\n")
