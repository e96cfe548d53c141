"""docs/units.md gives the unit of every parameter a user sets.

The keys are read from the code (the laws' dataclass fields, the scene parser's tables of laws,
formulations, constraints and loads and the signatures it checks keys against, the command-line
parser, the registration ``Options``), so a new key without a row in the table fails here.

A row of the table is ``| where | key | unit | meaning |``; the names in backticks in its first
two cells are the places (section, law, load, builder, command) and the keys it documents.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
from pathlib import Path

import pytest

from lungmech.app import cli
from lungmech.app import scene as scenes
from lungmech.fem.materials import LAWS
from lungmech.registration.sobolev import Options

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "docs" / "units.md"
UNITS = {"—", "1", "m", "mm", "voxel", "s", "Pa", "N", "N/m³", "kg/m³", "m/s²", "residual's unit"}
# Command-line options that take no parameter of the physics: where results go, and quiet.
NOT_PARAMETERS = {"--help", "--output", "--quiet"}


def _names(cell: str) -> set[str]:
    return set(re.findall(r"`([^`]+)`", cell))


def _rows() -> list[tuple[set[str], set[str], str]]:
    """(places, keys, unit) of every row of the table; a row without a place is the top level."""
    rows = []
    for line in TABLE.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]  # "\|" is a bar inside a cell
        if len(cells) != 4 or cells[0] == "where" or set(cells[0]) <= {"-"}:
            continue
        where, keys, unit, _ = cells
        rows.append((_names(where) or {""}, _names(keys), unit))
    return rows


ROWS = _rows()


def _missing(required: list[tuple[set[str], str]]) -> list[str]:
    """The (places, key) pairs no row documents: a row must name every place and the key."""
    return [
        f"{' '.join(sorted(places))}: {key}"
        for places, key in required
        if not any(places <= where and key in keys for where, keys, _ in ROWS)
    ]


def _parameters(function) -> list[str]:
    return [p for p in inspect.signature(function).parameters if p not in ("self", "comm")]


def _laws() -> list[tuple[set[str], str]]:
    required = []
    for name, law in LAWS.items():
        keys = [f.name for f in dataclasses.fields(law)]
        keys += _parameters(law.from_young) if hasattr(law, "from_young") else []
        keys += ["incompressible"] if hasattr(law, "incompressible") else []
        required += [({"[material]", name}, key) for key in keys]
    for name, builder in scenes.COMPOSITE_LAWS.items():
        required += [({"[material]", name}, key) for key in _parameters(builder)]
    return required + [({"[material]"}, "law"), ({"[material]", "sum"}, "terms")]


def _scene() -> list[tuple[set[str], str]]:
    required = [({""}, "title"), ({"[geometry]"}, "builder"), ({"[geometry]"}, "file"), ({"[geometry]"}, "boundaries")]
    for name, builder in scenes.BUILDERS.items():
        required += [({"[geometry]", name}, key) for key in _parameters(builder)]
    required += [({"[formulation]"}, "type"), ({"[formulation]"}, "degree")]
    for name, formulation in scenes.FORMULATIONS.items():
        required += [({"[formulation]", name}, key) for key in _parameters(formulation)]
    for section, kinds in (("[[constraints]]", scenes.CONSTRAINTS), ("[[loads]]", scenes.LOADS)):
        required.append(({section}, "type"))
        for name, kind in kinds.items():
            required += [({section, name}, key) for key in _parameters(kind)]
    required += [({"ramp"}, key) for key in _parameters(scenes.Ramp)]
    for section, settings in (
        ("[stepping]", scenes.Stepping),
        ("[solver]", scenes.NewtonOptions),
        ("[inverse]", scenes.InverseOptions),
        ("[output]", scenes.Output),
    ):
        required += [({section}, key) for key in _parameters(settings)]
    return required


def _commands(parser: argparse.ArgumentParser, prefix: str = "lungmech") -> list[tuple[set[str], str]]:
    """Every option of every (sub)command that takes a value, by its long name."""
    required = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, command in action.choices.items():
                required += _commands(command, f"{prefix} {name}")
        elif action.option_strings and action.nargs != 0:  # options with a value, not flags
            option = max(action.option_strings, key=len)
            if option not in NOT_PARAMETERS:
                required.append(({prefix}, option))
    return required


def _registration() -> list[tuple[set[str], str]]:
    return [({"Options"}, f.name) for f in dataclasses.fields(Options)]


@pytest.mark.parametrize(
    "what, required",
    [
        ("law parameters", _laws()),
        ("scene keys", _scene()),
        ("command-line options", _commands(cli.parser())),
        ("registration Options", _registration()),
    ],
    ids=["laws", "scene", "commands", "registration"],
)
def test_every_parameter_has_its_unit(what, required):
    assert required, f"found no {what} to check"
    assert _missing(required) == [], f"{what} missing from {TABLE.relative_to(ROOT)}"


def test_every_unit_is_one_of_the_known_ones():
    assert ROWS and {unit for _, _, unit in ROWS} <= UNITS


def test_the_readme_links_the_table():
    assert "(docs/units.md)" in (ROOT / "README.md").read_text(encoding="utf-8")
