"""Command line: ``lungmech run [SCENE] -o OUT`` and ``lungmech info``."""

from __future__ import annotations

import argparse
import logging
import sys
from importlib import resources
from pathlib import Path

from lungmech.errors import LungmechError

DEFAULT_SCENE = "lung_breathing.toml"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lungmech", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="solve a scene (the bundled default scene when none is given)")
    run.add_argument("scene", nargs="?", help="scene file (.toml)")
    run.add_argument("-o", "--output", default="results", help="output folder (replaced only on success)")
    run.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")
    commands.add_parser("info", help="versions, MPI size and available laws")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            return _info()
        return _run(args)
    except LungmechError as error:
        print(f"lungmech: error: {error}", file=sys.stderr)
        return 2


def _run(args) -> int:
    from mpi4py import MPI

    from lungmech import scene as scenes
    from lungmech.run import run

    comm = MPI.COMM_WORLD
    logging.basicConfig(
        level=logging.WARNING if args.quiet or comm.rank != 0 else logging.INFO,
        format="%(message)s",
        stream=sys.stdout,
    )
    if args.scene is None:
        with resources.as_file(resources.files("lungmech.scenes") / DEFAULT_SCENE) as path:
            scene = scenes.load(path)
        name = f"bundled default scene ({DEFAULT_SCENE})"
    else:
        scene = scenes.load(args.scene)
        name = args.scene
    if comm.rank == 0:
        print(f"lungmech: running {name}" + (f": {scene.title}" if scene.title else ""), flush=True)
    summary = run(scene, args.output, comm)
    if comm.rank == 0:
        print(
            f"lungmech: done in {summary['steps']} steps, {summary['newton_iterations']} Newton iterations; "
            f"volume {summary['reference_volume']:.6g} -> largest {summary['largest_volume']['volume']:.6g} "
            f"(t = {summary['largest_volume']['time']:.3g}) -> final {summary['deformed_volume']:.6g}; "
            f"outputs in {Path(args.output).resolve()}"
        )
    return 0


def _info() -> int:
    import dolfinx
    import petsc4py
    from mpi4py import MPI

    import lungmech
    from lungmech.materials import LAWS

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
