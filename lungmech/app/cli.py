"""Command line: ``lungmech run [SCENE] -o OUT``, ``lungmech rom build|solve``, ``lungmech register``,
``lungmech shape-modes``, ``lungmech shape``, ``lungmech phantom`` and ``lungmech info``.

Every failure ends in one line on standard error and a non-zero exit: 2 for bad input or a
failed computation, 130/143 for Ctrl-C/SIGTERM, 3 for an internal error (``LUNGMECH_DEBUG=1``
shows its traceback). Under MPI the line is printed once, and a failure that reaches one rank
only ends the whole run rather than leaving the others waiting.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
from collections.abc import Iterator
from importlib import resources
from pathlib import Path

from lungmech.app import registration_cli as registration
from lungmech.errors import Interrupted, LungmechError, ParameterError

DEFAULT_SCENE = "lung_breathing.toml"
RESULTS = Path("results")  # default outputs go to results/<name of the scene, model or image>


class UsageError(LungmechError):
    """A command line that argparse cannot parse."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, not the usage block
        raise UsageError(f"{message} (see '{self.prog} --help')")


def parser() -> argparse.ArgumentParser:
    top = _Parser(prog="lungmech", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = top.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="solve a scene (the bundled default scene when none is given)")
    run.add_argument("scene", nargs="?", help="scene file (.toml)")
    _common(run, "results/<scene name>")
    rom = commands.add_parser("rom", help="reduced-order models: build one from a scene, solve with one")
    actions = rom.add_subparsers(dest="action", required=True)
    build = actions.add_parser("build", help="build a reduced model from full-order runs of a scene")
    build.add_argument("scene", nargs="?", help="scene file (.toml; default: the bundled scene)")
    build.add_argument("-o", "--output", required=True, help="reduced model file (.npz)")
    build.add_argument("--basis", default="pod", help="pod, modal, modal+derivatives, polynomial or pod+modal")
    build.add_argument(
        "--size", type=int, default=20, help="number of basis vectors, at most (modes, for modal+derivatives)"
    )
    build.add_argument(
        "--scales",
        default=None,
        type=_scales,
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
    build.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")
    solve = actions.add_parser("solve", help="solve a scene with a reduced model (same outputs as run)")
    solve.add_argument("model", help="reduced model file (.npz) from 'lungmech rom build'")
    solve.add_argument("scene", nargs="?", help="scene file (default: the scene stored in the model file)")
    _common(solve, "results/<model name>-reduced")
    solve.add_argument(
        "--sweep",
        metavar="CSV",
        help="solve at every parameter point of this CSV file (a header of parameter names, one row per "
        "point): sweep.csv, summary.json and sweep.png in the output folder (default results/<model name>-sweep)",
    )
    registration.add_commands(commands)
    commands.add_parser("info", help="versions, MPI size and available laws")
    return top


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit code (never raises for bad input, interrupts or failures)."""
    _failures()  # collective, now, while every rank is here
    with _interrupts():
        try:
            args = parser().parse_args(argv)
            # Values are judged by lungmech's own finite checks, which name them: NumPy's
            # overflow warnings on the way would only add lines before that one.
            with _quiet_arithmetic():
                return _dispatch(args)
        except LungmechError as error:
            return _fail(2, f"lungmech: error: {error}")
        except Interrupted as interrupt:
            return _fail(
                128 + interrupt.signum,
                f"lungmech: interrupted by {interrupt.name}; nothing was written and earlier results are unchanged",
                interrupted=True,
            )
        except KeyboardInterrupt:
            return _fail(
                130, "lungmech: interrupted; nothing was written and earlier results are unchanged", interrupted=True
            )
        except OSError as error:  # the machine's, not lungmech's: a file or folder it cannot use (a JIT cache, say)
            if Interrupted.pending is not None or os.environ.get("LUNGMECH_DEBUG") or not error.strerror:
                return _main_failure(error)
            where = f"'{error.filename}'" if error.filename else "a file or folder"
            return _fail(2, f"lungmech: error: cannot use {where}: {error.strerror}")
        except Exception as error:  # a bug: say so in one line, with the traceback on request
            return _main_failure(error)


def _main_failure(error: Exception) -> int:
    """Exit 3 for an internal error (its traceback with LUNGMECH_DEBUG=1), or 130/143 for a
    signal that surfaced as one (inside a PETSc callback)."""
    if Interrupted.pending is not None:
        return _fail(
            128 + Interrupted.pending,
            f"lungmech: interrupted by {Interrupted(Interrupted.pending).name}; nothing was written and "
            "earlier results are unchanged",
            interrupted=True,
        )
    if os.environ.get("LUNGMECH_DEBUG"):
        raise error
    return _fail(
        3,
        f"lungmech: internal error ({type(error).__name__}: {error}); please report it "
        "(LUNGMECH_DEBUG=1 shows the traceback)",
    )


@contextlib.contextmanager
def _quiet_arithmetic() -> Iterator[None]:
    import warnings

    import numpy as np

    with np.errstate(over="ignore", invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=RuntimeWarning, message=".*(overflow|invalid value|divide by zero)")
        yield


def _dispatch(args: argparse.Namespace) -> int:
    if args.command == "info":
        return _info()
    if args.command in registration.COMMANDS:
        return registration.run(args)
    if args.command == "rom" and args.action == "build":
        return _rom_build(args)
    return _run(args)


def _fail(code: int, message: str, interrupted: bool = False) -> int:
    """Print ``message`` once and return ``code`` when every rank failed alike; otherwise
    (the failure reached this rank only) print it and end the whole MPI run now."""

    from lungmech import parallel

    comm = _failures()
    # Collective errors arrive together; a wait this long means the failure reached this rank alone.
    if parallel.arrive(comm, timeout=3.0 if interrupted else 60.0):
        if comm.rank == 0:
            print(message, file=sys.stderr, flush=True)
        return code
    print(f"{message} (rank {comm.rank}; ending the other ranks)", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(code)  # mpiexec then ends the ranks that wait for this one


_FAILURES = None


def _failures():
    """A communicator of its own for failures (a duplicate of the world's, made once): its
    barrier can never be matched by the job's own collective calls, so a rank that fails alone
    is told so instead of passing for a collective failure."""
    global _FAILURES
    if _FAILURES is None:
        from mpi4py import MPI

        _FAILURES = MPI.COMM_WORLD.Dup()
    return _FAILURES


@contextlib.contextmanager
def _interrupts() -> Iterator[None]:
    """SIGINT and SIGTERM raise :class:`Interrupted` (so staging folders are removed), or, in a
    deferred block (collective writes, :func:`lungmech.parallel.deferred`), are remembered until
    its end; a second one ends the process at once. Libraries that reset the handlers when they
    start (gmsh) are followed by :func:`lungmech.mesh.builders.gmsh_session`, which puts them back."""

    from petsc4py import PETSc  # noqa: F401  (PETSc installs its own handlers when it starts: ours come after)

    def handler(signum, frame):
        for again in (signal.SIGINT, signal.SIGTERM):
            signal.signal(again, lambda s, f: os._exit(128 + s))
        Interrupted.pending = signum
        if Interrupted.deferring:
            return
        raise Interrupted(signum)

    Interrupted.pending = None
    try:
        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread (e.g. called from a test runner's worker)
        yield
        return
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)


def _common(command: argparse.ArgumentParser, default: str) -> None:
    command.add_argument(
        "-o",
        "--output",
        help=f"output folder (default {default}); replaced only when the run "
        "succeeds, and only if it is empty or lungmech's own",
    )
    command.add_argument(
        "--scale",
        default=(1.0,),
        type=_scales,
        metavar="S",
        help="scale the loads' change from the start (one factor, or one per load joined by ':')",
    )
    command.add_argument(
        "--set",
        action="append",
        default=[],
        type=_assignment,
        metavar="NAME=VALUE",
        help="set a parameter of the scene's [parameters] (repeatable); checked against its range",
    )
    command.add_argument(
        "--at",
        type=_seconds,
        metavar="T",
        help="a static answer: the equilibrium at time T (s) of the load path (the path stops there); "
        "summary.json's outputs hold it",
    )
    command.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"--at takes a time in s, a finite number (got {text!r})")
    return value


def _assignment(text: str) -> tuple[str, float]:
    name, equals, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not equals or not name.strip() or not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"--set takes NAME=NUMBER (got {text!r})")
    return name.strip(), number


def _scales(text: str) -> list:
    """'0.5,1' -> [0.5, 1.0]; '0.5:1,1.5:1' -> [(0.5, 1.0), (1.5, 1.0)]; finite numbers only."""
    import math

    try:
        scales = [tuple(float(f) for f in item.split(":")) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not all(math.isfinite(f) for scale in scales for f in scale):
        raise argparse.ArgumentTypeError(f"load scales must be finite numbers: {text!r}")
    return [s[0] if len(s) == 1 else s for s in scales]


def _logging(args):
    """Logging on rank 0 (warnings only with --quiet); returns the world communicator."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    logging.basicConfig(
        level=logging.WARNING if args.quiet or comm.rank != 0 else logging.INFO,
        format="%(message)s",
        stream=sys.stdout,
        force=True,
    )
    return comm


def _setup(args):
    """Logging on rank 0, and the scene named by ``args.scene`` (or the bundled one)."""
    from lungmech.app import scene as scenes

    comm = _logging(args)
    if args.scene is None:
        with resources.as_file(resources.files("lungmech.scenes") / DEFAULT_SCENE) as path:
            return comm, scenes.load(path), f"bundled default scene ({DEFAULT_SCENE})", Path(path)
    return comm, scenes.load(args.scene), args.scene, Path(args.scene)


def _rom_build(args) -> int:
    from lungmech.app.reduce import build

    comm, scene, name, path = _setup(args)
    if comm.rank == 0:
        print(f"lungmech: building a {args.basis} reduced model of {name}", flush=True)
    summary = build(
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
    )
    if comm.rank == 0:
        seconds = ", ".join(f"{k} {v:.1f} s" for k, v in summary["offline_seconds"].items())
        hyper = summary["hyper"]
        sampled = (
            f", hyper-reduced by ECSW at τ = {hyper['tolerance']:g} on "
            + ", ".join(f"{n} {name.replace('_', ' ')}" for name, n in hyper["samples"].items())
            + f" sampled cells of {hyper['cells']}"
            if hyper
            else ""
        )
        print(
            f"lungmech: {summary['kind']} basis of {summary['size']} vectors on {summary['dofs']} dofs{sampled} "
            f"({seconds}); saved to {Path(args.output).resolve()}"
        )
        if greedy := summary["greedy"]:
            print(_greedy_report(greedy))
    return 0


def _greedy_report(greedy: dict) -> str:
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


def _run(args) -> int:
    if args.command == "rom" and args.sweep is not None:
        return _sweep(args)
    if args.command == "rom" and args.scene is None:  # the scene inside the model file
        from lungmech.app.reduce import embedded_scene

        comm = _logging(args)
        with embedded_scene(args.model, comm) as scene:
            return _solve(args, comm, scene, f"the scene inside {args.model}", Path(args.model))
    comm, scene, name, path = _setup(args)
    return _solve(args, comm, scene, name, path)


def _sweep(args) -> int:
    from lungmech.app.sweep import sweep

    comm = _logging(args)
    if args.scene is not None:
        raise ParameterError("--sweep solves the scene inside the model file: leave out the scene file")
    if args.scale != (1.0,):
        raise ParameterError("--sweep takes no --scale: sweep a load's amplitude as a column of [parameters]")
    output = args.output if args.output is not None else RESULTS / f"{Path(args.model).stem}-sweep"
    if comm.rank == 0:
        print(f"lungmech: sweeping the reduced model {args.model} over the points of {args.sweep}", flush=True)
    summary = sweep(args.model, args.sweep, output, comm, dict(args.set), None if args.at is None else [args.at])
    if comm.rank == 0:
        largest = summary["error_indicator_largest"]
        estimate = f"; largest estimated error {largest:.1e} (relative, energy norm)" if largest is not None else ""
        print(
            f"lungmech: {summary['points']} points in {sum(summary['seconds_per_point']):.2f} s "
            f"(median {1e3 * summary['median_seconds_per_point']:.1f} ms per point){estimate}; outputs in "
            f"{Path(output).resolve()}"
        )
    return 0


def _solve(args, comm, scene, name: str, path: Path) -> int:
    from lungmech.app.console import end_of_run
    from lungmech.app.run import check_scale, full_order_model, run

    model, inputs, note = full_order_model, [], None
    if args.set:
        scene = scene.with_values(dict(args.set))
    if len(args.scale) > 1:
        raise ParameterError("--scale takes one value (per-load factors are joined by ':', e.g. 1.2:1)")
    scale = check_scale(scene, args.scale[0])
    if args.command == "rom":
        from lungmech.app.reduce import reduced_order, trained_range
        from lungmech.rom import store

        model, inputs = reduced_order(args.model, inside=args.scene is None), [args.model]
        note = trained_range(store.read_on_root(args.model, comm, arrays=False)[0]["extra"], scale)
    default = f"{Path(args.model).stem}-reduced" if args.command == "rom" else path.stem
    output = args.output if args.output is not None else RESULTS / default
    if comm.rank == 0:
        how = " with the reduced model " + args.model if args.command == "rom" else ""
        print(f"lungmech: running {name}{how}" + (f": {scene.title}" if scene.title else ""), flush=True)
        if note:
            print(f"lungmech: note: {note}", flush=True)
    summary = run(scene, output, comm, scale=scale, model=model, inputs=inputs, times=_at(args, scene))
    if comm.rank == 0:
        print(end_of_run(summary, Path(output).resolve()))
    return 0


def _at(args, scene) -> list[float] | None:
    """The static answer's time (--at T, s), checked against the scene's load path."""
    if args.at is None:
        return None
    stepping = scene.stepping
    if not stepping.start <= args.at <= stepping.end:
        raise ParameterError(
            f"--at {args.at:g} s lies outside the scene's load path [{stepping.start:g}, {stepping.end:g}] s "
            "([stepping] start and end)"
        )
    return [args.at]


def _info() -> int:
    import petsc4py
    from mpi4py import MPI

    import dolfinx

    import lungmech
    from lungmech.fem.materials import LAWS

    try:
        import slepc4py

        slepc = slepc4py.__version__
    except ImportError:
        slepc = "not installed"
    print(f"lungmech {lungmech.__version__}")
    print(f"DOLFINx {dolfinx.__version__}, petsc4py {petsc4py.__version__}, slepc4py {slepc}")
    print(f"Python {sys.version.split()[0]}, MPI ranks {MPI.COMM_WORLD.size}")
    print("laws: " + ", ".join([*LAWS, "sum"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
