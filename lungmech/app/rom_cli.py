"""The reduced-model commands of the CLI: ``rom build`` and ``rom solve`` (its ``--sweep``; a
single solve is ``run``'s, :func:`lungmech.app.cli.main`)."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import TYPE_CHECKING

from lungmech.app.arguments import (
    RESULTS,
    check_ensemble,
    common,
    ensemble_of,
    ensemble_options,
    logging_comm,
    probes_option,
    scales,
    setup,
    with_probes,
)
from lungmech.errors import ParameterError

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.app.scene import Scene
    from lungmech.parallel.ensemble import Ensemble


def add_commands(commands: argparse._SubParsersAction) -> None:
    """``rom build`` and ``rom solve`` under ``commands``."""
    rom = commands.add_parser("rom", help="reduced-order models: build one from a scene, solve with one")
    actions = rom.add_subparsers(dest="action", required=True)
    build = actions.add_parser("build", help="build a reduced model from full-order runs of a scene")
    build.add_argument(
        "scene", nargs="?", help="scene file (.toml), or a bundled scene by name (default: lung_breathing)"
    )
    build.add_argument("-o", "--output", required=True, help="reduced model file (.npz)")
    build.add_argument("--basis", default="pod", help="pod, modal, modal+derivatives, polynomial or pod+modal")
    build.add_argument(
        "--size", type=int, default=20, help="number of basis vectors, at most (modes, for modal+derivatives)"
    )
    build.add_argument(
        "--scales",
        default=None,
        type=scales,
        help="training load scales, comma-separated; one factor per load joined by ':' (e.g. 0.5:1,1.5:1); "
        "default 0.5,1,1.5, or 1 when the scene has [parameters]",
    )
    build.add_argument(
        "--samples",
        type=int,
        default=None,
        help="training points: Sobol' samples of the scene's [parameters] box (default 8; 1 without parameters)",
    )
    build.add_argument("--seed", type=int, default=0, help="seed of the training samples (default 0)")
    build.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="train greedily over the [parameters] box until the reduced model's error indicator (relative "
        "energy-norm error) is below this at every candidate point (--samples of them, default 32)",
    )
    build.add_argument(
        "--inner",
        default="energy",
        help="inner product of the basis: energy (the default: the tangent at rest, the norm of the tolerance, "
        "the indicator and the errors), mass or l2",
    )
    build.add_argument("--order", type=int, default=2, help="order of a polynomial basis")
    build.add_argument(
        "--hyper",
        default=None,
        help="hyper-reduction: ecsw (online work on a few sampled cells, independent of the mesh size)",
    )
    build.add_argument(
        "--ecsw-tolerance",
        type=float,
        default=1e-4,
        help="ECSW: reproduce the training reduced forces to this relative tolerance (default 1e-4)",
    )
    build.add_argument(
        "--ecsw-size",
        type=int,
        default=None,
        help="ECSW: truncate the basis to this many vectors after sampling (the sample trained on the whole basis)",
    )
    build.add_argument(
        "--ecsw-judge",
        type=float,
        default=None,
        help="ECSW with --tolerance: the tolerance the greedy judges its rounds at (default --ecsw-tolerance); "
        "the model is then re-sampled at --ecsw-tolerance",
    )
    build.add_argument(
        "--batch",
        type=int,
        default=1,
        metavar="B",
        help="with --tolerance: full solves a greedy round adds, at its B largest indicators, solved at once on "
        "the groups or workers below (default 1)",
    )
    ensemble_options(build, "the training's full solves")
    probes_option(build)
    build.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")
    solve = actions.add_parser("solve", help="solve a scene with a reduced model (same outputs as run)")
    solve.add_argument("model", help="reduced model file (.npz) from 'lungmech rom build'")
    solve.add_argument("scene", nargs="?", help="scene file (default: the scene stored in the model file)")
    common(solve, "results/<model name>-reduced")
    solve.add_argument(
        "--fields",
        action="store_true",
        help="also the full fields (fields.pvd, where the scene's [output] asks) and deformed.png: the full "
        "mesh is built (without it, a hyper-reduced model is solved on its sampled cells alone)",
    )
    solve.add_argument(
        "--sweep",
        metavar="CSV",
        help="solve at every parameter point of this CSV file (a header of parameter names, one row per "
        "point): sweep.csv, summary.json and sweep.png in the output folder (default results/<model name>-sweep)",
    )


def build(args: argparse.Namespace) -> int:
    comm, scene, name, path = setup(args)
    check_ensemble(args, comm)
    scene = with_probes(args, scene, comm)
    if comm.rank == 0:
        print(f"lungmech: building a {args.basis} reduced model of {name}", flush=True)
    given = args.engine is not None or args.group_size is not None
    with ensemble_of(args, comm) if given else contextlib.nullcontext(None) as ensemble:
        summary = _built(args, scene, comm, ensemble)
    if comm.rank == 0:
        seconds = ", ".join(f"{k} {v:.1f} s" for k, v in summary["offline_seconds"].items())
        hyper = summary["hyper"]
        sampled = (
            f", hyper-reduced by ECSW at τ = {hyper['tolerance']:g} on {hyper['described']} of the mesh's {hyper['cells']}"
            if hyper
            else ""
        )
        print(
            f"lungmech: {summary['kind']} basis of {summary['size']} vectors on {summary['dofs']} dofs{sampled} "
            f"({seconds}); saved to {Path(args.output).resolve()}"
        )
        if paths := summary.get("training_paths"):
            print(
                f"lungmech: training: {paths['solved'] + paths['kept']} full solves ({paths['where']}), "
                f"{paths['solved']} solved now, {paths['kept']} found in the cache {paths['cache']}"
            )
        if greedy := summary["greedy"]:
            print(greedy_report(greedy))
    return 0


def _built(args: argparse.Namespace, scene: Scene, comm: MPI.Comm, ensemble: Ensemble | None) -> dict:
    from lungmech.app.reduce import build

    return build(
        scene,
        args.output,
        kind=args.basis,
        size=args.size,
        scales=args.scales,
        samples=args.samples,
        seed=args.seed,
        inner=args.inner,
        order=args.order,
        comm=comm,
        hyper=args.hyper,
        hyper_tolerance=args.ecsw_tolerance,
        tolerance=args.tolerance,
        hyper_size=args.ecsw_size,
        judge=args.ecsw_judge,
        batch=args.batch,
        ensemble=ensemble,
        cache=args.cache,
    )


def greedy_report(greedy: dict) -> str:
    """The greedy training in a few lines: each full solve's indicator next to the true error."""
    last = greedy["rounds"][-1]
    verdict = "met" if greedy["met"] else "NOT met (no candidate point or full solve was left to improve it)"
    largest = f"{last['indicator']:.2e}" if last["indicator"] is not None else "inf (a reduced solve failed)"
    lines = [
        f"lungmech: greedy training: tolerance {greedy['tolerance']:g} {verdict} with {greedy['full_solves']} full "
        f"solves; largest indicator over the candidates and the training points {largest} × safety "
        f"{greedy['safety']:.2f}, at {last['where']} (relative energy-norm errors [1])"
    ]
    for r in greedy["rounds"][:-1]:
        shown = f"{r['indicator']:.2e}" if r["indicator"] is not None else "failed solve"
        error = f"{r['error']:.2e}" if r["error"] is not None else "n/a"
        lines.append(f"  {r['size']:3d} vectors: indicator {shown}, true error {error} at {r['where']}")
    return "\n".join(lines)


def sweep(args: argparse.Namespace) -> int:
    from lungmech.app.sweep import sweep as solve_points

    comm = logging_comm(args)
    if args.scene is not None:
        raise ParameterError("--sweep solves the scene inside the model file: leave out the scene file")
    if args.scale != (1.0,):
        raise ParameterError("--sweep takes no --scale: sweep a load's amplitude as a column of [parameters]")
    output = args.output if args.output is not None else RESULTS / f"{Path(args.model).stem}-sweep"
    if comm.rank == 0:
        print(f"lungmech: sweeping the reduced model {args.model} over the points of {args.sweep}", flush=True)
    summary = solve_points(args.model, args.sweep, output, comm, dict(args.set), None if args.at is None else [args.at])
    if comm.rank == 0:
        largest = summary["error_indicator_largest"]
        estimate = f"; largest estimated error {largest:.1e} (relative, energy norm)" if largest is not None else ""
        print(
            f"lungmech: {summary['points']} points in {sum(summary['seconds_per_point']):.2f} s "
            f"(median {1e3 * summary['median_seconds_per_point']:.1f} ms per point){estimate}; outputs in "
            f"{Path(output).resolve()}"
        )
    return 0
