"""The registration commands of the CLI: ``register``, ``shape-modes``, ``shape`` and ``phantom``."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import TYPE_CHECKING

from lungmech.app.arguments import image_label
from lungmech.app.console import litres
from lungmech.errors import ParameterError
from lungmech.parallel import on_root
from lungmech.parallel.destination import output_file

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.registration.sobolev import Options

COMMANDS = ("register", "shape-modes", "shape", "phantom")


def add_commands(commands: argparse._SubParsersAction) -> None:
    register = commands.add_parser("register", help="map a reference mesh onto a segmented 3-D image")
    register.add_argument(
        "image", help="segmentation (.nii, .nii.gz, .mha, .nrrd, .npz, or a folder of one DICOM series)"
    )
    _reference(register, default=None)
    register.add_argument(
        "--side",
        choices=("right", "left"),
        help="the lung's side, where the image cannot tell it (no orientation in its header, unclear shape); "
        "by default it is read from the image, and the bundled phantom of that side is the reference",
    )
    register.add_argument(
        "--accept-other-side",
        action="store_true",
        help="register with a reference (or --side) of the other side than the image's lung (refused by default)",
    )
    register.add_argument(
        "-o",
        "--output",
        help="output folder (default results/<image name>-registration); replaced only on "
        "success, and only if it is empty or lungmech's own",
    )
    _image_options(register)
    _descent_options(register)

    modes = commands.add_parser("shape-modes", help="register a reference onto many images and build shape modes")
    modes.add_argument("images", nargs="*", help="image files or folders of images")
    _reference(modes, default=None)
    modes.add_argument(
        "--accept-other-side",
        action="store_true",
        help="register images whose lung is of the other side than the reference's (refused by default)",
    )
    modes.add_argument(
        "-o",
        "--output",
        default="results/shape_modes",
        help="output folder (default "
        "results/shape_modes); replaced only on success, and only if it is empty or lungmech's own",
    )
    modes.add_argument(
        "--keep-size",
        action="store_true",
        help="keep each lung's size as a change of shape (remove only its position and orientation): modes for a "
        "model over a population ([geometry] shape_modes)",
    )
    modes.add_argument("--synthetic", type=int, metavar="N", help="use N synthetic patients instead of images")
    modes.add_argument("--latent", type=int, default=2, help="latent shape parameters of the synthetic cohort (1-5)")
    modes.add_argument("--seed", type=int, default=0, help="random seed of the synthetic cohort")
    modes.add_argument("--spacing", type=float, default=2.5, help="voxel size of the synthetic images, mm")
    modes.add_argument(
        "--side",
        choices=("right", "left"),
        default="right",
        help="lung of the synthetic cohort (right); the default reference is the phantom of the images' side",
    )
    _image_options(modes)
    _descent_options(modes)

    shape = commands.add_parser("shape", help="a new geometry from shape-mode coefficients")
    shape.add_argument("modes", help="shape modes (.npz) from 'lungmech shape-modes'")
    _reference(shape)
    shape.add_argument("-c", "--coefficients", required=True, help="comma-separated, in standard deviations")
    shape.add_argument(
        "-o",
        "--output",
        required=True,
        help="mesh file to write: .vtu (meshio, pyvista, ParaView) or .xdmf (DOLFINx); use it as [geometry] file",
    )

    phantom = commands.add_parser("phantom", help="write a synthetic lung segmentation")
    phantom.add_argument("-o", "--output", required=True, help="image file (.nii.gz, .nii, .npz, .mha, .nrrd)")
    phantom.add_argument("--side", choices=("right", "left"), default="right")
    phantom.add_argument("--spacing", type=float, default=2.0, help="voxel size, mm")
    for name in ("height", "width", "depth"):
        phantom.add_argument(f"--{name}", type=float, help=f"{name}, m")
    for name in ("dome", "apex", "mediastinal", "notch"):
        phantom.add_argument(f"--{name}", type=float, help=f"shape fraction '{name}' (see LungShape)")


def _reference(command: argparse.ArgumentParser, default: str | None = "lung_phantom_right") -> None:
    shown = f"{default} (default)" if default else "lung_phantom_right"
    command.add_argument(
        "--reference",
        default=default,
        type=_mesh,
        help="reference mesh (.msh, .vtu or .xdmf), or a bundled one by name: "
        f"{shown}, lung_phantom_left" + ("" if default else "; default: the phantom of the image's lung's side"),
    )


def _mesh(text: str) -> str:
    from lungmech.meshes import locate

    return str(locate(text))


def _image_options(command: argparse.ArgumentParser) -> None:
    image_label(command, "organ")
    command.add_argument(
        "--unit", choices=("mm", "m"), help="length unit of the image header (default: from the header)"
    )
    command.add_argument("-q", "--quiet", action="store_true", help="no progress")


def _descent_options(command: argparse.ArgumentParser) -> None:
    command.add_argument("--stages", help="image smoothings in voxels, coarse to fine, comma-separated (default 2,1)")
    command.add_argument("--image-function", choices=("distance", "binary"), default="distance")
    command.add_argument("--min-jacobian", type=float, default=0.25, help="reject steps making det F smaller")
    command.add_argument("--max-iterations", type=int, default=200, help="per stage")
    command.add_argument(
        "--accept-unconverged",
        action="store_true",
        help="keep a registration whose descent did not converge (refused by default)",
    )
    command.add_argument(
        "--accept-implausible",
        action="store_true",
        help="register a target whose size is far from the reference's (refused by default: "
        "the image's length unit is likely wrong)",
    )


def run(args: argparse.Namespace) -> int:
    import logging
    import sys

    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    logging.basicConfig(
        level=logging.WARNING if getattr(args, "quiet", False) or comm.rank else logging.INFO,
        format="%(message)s",
        stream=sys.stdout,
        force=True,
    )
    return {"register": _register, "shape-modes": _shape_modes, "shape": _shape, "phantom": _phantom}[args.command](
        args, comm
    )


def _accepted(args: argparse.Namespace) -> tuple[str, ...]:
    doubts = ("unconverged", "implausible", "other side")
    return tuple(doubt for doubt in doubts if getattr(args, f"accept_{doubt.replace(' ', '_')}", False))


def _options(args: argparse.Namespace) -> Options:
    from lungmech.registration.sobolev import Options

    settings = {
        "image_function": args.image_function,
        "min_jacobian": args.min_jacobian,
        "max_iterations": args.max_iterations,
    }
    if args.stages:
        try:
            settings["stages"] = tuple(float(s) for s in args.stages.split(","))
        except ValueError:
            raise ParameterError(f"--stages: not a list of numbers: {args.stages!r}") from None
    return Options(**settings)


def _register(args: argparse.Namespace, comm: MPI.Comm) -> int:
    from lungmech.app import registration as workflow
    from lungmech.registration import image

    options = _options(args)
    target = image.read(args.image, label=args.label, unit=args.unit)
    output = args.output if args.output is not None else f"results/{image.stem(Path(args.image))}-registration"
    reference, decided = workflow.choose_reference(target, args.reference, args.side, args.accept_other_side, comm)
    report = workflow.register_image(reference, target, output, options, comm, _accepted(args), decided)
    if comm.rank == 0:
        converged = "yes" if report["converged"] else "no (kept: --accept-unconverged)"
        print(
            f"lungmech: registered {reference} onto {args.image} ({decided['lung']} lung) in {report['iterations']} iterations "
            f"({report['total_seconds']:.1f} s), converged: {converged}; Dice {report['dice']:.4f}, mean surface "
            f"distance {1e3 * report['mean_surface_distance']:.2f} mm ({report['mean_surface_distance_voxels']:.2f} "
            f"voxels), hd95 {1e3 * report['hd95']:.2f} mm, min det F {report['min_det_F']:.3f}; "
            f"outputs in {Path(output).resolve()}"
        )
    return 0


def _shape_modes(args: argparse.Namespace, comm: MPI.Comm) -> int:
    from lungmech.app import registration as workflow
    from lungmech.registration import phantom

    options = _options(args)
    if (args.synthetic is None) == (not args.images):
        raise ParameterError("give either image files/folders or --synthetic N (one of the two)")
    if args.synthetic is not None:
        if not (math.isfinite(args.spacing) and args.spacing > 0):
            raise ParameterError(f"--spacing must be a positive voxel size in mm (got {args.spacing})")
        cohort = phantom.cohort(args.synthetic, args.latent, seed=args.seed, side=args.side)
        sources = {f"patient_{j:03d}": im for j, im in enumerate(cohort.images(spacing=1e-3 * args.spacing))}
    else:
        sources = workflow.read_images(args.images, label=args.label, unit=args.unit)
    reference = args.reference
    if reference is None:  # the phantom of the cohort's side: the synthetic one's, or the first image's
        first = next(iter(sources.values()))
        side = args.side if args.synthetic is not None else None
        reference, _ = workflow.choose_reference(first, None, side, "other side" in _accepted(args), comm)
    pose = "rigid" if args.keep_size else "similarity"
    report = workflow.build_shape_modes(
        reference, sources, args.output, options, comm, accept=_accepted(args), pose=pose
    )
    if comm.rank == 0:
        worst = report["worst"]
        compact = report["compactness"]
        unconverged = [m["name"] for m in report["members"] if not m["converged"]]
        converged = "yes" if not unconverged else f"no for {', '.join(unconverged)} (kept: --accept-unconverged)"
        print(
            f"lungmech: {report['images']} mappings, converged: {converged} (worst Dice {worst['dice']:.4f}, "
            f"min det F {worst['min_det_F']:.3f}) -> {len(compact)} shape modes; the first "
            f"{min(3, len(compact))} capture "
            + ", ".join(f"{100 * c:.1f} %" for c in compact[:3])
            + f" of the variance; outputs in {Path(args.output).resolve()}"
        )
    return 0


def _shape(args: argparse.Namespace, comm: MPI.Comm) -> int:
    from lungmech import mesh as geometry
    from lungmech.registration.library import ShapeModes

    try:
        coefficients = [float(c) for c in args.coefficients.split(",")]
    except ValueError:
        raise ParameterError(f"--coefficients: not a list of numbers: {args.coefficients!r}") from None
    if Path(args.output).suffix not in (".vtu", ".xdmf"):
        raise ParameterError(f"-o {args.output}: a shape is written as a .vtu or .xdmf mesh (e.g. -o new_lung.vtu)")
    inputs = [args.modes, args.reference, *geometry.companions(args.reference)]
    with output_file(
        args.output,
        comm,
        inputs=inputs,
        ours=geometry.is_lungmech_mesh,
        companions=[p.name for p in geometry.companions(args.output)],
    ) as path:
        modes = ShapeModes.load(args.modes)
        new = modes.geometry(geometry.from_file(args.reference, comm, dimension=3), coefficients)
        geometry.write(new, path)
        volume = new.volume()  # collective
    if comm.rank == 0:
        print(
            f"lungmech: shape {coefficients} (standard deviations) written to {Path(args.output).resolve()} "
            f"(volume {litres(volume)})"
        )
    return 0


def _phantom(args: argparse.Namespace, comm: MPI.Comm) -> int:
    from lungmech.mesh.lung_shape import LungShape
    from lungmech.registration import image, phantom

    image.kind(Path(args.output))  # a bad suffix fails on every rank, before any work
    fields = {f.name for f in dataclasses.fields(LungShape)}
    given = {k: v for k, v in vars(args).items() if k in fields and v is not None}
    if not (math.isfinite(args.spacing) and args.spacing > 0):
        raise ParameterError(f"--spacing must be a positive voxel size in mm (got {args.spacing})")
    with output_file(
        args.output, comm, ours=image.written_by_lungmech, companions=image.companions(args.output)
    ) as path:
        shape = LungShape(**given)
        target = phantom.voxelise(shape, 1e-3 * args.spacing)
        on_root(comm, lambda: image.write(target, path))
    if comm.rank == 0:
        print(
            f"lungmech: {shape.side} lung phantom, {target.shape} voxels of {args.spacing} mm, "
            f"volume {litres(target.volume)} -> {Path(args.output).resolve()}"
        )
    return 0
