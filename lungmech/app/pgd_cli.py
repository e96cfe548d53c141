"""The PGD command of the CLI: ``pgd build`` (its models are solved with ``rom solve``, the one
online path of every model file)."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from lungmech.app.arguments import check_ensemble, ensemble_of, ensemble_options, probes_option, setup, with_probes

COMMANDS = ("pgd",)


def add_commands(commands: argparse._SubParsersAction) -> None:
    """``pgd build`` under ``commands``."""
    pgd = commands.add_parser("pgd", help="a PGD model: the solution over the whole [parameters] box, no full solve")
    actions = pgd.add_subparsers(dest="action", required=True)
    build = actions.add_parser(
        "build",
        help="build a scene's PGD model, a priori or (--samples) fitted to full solves; solve it with "
        "'lungmech rom solve FILE --set/--sweep'",
    )
    build.add_argument("scene", nargs="?", help="scene file (.toml) with [parameters], or a bundled scene by name")
    build.add_argument("-o", "--output", required=True, help="PGD model file (.npz)")
    build.add_argument("--modes", type=int, default=20, help="separated terms at most (default 20)")
    build.add_argument(
        "--intervals",
        type=int,
        default=None,
        help="cubic-spline intervals on each parameter's axis (default 32; a nonlinear model a priori, 2; with "
        "--samples, the best of 1, 2, 4 and 8 on the held-out solves)",
    )
    build.add_argument(
        "--tolerance",
        type=float,
        default=1e-6,
        help="stop when a new term's amplitude is below this fraction of the whole's, in the box's mean energy "
        "norm; with --samples, when the fit's relative least-squares error is below it (default 1e-6)",
    )
    build.add_argument(
        "--samples",
        type=int,
        default=None,
        help="fit the terms to the full model's solves at this many Sobol' points of the box (any model: "
        "nonlinear laws, follower pressures); the number of terms, up to --modes, is chosen on a held-out "
        "quarter of them (default: a priori, no full solve)",
    )
    build.add_argument(
        "--quadrature",
        type=int,
        default=512,
        help="a priori, a nonlinear model (Newton on the box): the most residual assemblies an iteration — the "
        "parameters' Gauss grid where it has no more points, else this many Sobol' points (default 512)",
    )
    build.add_argument(
        "--seed", type=int, default=0, help="the Sobol' sample's seed (--samples, --quadrature; default 0)"
    )
    ensemble_options(build, "the full solves of --samples")
    probes_option(build)
    build.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    """``lungmech pgd build``: the model file, and its summary in a few lines."""
    from lungmech.app.pgd import build

    comm, scene, name, _ = setup(args)
    check_ensemble(args, comm)
    scene = with_probes(args, scene, comm)
    if comm.rank == 0:
        print(f"lungmech: building the PGD model of {name}", flush=True)
    given = args.engine is not None or args.group_size is not None
    with ensemble_of(args, comm) if given else contextlib.nullcontext(None) as ensemble:
        summary = build(
            scene,
            args.output,
            args.modes,
            args.intervals,
            args.tolerance,
            comm,
            samples=args.samples,
            seed=args.seed,
            ensemble=ensemble,
            cache=args.cache,
            quadrature=args.quadrature,
        )
    if comm.rank == 0 and summary["samples"] is not None:
        seconds = ", ".join(f"{k} {v:.1f} s" for k, v in summary["offline_seconds"].items())
        print(
            f"lungmech: {summary['terms']} separated terms on {summary['modes']} space modes over "
            f"{', '.join(summary['parameters'])} ({summary['dofs']} dofs), fitted to {summary['samples']} full "
            f"solves; held-out error {summary['held_out']:.1e} (relative, energy norm, the largest over a quarter "
            f"of the solves held out); {seconds}; saved to {Path(args.output).resolve()}"
        )
    elif comm.rank == 0:
        seconds = ", ".join(f"{k} {v:.1f} s" for k, v in summary["offline_seconds"].items())
        stopped = (
            f"the last term's amplitude {summary['last_amplitude']:.1e} below the tolerance"
            if summary["converged"]
            else f"at --modes {args.modes} (the last term's amplitude {summary['last_amplitude']:.1e}, relative)"
        )
        newton = ""
        if summary["newton_iterations"] is not None:
            newton = (
                f"Newton on {summary['quadrature']} points of the box, {', '.join(map(str, summary['newton_iterations']))} "
                f"iterations at the output times; indicator {summary['estimate']:.1e} (the largest at 16 points); "
            )
        print(
            f"lungmech: {summary['terms']} separated terms on {summary['modes']} space modes over "
            f"{', '.join(summary['parameters'])} ({summary['dofs']} dofs; {newton}stopped {stopped}; {seconds}); "
            f"saved to {Path(args.output).resolve()}"
        )
    return 0
