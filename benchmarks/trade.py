"""The speed–accuracy trade of the bundled breathing lung, measured by `lungmech trade` itself.

    python benchmarks/trade.py             # the imaged lung over its 3-parameter box (about 1.5 h on 2 cores)
    python benchmarks/trade.py --quick     # the sphere octant over its stiffness: P1, P2 and 2 reduced models against h/2
    python benchmarks/trade.py --quantity energy    # the same trade on the state in the energy norm (trade_energy.*)

A thin caller of :func:`lungmech.app.trade.trade`: the bundled ``lung_breathing_parameters``
scene, as the imaged-lung problem every command answers (the image is the lung at
end-expiration for every μ), over stiffness × breath depth × posture. Candidates: the full
model P1 at 2h (remeshed), h and h/2; POD Galerkin (20 vectors at most, 8 training points)
and its ECSW hyper-reductions at τ = 1e-3, 1e-4, 1e-5, built by the one reductor
(``--build``). P2 on h is left out: with balanced gravity it took 957–997 s a point here (26
Newton iterations, 85 % of them in the gravity's state-dependent tangent, assembled a unit at a
time), against 29 s for P1 h/2 — sixteen points would have cost four hours more. Reference: P1 h/4. Points: 8 seeded Sobol' points and the box's 8
corners. The quantity (``--quantity``): the volume at end-inspiration, relative to the breath's
volume change; or another of ``lungmech trade``'s, its results named after it.
The full solves run on Parsl's 2 local workers (``--workers 0``: one after another); each
candidate is then measured in a process of its own, on one rank.

Two tolerances, 1e-2 and 1e-4, chosen from one measurement. Every full answer and the models
are kept in lungmech's cache (``--cache``, default ``results/raw/lungmech-cache``): an
interrupted run resumes. Writes results/trade{,_quick}.{md,csv,png} and, beside them,
trade{,_quick}.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

import machine
from machine import provenance, say, write_results

TOLERANCES = (1e-2, 1e-4)
QUICK_TOLERANCES = (5e-2, 1e-3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the sphere octant, 2 interior points, small models")
    parser.add_argument("--workers", type=int, default=None, help="Parsl's local workers (default 2; 0 with --quick)")
    parser.add_argument("--cache", default=None, help="lungmech's cache folder (default results/raw/lungmech-cache)")
    parser.add_argument("--quantity", default="volume", help="what the tolerances are on (lungmech trade's --quantity)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the trade's progress lines
    workers = args.workers if args.workers is not None else (0 if args.quick else 2)
    with tempfile.TemporaryDirectory(prefix="lungmech-trade-") as folder:
        bundled = "sphere_inflation_parameters.toml" if args.quick else "lung_breathing_parameters.toml"
        scene = Path(str(resources.files("lungmech.scenes") / bundled))
        cache = Path(args.cache) if args.cache else (Path(folder) / "cache" if args.quick else _default_cache())
        found = _traded(scene, cache, workers, args.quick, args.quantity)
    named = "" if args.quantity == "volume" else f"_{args.quantity}"
    stem = f"trade{named}_quick" if args.quick else f"trade{named}"
    command = (
        "python benchmarks/trade.py"
        + (" --quick" if args.quick else "")
        + (f" --quantity {args.quantity}" if named else "")
    )
    _report(found, stem, command, workers)


def _default_cache() -> Path:
    return machine.RESULTS / "raw" / "lungmech-cache"


def _traded(scene: Path, cache: Path, workers: int, quick: bool, quantity: str) -> list:
    """The trade of ``scene`` at the first tolerance, measured; at the others, the same
    measurement chosen from again (:func:`lungmech.trade.choice.choose`)."""
    from dataclasses import replace

    from lungmech.app.ladder import Discretisation
    from lungmech.app.trade import Candidate, Family, trade
    from lungmech.errors import ParameterError
    from lungmech.parallel.engine import local_pool
    from lungmech.parallel.ensemble import Serial
    from lungmech.trade.choice import Choice, choose

    family = Family(taus=(1e-2,), sizes=(6,), samples=4) if quick else Family()
    count, levels = (1, 1) if quick else (8, 2)
    if quick:  # P1 and P2 on h
        full = [Candidate.full(Discretisation(0, degree)) for degree in (1, 2)]
    else:  # P1 at 2h, h and h/2 (P2 left out: see the module's doc)
        full = [Candidate.full(Discretisation(level, 1)) for level in (-1, 0, 1)]
    first, *others = QUICK_TOLERANCES if quick else TOLERANCES
    say(f"trade at {first:g}")
    began = time.perf_counter()
    if workers:
        with local_pool(workers, 1) as pool:
            found = trade(
                scene, first, quantity, count, cache=cache, levels=levels, full=full, build=family, ensemble=pool
            )
    else:
        found = trade(
            scene, first, quantity, count, cache=cache, levels=levels, full=full, build=family, ensemble=Serial()
        )
    kept = found.full_solves.get("kept", 0)
    found.notes.append(f"the trade took {time.perf_counter() - began:.0f} s; {kept} full answers were kept before")
    convergence = found.convergence.get(found.quantity)
    accuracy = None if convergence is None else convergence.estimate
    chosen = []
    for tolerance in others:
        try:
            choice = choose(found.measured, tolerance, found.quantity, None, accuracy)
        except ParameterError as refused:  # below the reference's own accuracy: the trade says so
            choice = Choice(None, f"refused: {refused}")
        chosen.append(replace(found, tolerance=tolerance, choice=choice))
    return [found, *chosen]


def _report(found: list, stem: str, command: str, workers: int) -> None:
    """results/<stem>.md (the first trade's page, each tolerance's choice), .csv, .png, .json."""
    from lungmech.app import trade_report
    from lungmech.app.plot import pareto

    first = found[0]
    choices = [f"- **{t.tolerance:.0e}**: {t.choice.reason if t.choice else 'none'}" for t in found]
    engine = f"Parsl's {workers} local workers of 1 rank" if workers else "one process"
    header = [
        "# The speed–accuracy trade of the bundled breathing lung",
        "",
        provenance(command, f"full solves on {engine}; each candidate measured on one rank"),
        "",
        f"The choice at each tolerance on the {trade_report.COLUMNS[first.quantity][0]} (relative to "
        f"{trade_report.quantities.DENOMINATORS[first.quantity]}):",
        "",
        *choices,
        "",
        "",
    ]
    page = trade_report.markdown(first, command).replace("![error against online time](trade.png)", "")
    page = page.replace(f"# Trade: {Path(first.scene).name}", "## The table")
    machine.RESULTS.mkdir(parents=True, exist_ok=True)
    write_results(machine.RESULTS, stem, trade_report.rows(first), "\n".join(header) + page)  # the plot beside it
    (machine.RESULTS / f"{stem}.json").write_text(json.dumps(trade_report.summary(first), indent=1) + "\n")
    label = trade_report.COLUMNS[first.quantity][0]
    pareto(
        trade_report.pareto_points(first),
        [t.tolerance for t in found],
        f"{label} (of {trade_report.quantities.DENOMINATORS[first.quantity]}) [-]",
        machine.RESULTS / f"{stem}.png",
        [t.choice.chosen.name for t in found if t.choice and t.choice.chosen],
        f"{Path(first.scene).name}: worst of {len(first.points)} points against {first.reference}",
    )
    print((machine.RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    sys.exit(main())
