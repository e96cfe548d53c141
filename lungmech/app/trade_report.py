"""What a trade found, for people and programs: ``trade.md``, ``trade.csv``, ``trade.json``, the
Pareto plot ``trade.png``, a one-screen console table, and ``choice.json`` (with the chosen
model file beside it) for ``rom solve`` and the twin.

Every column carries its unit; every error says its denominator (:mod:`lungmech.trade.quantities`).
Per model: the worst and mean error over the points on each quantity and the point of the
worst, a reduced model's error of reduction alone (against the full model on the scene's mesh,
which it reduces), the largest error it estimated of itself (a reduced model's indicator, in the
energy norm: beside the measured errors, a check of its own warning light), the points where it failed, its warm online time per point, its start-up, its offline
cost (seconds and full solves) and its peak memory.
"""

from __future__ import annotations

import csv
import datetime
import json
import math
import platform
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import lungmech
from lungmech.trade import quantities
from lungmech.trade.points import failure_bound

if TYPE_CHECKING:
    from lungmech.app.trade import Trade

__all__ = ["console_table", "markdown", "pareto_points", "rows", "summary", "write"]

FAMILIES = {"full": "full order", "galerkin": "Galerkin (reduced)", "ecsw": "hyper-reduced (ECSW)", "pgd": "PGD"}
COLUMNS = {  # a quantity's error columns: the name and unit they carry
    "volume": ("volume error", "-"),
    "pv": ("P–V error", "-"),
    "probes": ("probe error", "-"),
    "probes_mm": ("probe error", "mm"),
    "energy": ("energy-norm error", "-"),
}


def rows(found: Trade) -> list[dict[str, Any]]:
    """One row per measured model (the reference first), every column with its unit."""
    out = []
    chosen = found.choice.chosen.name if found.choice is not None and found.choice.chosen is not None else None
    for name in [found.reference, *(m.name for m in found.measured)]:
        result, family = found.results[name], found.families[name]
        row: dict[str, Any] = {
            "model": name,
            "family": "reference" if name == found.reference else family,
            "dofs": result.get("dofs"),
            "basis size": result.get("basis_size"),
            "ECSW τ": (result.get("hyper") or {}).get("tolerance"),
        }
        judged = name != found.reference  # the reference's answers are the yardstick, not judged
        for quantity, values in found.errors.get(name, {}).items():
            label, unit = COLUMNS[quantity]
            row[f"{label} max [{unit}]"] = _max(values) if judged else None
            row[f"{label} mean [{unit}]"] = _mean(values) if judged else None
        errors = found.errors.get(name, {}).get(found.quantity)
        row["point of max"] = _point(_worst_point(found, errors)) if judged and errors is not None else None
        reduction = found.reduction.get(name, {}).get(found.quantity)
        row["reduction error max [-]"] = None if reduction is None else _max(reduction)
        answers = result["answers"]
        row["own estimate max [-]"] = _own_estimate(answers) if judged else None
        row["failed points"] = sum(a["failed"] is not None for a in answers)
        row["online [ms]"] = _ms(result.get("online_seconds")) if judged else None
        row["timed solves"] = result.get("timed_solves") if judged else None
        row["start-up [s]"] = result.get("start_up_seconds") if judged else None
        row["offline [s]"] = result.get("offline_seconds", 0.0) if judged else None
        row["full solves"] = result.get("full_solves", 0) if judged else None
        row["peak RSS [MiB]"] = result.get("peak_rss_mib") if judged else None
        row["chosen"] = name == chosen
        out.append(row)
    return out


def _own_estimate(answers: list[dict]) -> float | None:
    """The largest error a model estimated of its own answers (a reduced model's indicator: its
    relative energy-norm error along the path, :mod:`lungmech.rom.indicator`), None where it
    gives none (a full model, a basis without an enrichment)."""
    estimates = [a["indicator"] for a in answers if a["failed"] is None and a.get("indicator") is not None]
    return max(estimates) if estimates else None


