"""Command line: ``lungmech run [SCENE] -o OUT``, ``lungmech rom build|solve``, ``lungmech trade``,
``lungmech personalise``,
``lungmech register``, ``lungmech shape-modes``, ``lungmech shape``, ``lungmech phantom`` and
``lungmech info``.

Every failure ends in one line on standard error and a non-zero exit: 2 for bad input or a
failed computation, 130/143 for Ctrl-C/SIGTERM, 3 for an internal error (``LUNGMECH_DEBUG=1``
shows its traceback). Under MPI the line is printed once, and a failure that reaches one rank
only ends the whole run rather than leaving the others waiting.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, NoReturn

from lungmech._threads import cap_threads
from lungmech.app import personalise_cli, pgd_cli, rom_cli, trade_cli
from lungmech.app import registration_cli as registration
from lungmech.app.arguments import RESULTS, check_ensemble, common, ensemble_of, ensemble_options, logging_comm, setup
from lungmech.errors import Interrupted, LungmechError, ParameterError

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.app.scene import Scene
    from lungmech.fem.parametric import ParametricModel


class UsageError(LungmechError):
    """A command line that argparse cannot parse."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, not the usage block
        raise UsageError(f"{message} (see '{self.prog} --help')")


def parser() -> argparse.ArgumentParser:
    top = _Parser(prog="lungmech", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = top.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="solve a scene (the bundled default scene when none is given)")
    run.add_argument(
        "scene", nargs="?", help="scene file (.toml), or a bundled scene by name (e.g. lung_breathing_parameters)"
    )
    common(run, "results/<scene name>")
    run.add_argument(
        "--sweep",
        metavar="CSV",
        help="solve the full model at every parameter point of this CSV file (a header of parameter names, one "
        "row per point), each point one solve of an ensemble: sweep.csv, summary.json and sweep.png in the "
        "output folder (default results/<scene name>-sweep)",
    )
    ensemble_options(run, "with --sweep, the points' solves")
    rom_cli.add_commands(commands)
    pgd_cli.add_commands(commands)
    trade_cli.add_commands(commands)
    personalise_cli.add_commands(commands)
    registration.add_commands(commands)
    commands.add_parser("info", help="versions, MPI size and available laws")
    return top


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit code (never raises for bad input, interrupts or failures)."""
    _failures()  # collective, now, while every rank is here
    cap_threads()  # one BLAS thread: threads that spin for cores another load holds cost far more than they give
    with _interrupts():
        try:
            args = parser().parse_args(argv)
            args.argv = list(sys.argv[1:] if argv is None else argv)
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
    if args.command in trade_cli.COMMANDS:
        return trade_cli.run(args)
    if args.command in personalise_cli.COMMANDS:
        return personalise_cli.run(args)
    if args.command in pgd_cli.COMMANDS:
        return pgd_cli.run(args)
    if args.command == "rom" and args.action == "build":
        return rom_cli.build(args)
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


_FAILURES: MPI.Comm | None = None


def _failures() -> MPI.Comm:
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

    def handler(signum: int, frame: FrameType | None) -> None:
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


def _run(args: argparse.Namespace) -> int:
    if args.command == "rom" and args.sweep is not None:
        return rom_cli.sweep(args)
    if args.command == "run" and args.sweep is not None:
        return _sweep(args)
    if args.command == "run" and (args.group_size, args.engine, args.cache, args.workers, args.worker_ranks) != (
        None,
        None,
        None,
        2,
        1,
    ):
        raise ParameterError(
            "--group-size, --engine, --workers, --worker-ranks and --cache say where a sweep's solves run: give --sweep"
        )
    if args.command == "rom" and args.scene is None:  # the scene inside the model file
        from lungmech.app.reduce import embedded_scene
        from lungmech.rom import store

        comm = logging_comm(args)
        content = store.read_on_root(args.model, comm)  # once: the digest reads every byte
        with embedded_scene(args.model, comm, content=content) as scene:
            return _solve(args, comm, scene, f"the scene inside {args.model}", Path(args.model), content)
    comm, scene, name, path = setup(args)
    return _solve(args, comm, scene, name, path)


def _solve(
    args: argparse.Namespace,
    comm: MPI.Comm,
    scene: Scene,
    name: str,
    path: Path,
    content: tuple[dict, dict] | None = None,
) -> int:
    from lungmech.app.console import end_of_run
    from lungmech.app.run import check_scale, full_order_model, run

    model: Callable[[Scene, MPI.Comm], ParametricModel] = full_order_model
    inputs, note = [], None
    if args.set:
        scene = scene.with_values(dict(args.set))
    if len(args.scale) > 1:
        raise ParameterError("--scale takes one value (per-load factors are joined by ':', e.g. 1.2:1)")
    scale = check_scale(scene, args.scale[0])
    if args.command == "rom":
        from lungmech.app.reduce import reduced_order, trained_range
        from lungmech.rom import store

        content = content if content is not None else store.read_on_root(args.model, comm)
        model = reduced_order(args.model, inside=args.scene is None, fields=args.fields, content=content)
        inputs, note = [args.model], trained_range(content[0]["extra"], scale)
    default = f"{Path(args.model).stem}-reduced" if args.command == "rom" else path.stem
    output = args.output if args.output is not None else RESULTS / default
    if comm.rank == 0:
        how = " with the reduced model " + args.model if args.command == "rom" else ""
        print(f"lungmech: running {name}{how}" + (f": {scene.title}" if scene.title else ""), flush=True)
        if note:
            print(f"lungmech: note: {note}", flush=True)
    full_fields = args.command != "rom" or args.fields
    summary = run(
        scene, output, comm, scale=scale, model=model, inputs=inputs, times=_at(args, scene), full_fields=full_fields
    )
    if comm.rank == 0:
        print(end_of_run(summary, Path(output).resolve()))
    return 0


def _sweep(args: argparse.Namespace) -> int:
    """``run SCENE --sweep CSV``: the full model at every point, on the ensemble the options name."""
    from lungmech.app.cache import default_folder
    from lungmech.app.sweep import sweep_full

    comm, scene, name, path = setup(args)
    check_ensemble(args, comm)
    if args.scale != (1.0,):
        raise ParameterError("--sweep takes no --scale: sweep a load's amplitude as a column of [parameters]")
    output = args.output if args.output is not None else RESULTS / f"{path.stem}-sweep"
    if comm.rank == 0:
        print(f"lungmech: sweeping the full model of {name} over the points of {args.sweep}", flush=True)
    cache = args.cache if args.cache is not None else default_folder()
    with ensemble_of(args, comm) as ensemble:
        summary = sweep_full(path, args.sweep, output, ensemble, cache, comm, dict(args.set), _at(args, scene))
    if comm.rank == 0:
        failed = f", {len(summary['failed'])} failed (see summary.json)" if summary["failed"] else ""
        print(
            f"lungmech: {summary['points']} points ({summary['full solves on']}), median "
            f"{summary['median_seconds_per_point']:.2f} s per solve{failed}; outputs in {Path(output).resolve()}"
        )
    return 0


def _at(args: argparse.Namespace, scene: Scene) -> list[float] | None:
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
