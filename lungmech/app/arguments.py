"""What the command line's commands share: the options of a solve (``-o``, ``--scale``, ``--set``,
``--at``, ``-q``), their value types, logging on rank 0 and the scene a command names."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import sys
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.app.scene import Scene
    from lungmech.parallel.ensemble import Ensemble

DEFAULT_SCENE = "lung_breathing.toml"
RESULTS = Path("results")  # default outputs go to results/<name of the scene, model or image>


def common(command: argparse.ArgumentParser, default: str) -> None:
    command.add_argument(
        "-o",
        "--output",
        help=f"output folder (default {default}); replaced only when the run "
        "succeeds, and only if it is empty or lungmech's own",
    )
    command.add_argument(
        "--scale",
        default=(1.0,),
        type=scales,
        metavar="S",
        help="scale the loads' change from the start (one factor, or one per load joined by ':')",
    )
    command.add_argument(
        "--set",
        action="append",
        default=[],
        type=assignment,
        metavar="NAME=VALUE",
        help="set a parameter of the scene's [parameters] (repeatable); checked against its range",
    )
    command.add_argument(
        "--at",
        type=seconds,
        metavar="T",
        help="a static answer: the equilibrium at time T (s) of the load path (the path stops there); "
        "summary.json's outputs hold it",
    )
    command.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")


def seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"--at takes a time in s, a finite number (got {text!r})")
    return value


def assignment(text: str) -> tuple[str, float]:
    name, equals, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not equals or not name.strip() or not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"--set takes NAME=NUMBER (got {text!r})")
    return name.strip(), number


def labels(text: str) -> tuple[int, ...]:
    """'3' -> (3,); '12,13,14' -> (12, 13, 14): the labels of an organ in a label image (a
    lung's lobes, say)."""
    try:
        values = tuple(int(item) for item in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--label takes integers, comma-separated (got {text!r})") from None
    return values


def image_label(command: argparse.ArgumentParser, what: str) -> None:
    """The --label option: which values of a label image are the ``what``."""
    command.add_argument(
        "--label",
        type=labels,
        help=f"label of the {what} in a multi-label segmentation; several comma-separated (a lung's lobes) are "
        "taken together",
    )


def scales(text: str) -> list:
    """'0.5,1' -> [0.5, 1.0]; '0.5:1,1.5:1' -> [(0.5, 1.0), (1.5, 1.0)]; finite numbers only."""
    import math

    try:
        scales = [tuple(float(f) for f in item.split(":")) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not all(math.isfinite(f) for scale in scales for f in scale):
        raise argparse.ArgumentTypeError(f"load scales must be finite numbers: {text!r}")
    return [s[0] if len(s) == 1 else s for s in scales]


def logging_comm(args: argparse.Namespace) -> MPI.Comm:
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


def setup(args: argparse.Namespace) -> tuple[MPI.Comm, Scene, str, Path]:
    """Logging on rank 0, and the scene named by ``args.scene`` (or the bundled one)."""
    from lungmech.app import scene as scenes
    from lungmech.errors import SceneError
    from lungmech.scenes import bundled, names

    comm = logging_comm(args)
    if args.scene is None:
        with resources.as_file(resources.files("lungmech.scenes") / DEFAULT_SCENE) as path:
            return comm, scenes.load(path), f"bundled default scene ({DEFAULT_SCENE})", Path(path)
    if not Path(args.scene).exists():  # a file of that name is the user's; else a bundled scene
        found = bundled(args.scene)
        if found is None:
            listed = ", ".join(names())
            raise SceneError(f"scene file '{args.scene}' not found (bundled scenes, named without a path: {listed})")
        with resources.as_file(found) as path:
            return comm, scenes.load(path), f"bundled scene {path.name}", Path(path)
    return comm, scenes.load(args.scene), args.scene, Path(args.scene)


def probes_option(command: argparse.ArgumentParser) -> None:
    """``--probes scene|surface``: a model file's probes (``rom build``, ``pgd build``)."""
    command.add_argument(
        "--probes",
        choices=("scene", "surface"),
        default="scene",
        help="the model's probes: the scene's (default), or its mesh's surface nodes (on a population's scene, "
        "its template's): a model lungmech personalise --model fits a patient's images with",
    )


def with_probes(args: argparse.Namespace, scene: Scene, comm: MPI.Comm) -> Scene:
    """``scene`` with the probes ``--probes`` asks for (:func:`probes_option`)."""
    from lungmech.app.template import with_surface_probes

    return with_surface_probes(scene, comm) if args.probes == "surface" else scene


def ensemble_options(command: argparse.ArgumentParser, what: str, cache: bool = True) -> None:
    """Where ``what`` (many independent solves) run: --group-size, --engine, --workers,
    --worker-ranks, and (``cache``) --cache, where their answers are kept."""
    command.add_argument(
        "--group-size",
        type=int,
        default=None,
        metavar="K",
        help=f"under mpiexec -n P: {what} in P/K groups of K ranks, each solving its own points "
        "(default: every solve on all P ranks)",
    )
    command.add_argument(
        "--engine",
        choices=("parsl",),
        default=None,
        help=f"{what} on Parsl's workers on this machine (pip install lungmech[cluster]); a cluster's "
        "provider is given in Python (docs: the MPI guide)",
    )
    command.add_argument("--workers", type=int, default=2, help="with --engine: solves at once (default 2)")
    command.add_argument("--worker-ranks", type=int, default=1, help="with --engine: MPI ranks of each (default 1)")
    if not cache:
        return
    command.add_argument(
        "--cache",
        default=None,
        help=f"lungmech's cache folder, where {what} are kept: a rerun resumes from them (default $LUNGMECH_CACHE "
        "or ~/.cache/lungmech)",
    )


def check_ensemble(args: argparse.Namespace, comm: MPI.Comm) -> None:
    """Refuse ensemble options that cannot act together, in one line."""
    from lungmech.errors import ParameterError

    if args.engine is not None and (comm.size > 1 or args.group_size is not None):
        raise ParameterError("--engine starts its own workers: run it on one rank, without --group-size")
    if args.engine is None and (args.workers != 2 or args.worker_ranks != 1):
        raise ParameterError("--workers and --worker-ranks shape an engine's workers: give --engine parsl")


@contextlib.contextmanager
def ensemble_of(args: argparse.Namespace, comm: MPI.Comm) -> Iterator[Ensemble]:
    """Where the solves run: Parsl's workers (--engine), groups of ranks (--group-size), or
    this process on every rank; stopped at the end. Collective."""
    from lungmech.parallel.ensemble import Groups, Serial

    if args.engine is not None:
        from lungmech.parallel.engine import local_pool

        with local_pool(args.workers, args.worker_ranks) as pool:
            yield pool
    elif args.group_size is not None:
        groups = Groups(args.group_size, comm)
        try:
            yield groups
        finally:
            groups.free()
    else:
        yield Serial(comm)