def summary(found: Trade) -> dict[str, Any]:
    """Everything the trade measured, as JSON: the settings, the points, each model's errors at
    every point (nan as null), its costs, the reference's convergence, the choice and the notes."""
    choice = found.choice
    return _finite(
        {
            "lungmech": lungmech.__version__,
            "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "machine": f"{platform.node()} ({platform.machine()}, {platform.system()})",
            "scene": found.scene,
            "tolerance": found.tolerance,
            "quantity": found.quantity,
            "denominator": quantities.DENOMINATORS[found.quantity],
            "queries": found.queries,
            "full_solves_on": found.ensemble,
            "full_solves": found.full_solves,
            "output_times_s": found.times,
            "reference": found.reference,
            "reduced_against": found.own,
            "points": [
                {"kind": kind, "values": point}
                for kind, point in zip(found.points.kinds, found.points.points, strict=True)
            ],
            "failure_bound_95": failure_bound(len(found.points)),
            "convergence": {
                q: {"observed": c.observed, "expected": c.expected, "agree": c.agree, "reference_error": c.estimate}
                for q, c in found.convergence.items()
            },
            "models": [
                row
                | {
                    "errors": {q: _listed(v) for q, v in found.errors.get(row["model"], {}).items()},
                    "reduction_errors": {q: _listed(v) for q, v in found.reduction.get(row["model"], {}).items()},
                    "failures": [a["failed"] for a in found.results[row["model"]]["answers"]],
                    "ranks": found.results[row["model"]].get("ranks"),
                }
                for row in rows(found)
            ],
            "choice": None
            if choice is None
            else {"model": None if choice.chosen is None else choice.chosen.name, "reason": choice.reason},
            "notes": found.notes,
        }
    )


def markdown(found: Trade, command: str = "") -> str:
    """The trade as a page: what was asked, the table, the reference's convergence, the choice."""
    table = rows(found)
    columns = [c for c in table[0] if c not in ("chosen",)]
    lines = [
        f"# Trade: {Path(found.scene).name}",
        "",
        f"Which model meets **{found.tolerance:.1e}** on **{found.quantity}** (relative to "
        f"{quantities.DENOMINATORS[found.quantity]}) at the least cost per query"
        + (f", its offline cost shared over {found.queries} queries" if found.queries else "")
        + "?",
        "",
        f"- Points: {len(found.points)} ({_kinds(found)}); none failing, the share of the box that could fail "
        f"is below {failure_bound(len(found.points)):.1%} (95 %).",
        f"- Reference: {found.reference}"
        + (f", static at t = {found.times[0]:g} s" if found.times else ", the whole path")
        + ".",
    ]
    if found.reduction:
        lines.append(
            f"- Reduction error: a reduced model against {found.own}, the full model it reduces (same "
            "denominator): its own share of the error, which a larger basis or a smaller τ removes; the rest is "
            "the mesh's. Its own estimate estimates this share."
        )
    for q, c in found.convergence.items():
        estimate = f"; the reference's own error ≈ {c.estimate:.1e} (Richardson)" if c.estimate is not None else ""
        lines.append(f"- Observed order of {q}: {c.observed:.2f} (expected {c.expected:g}){estimate}.")
    solves = found.full_solves
    lines.append(
        f"- Full solves: {solves.get('solved', 0)} solved ({found.ensemble}), {solves.get('kept', 0)} found in the "
        "cache; each candidate then measured in a process of its own."
    )
    if command:
        lines.append(f"- Command: `{command}`")
    lines += ["", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in table:
        cells = [_cell(row[c]) for c in columns]
        if row["chosen"]:
            cells[0] = f"**{cells[0]}** (chosen)"
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"**Choice**: {found.choice.reason if found.choice else 'none'}", ""]
    if found.notes:
        lines += ["Notes:", "", *(f"- {note}" for note in found.notes), ""]
    lines += ["![error against online time](trade.png)", ""]
    return "\n".join(lines)


def console_table(found: Trade) -> str:
    """One screen: a line per model (the chosen one starred), the reference, the choice."""
    q = found.quantity
    worst = f"worst {COLUMNS[q][0]}"
    width = len(worst) + 2
    header = f"{'':2}{'model':<22}{'family':<10}{'dofs':>9}{worst:>{width}}{'failed':>8}"
    header += f"{'online ms':>11}{'offline s':>11}{'RSS MiB':>9}"
    lines = [header]
    for row in rows(found):
        mark = "* " if row["chosen"] else "  "
        dofs = "" if row["dofs"] is None else str(row["dofs"])
        line = f"{mark}{row['model'][:21]:<22}{row['family'][:9]:<10}{dofs:>9}"
        line += f"{_short(row.get(f'{COLUMNS[q][0]} max [-]')):>{width}}{row['failed points']:>8}"
        line += f"{_short(row.get('online [ms]')):>11}{_short(row.get('offline [s]')):>11}"
        line += f"{_short(row.get('peak RSS [MiB]')):>9}"
        lines.append(line)
    lines.append(
        f"errors relative to {quantities.DENOMINATORS[q]}, against {found.reference}, at {len(found.points)} points"
    )
    for name, c in found.convergence.items():
        lines.append(f"observed order of {name}: {c.observed:.2f} (expected {c.expected:g})")
    lines.append(f"choice: {found.choice.reason if found.choice else 'none'}")
    lines += [f"note: {note}" for note in found.notes]
    return "\n".join(lines)


