"""``lungmech personalise --expiration EXP --inspiration INSP [--scene SCENE] -o OUT``: a
patient's lung parameters from a pair of segmentations (:func:`lungmech.app.personalise.personalise`),
written to ``OUT/report.json`` and summarised in a few lines."""

from __future__ import annotations

import argparse
from pathlib import Path

from lungmech.app.arguments import setup
from lungmech.errors import ParameterError

COMMANDS = ("personalise",)
DEFAULT_SCENE = "lung_personalise"


def add_commands(commands: argparse._SubParsersAction) -> None:
    """``personalise`` under ``commands``."""
    command = commands.add_parser(
        "personalise", help="estimate a lung's parameters from its end-expiration and end-inspiration segmentations"
    )
    command.add_argument(
        "--expiration", required=True, help="end-expiration segmentation (.nii, .nii.gz, .mha, .nrrd, .npz)"
    )
    command.add_argument("--inspiration", required=True, help="end-inspiration segmentation, same formats")
    command.add_argument(
        "--scene",
        default=DEFAULT_SCENE,
        help=f"the lung's physics and parameter box (default: the bundled {DEFAULT_SCENE})",
    )
    command.add_argument(
        "--estimate", help="the parameters to estimate, comma-separated (default: every one the position does not fix)"
    )
    command.add_argument(
        "--position",
        default="supine",
        choices=("supine", "upright", "prone"),
        help="the patient's position in both images",
    )
    command.add_argument(
        "--at", type=float, help="end-inspiration's time on the scene's load path, s (default: its end)"
    )
    command.add_argument("--size", type=int, default=10, help="basis size of the patient's reduced model (default 10)")
    command.add_argument("--training", type=int, default=8, help="full breaths it is trained on (default 8)")
    command.add_argument(
        "--tau",
        default="1e-4",
        help="its ECSW tolerance, or 'none' for a Galerkin model on the whole mesh (default 1e-4)",
    )
    command.add_argument("--level", type=float, default=0.95, help="the intervals' level (default 0.95)")
    command.add_argument(
        "--resamples", type=int, default=20, help="estimates under resampled noise, the intervals' check (default 20)"
    )
    command.add_argument(
        "--no-mesh-check",
        action="store_true",
        help="leave the mesh's own error out of the intervals (checked by default: the full model against the "
        "lung refined once at 3 points, 8 times the unknowns)",
    )
    command.add_argument("--label", type=int, help="label of the lung in multi-label segmentations")
    command.add_argument(
        "--unit", choices=("mm", "m"), help="length unit of the images' headers (default: from the header)"
    )
    command.add_argument(
        "-o",
        "--output",
        default="results/personalised",
        help="output folder (default results/personalised); replaced only on success",
    )
    command.add_argument("-q", "--quiet", action="store_true", help="no progress")


def run(args: argparse.Namespace) -> int:
    from lungmech import checks
    from lungmech.app.personalise import Setting, personalise
    from lungmech.registration import image

    args.scene = args.scene or DEFAULT_SCENE
    comm, scene, _, _ = setup(args)
    tau = None if str(args.tau).lower() == "none" else checks.real("--tau", _number("--tau", args.tau), positive=True)
    setting = Setting(
        estimate=tuple(name.strip() for name in args.estimate.split(",") if name.strip()) if args.estimate else (),
        position=args.position,
        inspiration=args.at,
        training=checks.integer("--training", args.training, minimum=2),
        size=checks.integer("--size", args.size, minimum=1),
        tau=tau,
        level=args.level,
        resamples=checks.integer("--resamples", args.resamples, minimum=0),
        mesh_check=not args.no_mesh_check,
    )
    expiration = image.read(args.expiration, label=args.label, unit=args.unit)
    inspiration = image.read(args.inspiration, label=args.label, unit=args.unit)
    report = personalise(scene, expiration, inspiration, args.output, setting, comm)
    if comm.rank == 0:
        for name, found in report["parameters"].items():
            unit = "" if found["unit"] in ("", "1") else f" {found['unit']}"
            interval = found["interval"]
            said = (
                f"{100 * report['level']:.0f} % interval [{interval[0]:.4g}, {interval[1]:.4g}]{unit}"
                + (f" ({found['note']})" if found["note"] else "")
                if interval
                else found["note"]
            )
            print(f"lungmech: {name} = {found['value']:.4g}{unit}, {said}")
        for direction in report["directions"]:
            if direction["weak"]:
                print(
                    f"lungmech: the images cannot determine {direction['text']} (standard deviation "
                    f"{direction['deviation_unit_box']:.2f} of the range)"
                )
        fit, seconds = report["fit"], report["seconds"]
        print(
            f"lungmech: surface fitted to {1e3 * fit['surface_rms']:.2f} mm RMS (full order at the estimate: "
            f"{1e3 * fit['full_order_surface_rms']:.2f} mm); estimate {seconds['estimate']:.1f} s after an offline "
            f"step of {seconds['offline']:.0f} s and a registration of {seconds['registration']:.0f} s; "
            f"report in {Path(args.output).resolve() / 'report.json'}"
        )
    return 0


def _number(key: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ParameterError(f"{key} must be a number or 'none' (got {text!r})") from None
