"""Command line: ``lungmech run [SCENE] -o OUT``, ``lungmech rom build|solve``, ``lungmech register``,
``lungmech shape-modes``, ``lungmech shape``, ``lungmech phantom`` and ``lungmech info``."""

from __future__ import annotations

import argparse
import logging
import sys
from importlib import resources
from pathlib import Path

from lungmech.errors import LungmechError, ParameterError
from lungmech.registration import commands as registration

DEFAULT_SCENE = "lung_breathing.toml"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lungmech", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="solve a scene (the bundled default scene when none is given)")
    run.add_argument("scene", nargs="?", help="scene file (.toml)")
    _common(run)
    rom = commands.add_parser("rom", help="reduced-order models: build one from a scene, solve with one")
    actions = rom.add_subparsers(dest="action", required=True)
    build = actions.add_parser("build", help="build a reduced model from full-order runs of a scene")
    build.add_argument("scene", nargs="?", help="scene file (.toml; default: the bundled scene)")
    build.add_argument("-o", "--output", required=True, help="reduced model file (.npz)")
    build.add_argument("--basis", default="pod", help="pod, modal, modal+derivatives, polynomial or pod+modal")
    build.add_argument("--size", type=int, default=20, help="number of basis vectors, at most (modes, for modal+derivatives)")
    build.add_argument("--scales", default="0.5,1,1.5", type=_scales,
                       help="training load scales, comma-separated; one factor per load joined by ':' (e.g. 0.5:1,1.5:1)")
    build.add_argument("--inner", default="mass", help="inner product of the basis: mass, energy or l2")
    build.add_argument("--order", type=int, default=2, help="order of a polynomial basis")
    build.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")
    solve = actions.add_parser("solve", help="solve a scene with a reduced model (same outputs as run)")
    solve.add_argument("model", help="reduced model file (.npz) from 'lungmech rom build'")
    solve.add_argument("scene", nargs="?", help="scene file (default: the one the model was built from)")
    _common(solve)
    registration.add_commands(commands)
    commands.add_parser("info", help="versions, MPI size and available laws")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            return _info()
        if args.command in registration.COMMANDS:
            return registration.run(args)
        if args.command == "rom" and args.action == "build":
            return _rom_build(args)
        return _run(args)
    except LungmechError as error:
        print(f"lungmech: error: {error}", file=sys.stderr)
        return 2


def _common(command: argparse.ArgumentParser) -> None:
    command.add_argument("-o", "--output", default="results", help="output folder (replaced only on success)")
    command.add_argument("--scale", default=(1.0,), type=_scales, metavar="S",
                         help="scale the loads' change from the start (one factor, or one per load joined by ':')")
    command.add_argument("-q", "--quiet", action="store_true", help="no per-step progress")


def _scales(text: str) -> list:
    """'0.5,1' -> [0.5, 1.0]; '0.5:1,1.5:1' -> [(0.5, 1.0), (1.5, 1.0)]."""
    try:
        scales = [tuple(float(f) for f in item.split(":")) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    return [s[0] if len(s) == 1 else s for s in scales]


def _setup(args):
    """Logging on rank 0, and the scene named by ``args.scene`` (or the bundled one)."""
    from mpi4py import MPI

    from lungmech import scene as scenes

    comm = MPI.COMM_WORLD
    logging.basicConfig(
        level=logging.WARNING if args.quiet or comm.rank != 0 else logging.INFO,
        format="%(message)s",
        stream=sys.stdout,
    )
    if args.scene is None:
        with resources.as_file(resources.files("lungmech.scenes") / DEFAULT_SCENE) as path:
            return comm, scenes.load(path), f"bundled default scene ({DEFAULT_SCENE})", Path(path)
    return comm, scenes.load(args.scene), args.scene, Path(args.scene)


def _rom_build(args) -> int:
    from lungmech.rom.scene import build

    comm, scene, name, path = _setup(args)
    if comm.rank == 0:
        print(f"lungmech: building a {args.basis} reduced model of {name}", flush=True)
    summary = build(scene, args.output, kind=args.basis, size=args.size, scales=args.scales, inner=args.inner,
                    order=args.order, comm=comm, scene_path=path)
    if comm.rank == 0:
        seconds = ", ".join(f"{k} {v:.1f} s" for k, v in summary["offline_seconds"].items())
        print(f"lungmech: {summary['kind']} basis of {summary['size']} vectors on {summary['dofs']} dofs "
              f"({seconds}); saved to {Path(args.output).resolve()}")
    return 0


def _run(args) -> int:
    from lungmech.run import full_order, run

    prepare = full_order
    if args.command == "rom":  # solve: the scene the model was built from, unless another is named
        from lungmech.rom import store
        from lungmech.rom.scene import reduced_order

        if args.scene is None:
            args.scene = store.read(args.model)[0]["extra"].get("scene")
        prepare = reduced_order(args.model)
    comm, scene, name, _ = _setup(args)
    if len(args.scale) > 1:
        raise ParameterError("--scale takes one value (per-load factors are joined by ':', e.g. 1.2:1)")
    scale = args.scale[0]
    if comm.rank == 0:
        how = " with the reduced model " + args.model if args.command == "rom" else ""
        print(f"lungmech: running {name}{how}" + (f": {scene.title}" if scene.title else ""), flush=True)
    summary = run(scene, args.output, comm, scale=scale, prepare=prepare)
    if comm.rank == 0:
        print(
            f"lungmech: done in {summary['steps']} steps, {summary['newton_iterations']} Newton iterations "
            f"({summary['solver']}); volume {summary['reference_volume']:.6g} -> largest "
            f"{summary['largest_volume']['volume']:.6g} (t = {summary['largest_volume']['time']:.3g}) -> final "
            f"{summary['deformed_volume']:.6g}; outputs in {Path(args.output).resolve()}"
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