def write(found: Trade, folder: Path, command: str = "") -> None:
    """``trade.md``, ``trade.csv``, ``trade.json``, ``trade.png`` and ``choice.json`` (with the
    chosen model file copied beside it as ``model.npz``) into ``folder``. Rank 0 only."""
    from mpi4py import MPI

    from lungmech.app.plot import drawn, pareto

    table = rows(found)
    (folder / "trade.md").write_text(markdown(found, command))
    with open(folder / "trade.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in table)
    (folder / "trade.json").write_text(json.dumps(summary(found) | {"command": command}, indent=1) + "\n")
    (folder / "choice.json").write_text(json.dumps(_finite(choice_record(found, folder)), indent=1) + "\n")
    shown = pareto_points(found)
    chosen = next((row["model"] for row in table if row["chosen"]), None)
    title = f"{Path(found.scene).name}: worst of {len(found.points)} points against {found.reference}"
    label = f"{COLUMNS[found.quantity][0]} (of {quantities.DENOMINATORS[found.quantity]}) [-]"
    convergence = found.convergence.get(found.quantity)
    accuracy = convergence.estimate if convergence is not None else None
    drawn(
        MPI.COMM_SELF,
        folder / "trade.png",
        lambda: pareto(shown, found.tolerance, label, folder / "trade.png", chosen, title, accuracy),
    )


def pareto_points(found: Trade) -> list[tuple[str, str, float | None, float | None, int, float]]:
    """Each candidate's (name, family, online ms, worst error, failed points, offline s), for
    :func:`lungmech.app.plot.pareto`."""
    label = COLUMNS[found.quantity][0]
    return [
        (r["model"], r["family"], r["online [ms]"], r[f"{label} max [-]"], r["failed points"], r["offline [s]"] or 0.0)
        for r in rows(found)
        if r["family"] != "reference"
    ]


def choice_record(found: Trade, folder: Path) -> dict[str, Any]:
    """What was chosen and what it was validated on; a model file is copied to ``folder``
    (``model.npz``, for ``lungmech rom solve``)."""
    chosen = found.choice.chosen if found.choice is not None else None
    record: dict[str, Any] = {
        "scene": found.scene,
        "quantity": found.quantity,
        "tolerance": found.tolerance,
        "reason": found.choice.reason if found.choice is not None else None,
        "validated_on": {
            "points": len(found.points),
            "kinds": _kinds(found),
            "reference": found.reference,
            "failure_bound_95": failure_bound(len(found.points)),
        },
        "model": None,
    }
    if chosen is None:
        return record
    request = found.requests[chosen.name]
    record["model"] = {"name": chosen.name, "family": chosen.family, "worst_error": chosen.error}
    if request["kind"] == "file":
        shutil.copyfile(request["path"], folder / "model.npz")
        record["model"] |= {"file": "model.npz", "built_from": request["path"]}
    else:
        record["model"] |= {"discretisation": request["discretisation"]}
    record["model"]["online_ms"] = _ms(chosen.online)
    record["model"]["offline_s"] = chosen.offline
    return record


def _kinds(found: Trade) -> str:
    kinds = found.points.kinds
    return ", ".join(f"{kinds.count(k)} {k}" for k in dict.fromkeys(kinds))


def _worst_point(found: Trade, errors: np.ndarray) -> dict[str, float] | None:
    """The point of the largest error (a failed one first: its error is unbounded)."""
    if np.isnan(errors).any():
        return found.points.points[int(np.flatnonzero(np.isnan(errors))[0])]
    return found.points.points[int(np.argmax(errors))] if errors.size else None


def _max(values: np.ndarray) -> float | None:
    finite = values[~np.isnan(values)]
    return float(finite.max()) if finite.size else None


def _mean(values: np.ndarray) -> float | None:
    finite = values[~np.isnan(values)]
    return float(finite.mean()) if finite.size else None


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None or not math.isfinite(seconds) else 1e3 * seconds


def _listed(values: np.ndarray) -> list[float | None]:
    return [None if math.isnan(v) else float(v) for v in values]


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else ""
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def _point(values: dict[str, float] | None) -> str | None:
    """A parameter point as text: "stiffness=5, depth=0.8" (the defaults: "defaults")."""
    if values is None:
        return None
    return ", ".join(f"{k}={v:.4g}" for k, v in values.items()) or "defaults"


def _short(value: Any) -> str:
    return "" if value is None else f"{value:.3g}" if isinstance(value, float) else str(value)


def _finite(data: Any) -> Any:
    """JSON without NaN or infinities (null in their place)."""
    if isinstance(data, dict):
        return {k: _finite(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [_finite(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data
