"""``lungmech trade SCENE --tolerance TOL -o OUT``: which model of a scene meets a tolerance at
the least cost, measured (:func:`lungmech.app.trade.trade`), written to ``OUT``
(:mod:`lungmech.app.trade_report`) and shown as a table."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from lungmech.app.arguments import RESULTS, check_ensemble, ensemble_of, ensemble_options, setup
from lungmech.trade.quantities import QUANTITIES

COMMANDS = ("trade",)


def add_commands(commands: argparse._SubParsersAction) -> None:
    """``trade`` under ``commands``."""
    trade = commands.add_parser(
        "trade",
        help="measure full and reduced models of a scene on the same points and choose the cheapest that "
        "meets a tolerance",
    )
    trade.add_argument("scene", help="scene file (.toml), or a bundled scene by name")
    trade.add_argument(
        "--tolerance",
        type=float,
        required=True,
        help="the largest relative error allowed on --quantity, over every test point (e.g. 1e-2)",
    )
    trade.add_argument(
        "--quantity",
        default="volume",
        choices=QUANTITIES,
        help="what the tolerance is on: volume (at end-inspiration, of the volume change to it; default), "
        "pv (the P–V curve, of the path's largest volume change), probes (of their largest motion), "
        "energy (the state at end-inspiration on the reference's mesh, in the energy norm, of its change from the start)",
    )
    trade.add_argument(
        "--points",
        type=int,
        default=8,
        help="seeded Sobol' test points inside the [parameters] box, none a model was trained on (default 8); "
        "the box's corners are added",
    )
    trade.add_argument("--seed", type=int, default=12345, help="seed of the test points (default 12345)")
    trade.add_argument(
        "--models", nargs="+", default=[], metavar="FILE", help="reduced model files (.npz) of this scene to measure"
    )
    trade.add_argument(
        "--build",
        action="store_true",
        help="also build reduced models (POD Galerkin and ECSW at each --taus, at each of --sizes) by the one "
        "reductor, kept in the cache",
    )
    trade.add_argument(
        "--taus",
        default=None,
        type=_numbers,
        help="with --build: the ECSW tolerances τ, comma-separated, or 'none' for Galerkin alone "
        "(default 1e-3,1e-4,1e-5)",
    )
    trade.add_argument(
        "--sizes",
        "--size",
        type=_integers,
        default=None,
        help="with --build: basis sizes, comma-separated: the POD's leading vectors, each a Galerkin model and "
        "each τ's ECSW (default 20)",
    )
    trade.add_argument("--samples", type=int, default=None, help="with --build: training points (Sobol'; default 8)")
    trade.add_argument(
        "--queries",
        type=int,
        default=None,
        help="share each model's offline cost over this many queries when choosing (default: online time alone)",
    )
    trade.add_argument(
        "--levels",
        type=int,
        default=2,
        help="the reference is the scene's mesh refined this many times (default 2: h/4), finer than every "
        "full candidate (h and its refinements down to h/2^(levels-1), 2h, P2 on h)",
    )
    ensemble_options(trade, "the full solves")
    trade.add_argument(
        "-o",
        "--output",
        help="output folder (default results/<scene name>-trade); replaced only when the trade succeeds, and "
        "only if it is empty or lungmech's own",
    )
    trade.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    from lungmech.app import trade_report
    from lungmech.app.trade import Family, trade
    from lungmech.errors import ParameterError
    from lungmech.parallel import on_root
    from lungmech.parallel.destination import hold_signals_until_swap, output_folder
    from lungmech.trade.choice import check_tolerance

    check_tolerance(args.tolerance)
    comm, _, name, path = setup(args)
    if not args.build and (args.samples, args.sizes, args.taus) != (None, None, None):
        raise ParameterError("--taus, --sizes and --samples shape the models --build makes: give --build")
    given = {
        "taus": None if args.taus is None else tuple(args.taus),
        "sizes": None if args.sizes is None else tuple(args.sizes),
        "samples": args.samples,
    }
    family = Family(**{name: value for name, value in given.items() if value is not None}) if args.build else None
    check_ensemble(args, comm)
    output = Path(args.output if args.output is not None else RESULTS / f"{path.stem}-trade")
    if comm.rank == 0:
        print(f"lungmech: trading the models of {name} at {args.tolerance:g} on {args.quantity}", flush=True)
    with (
        output_folder(output, comm, inputs=[path, *args.models], command="trade") as staging,
        ensemble_of(args, comm) as ensemble,
    ):
        found = trade(
            path,
            args.tolerance,
            args.quantity,
            args.points,
            args.models,
            args.queries,
            args.cache,
            args.levels,
            args.seed,
            build=family,
            comm=comm,
            ensemble=ensemble,
        )
        hold_signals_until_swap()
        on_root(comm, lambda: trade_report.write(found, staging, "lungmech " + shlex.join(args.argv)))
    if comm.rank == 0:
        print(trade_report.console_table(found))
        print(f"lungmech: outputs in {output.resolve()}")
    return 0


def _numbers(text: str) -> list[float]:
    if text.strip().lower() == "none":
        return []
    try:
        return [float(item) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text!r}") from None


def _integers(text: str) -> list[int]:
    try:
        return [int(item) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of whole numbers: {text!r}") from None
