"""``lungmech personalise --expiration EXP --inspiration INSP [--position P] [--scene SCENE] -o OUT``:
a patient's lung parameters from a pair of segmentations, or from several pairs in other
positions (the options repeated, in order: supine and prone together, say)
(:func:`lungmech.app.personalise.personalise`), written to ``OUT/report.json`` and summarised
in a few lines; ``--cohort FILE.csv``: many patients, one task of an ensemble each
(:mod:`lungmech.app.cohort`)."""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from lungmech.app.arguments import check_ensemble, ensemble_of, ensemble_options, image_label, setup
from lungmech.errors import ParameterError

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.app.patient_images import Reading
    from lungmech.app.personalise import Setting
    from lungmech.app.scene import Scene
    from lungmech.twin.displacement import Displacement

COMMANDS = ("personalise",)
DEFAULT_SCENE = "lung_personalise"


def add_commands(commands: argparse._SubParsersAction) -> None:
    """``personalise`` under ``commands``."""
    command = commands.add_parser(
        "personalise", help="estimate a lung's parameters from its end-expiration and end-inspiration segmentations"
    )
    command.add_argument(
        "--expiration",
        action="append",
        help="end-expiration segmentation (.nii, .nii.gz, .mha, .nrrd, .npz, or a folder of one DICOM series); "
        "repeated with --inspiration and --position for a pair in another position",
    )
    command.add_argument("--inspiration", action="append", help="end-inspiration segmentation, same formats")
    command.add_argument(
        "--position",
        action="append",
        choices=("supine", "upright", "prone"),
        help="the patient's position in each pair, in order (default supine)",
    )
    command.add_argument(
        "--displacement",
        action="append",
        help="a displacement field from end-expiration to end-inspiration computed elsewhere from the intensity "
        "images (a vector image: .nii, .nii.gz, .mha, .nrrd in ITK's LPS millimetres, or .npz), once per pair, as "
        "extra data inside the lung",
    )
    command.add_argument(
        "--displacement-smoothing",
        type=float,
        help="with --displacement: the length over which the field was smoothed, mm (its data are taken one per "
        "such length)",
    )
    command.add_argument(
        "--cohort",
        help="a CSV file of many patients (columns patient, expiration, inspiration[, position]; a patient's rows "
        "are its pairs), instead of --expiration and --inspiration",
    )
    command.add_argument(
        "--scene",
        help=f"the lung's physics and parameter box (default: --model's own, else the bundled {DEFAULT_SCENE})",
    )
    command.add_argument(
        "--estimate", help="the parameters to estimate, comma-separated (default: every one the position does not fix)"
    )
    command.add_argument(
        "--at", type=float, help="end-inspiration's time on the scene's load path, s (default: its end)"
    )
    command.add_argument(
        "--model",
        help="a reduced model file (lungmech trade's model.npz, lungmech rom build's, or a fitted lungmech pgd "
        "build's): the patient's model is built by its recipe (POD: basis size, training breaths, ECSW τ; PGD: most "
        "terms, training breaths) on its scene (or on --scene, of the same physics); "
        "a population's model (its scene names shape modes; rom build --probes surface) is used as it is, no model "
        "of the patient's own built: the patient's shape from the registration, projected on its modes",
    )
    command.add_argument(
        "--tolerance",
        type=float,
        help="the patient's model by the recipe lungmech trade measured on the bundled lung as the cheapest to meet "
        "this worst error on the volume (of the breath's volume change)",
    )
    command.add_argument(
        "--method",
        choices=("pod", "pgd"),
        help="the patient's model: pod (a POD basis, Galerkin or ECSW at --tau) or pgd (a PGD fitted to the training "
        "breaths, its breath and the lung's reference answered by evaluation; default pod)",
    )
    command.add_argument(
        "--size", type=int, help="basis size of the patient's reduced model, or a PGD's most terms (default 10; pgd 20)"
    )
    command.add_argument("--training", type=int, help="full breaths it is trained on (default 8; pgd 24)")
    command.add_argument(
        "--tau", help="its ECSW tolerance, or 'none' for a Galerkin model on the whole mesh (default 1e-4)"
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
    image_label(command, "lung")
    command.add_argument(
        "--lung",
        choices=("right", "left", "both"),
        help="the lung of segmentations that hold both (each lung a body, or by --label): one, or both with their "
        "parameters shared, each registered from the scene's lung of its side",
    )
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
    ensemble_options(command, "a cohort's patients", cache=False)  # (a patient's solves are not kept)


def run(args: argparse.Namespace) -> int:
    from lungmech import checks
    from lungmech.app.personalise import Setting
    from lungmech.app.population import is_population
    from lungmech.app.recipe import recipe_for, recipe_scene

    given = args.scene is not None
    args.scene = args.scene or DEFAULT_SCENE
    comm, scene, _, scene_path = setup(args)
    check_ensemble(args, comm)
    if args.model is not None and args.tolerance is not None:
        raise ParameterError("--model and --tolerance each give the patient's model its recipe: give one")
    for option, value in (("--model", args.model), ("--tolerance", args.tolerance)):
        if value is not None and any(v is not None for v in (args.method, args.size, args.training, args.tau)):
            raise ParameterError(
                f"{option} gives the patient's model its recipe (method, basis size, training, τ): leave out "
                "--method, --size, --training, --tau"
            )
    recipe: dict = {}
    if args.training is not None:
        recipe["training"] = checks.integer("--training", args.training, minimum=2)
    if args.size is not None:
        recipe["size"] = checks.integer("--size", args.size, minimum=1)
    if args.tau is not None:
        tau = None if str(args.tau).lower() == "none" else _number("--tau", args.tau)
        recipe["tau"] = None if tau is None else checks.real("--tau", tau, positive=True)
    if args.method == "pgd":
        if args.tau is not None:
            raise ParameterError("--tau is the ECSW tolerance of a POD model: a PGD (--method pgd) has none")
        recipe = {"training": 24, "size": 20, "tau": None} | recipe
    setting = Setting(
        method=args.method or "pod",
        estimate=tuple(name.strip() for name in args.estimate.split(",") if name.strip()) if args.estimate else (),
        inspiration=args.at,
        level=args.level,
        resamples=checks.integer("--resamples", args.resamples, minimum=0),
        mesh_check=not args.no_mesh_check,
        **recipe,
    )
    if args.tolerance is not None:
        chosen = recipe_for(checks.real("--tolerance", args.tolerance, positive=True))
        setting = replace(setting, size=chosen.size, training=chosen.training, tau=chosen.tau, recipe=chosen.source)
    if args.cohort is None and (args.group_size is not None or args.engine is not None):
        raise ParameterError("--group-size and --engine share out a cohort's patients: give --cohort")
    with (
        recipe_scene(args.model, scene if given else None, comm)
        if args.model
        else contextlib.nullcontext((None, scene))
    ) as (read, scene):
        population = read is not None and is_population(scene)
        if read is not None:
            setting = replace(
                setting, method=read.method, size=read.size, training=read.training, tau=read.tau, recipe=read.source
            )
        if args.cohort is not None:
            return _cohort(args, comm, scene_path if given or not args.model else None, setting)
        report = _one(args, comm, scene, setting, args.model if population else None)
    if comm.rank == 0:
        _say(report, args.output)
    return 0


def _one(args: argparse.Namespace, comm: MPI.Comm, scene: Scene, setting: Setting, population: str | None) -> dict:
    """One patient, from --expiration, --inspiration and --position (repeated, in order); on the
    ``population``'s model file as it is, if one is given, else on a model of the patient's own."""
    from lungmech.app import population as populations
    from lungmech.app.personalise import personalise

    expirations, inspirations = args.expiration or [], args.inspiration or []
    if not expirations or len(expirations) != len(inspirations):
        raise ParameterError(
            f"give --expiration and --inspiration once for each pair of images (got {len(expirations)} and "
            f"{len(inspirations)}), or --cohort"
        )
    positions = args.position or ["supine"] * len(expirations)
    if len(positions) != len(expirations):
        raise ParameterError(f"give --position once for each pair of images ({len(expirations)}; got {len(positions)})")
    fields = _displacements(args, len(expirations))
    reading = _reading(args)
    pairs = [
        pair for e, i, p, f in zip(expirations, inspirations, positions, fields) for pair in reading.pairs(e, i, p, f)
    ]
    if population is not None:
        return populations.personalise(population, scene, pairs, args.output, setting, comm)
    return personalise(scene, pairs, args.output, setting, comm)


def _reading(args: argparse.Namespace) -> Reading:
    from lungmech.app.patient_images import Reading

    return Reading(args.label, args.unit, args.lung)


def _displacements(args: argparse.Namespace, pairs: int) -> list[Displacement | None]:
    """The pairs' displacement fields (--displacement, once per pair, or none), with the
    smoothing --displacement-smoothing states (mm)."""
    from lungmech import checks
    from lungmech.registration.vectors import read_vectors
    from lungmech.twin.displacement import Displacement

    given = args.displacement or []
    if not given:
        if args.displacement_smoothing is not None:
            raise ParameterError(
                "--displacement-smoothing states a displacement field's smoothing: give --displacement"
            )
        return [None] * pairs
    if len(given) != pairs:
        raise ParameterError(f"give --displacement once for each pair of images ({pairs}; got {len(given)})")
    if args.displacement_smoothing is None:
        raise ParameterError(
            "--displacement needs --displacement-smoothing: the length (mm) over which the field was smoothed, "
            "over which its errors are alike"
        )
    smoothing = 1e-3 * checks.real("--displacement-smoothing", args.displacement_smoothing, positive=True)
    return [Displacement(read_vectors(path, unit=args.unit), smoothing) for path in given]


def _cohort(args: argparse.Namespace, comm: MPI.Comm, scene_path: Path | None, setting: Setting) -> int:
    """Every patient of --cohort, on the ensemble the options say; a line per patient."""
    from lungmech.app.cohort import cohort

    if args.expiration or args.inspiration or args.position or args.displacement:
        raise ParameterError(
            "--cohort names every patient's images: leave out --expiration, --inspiration, --position, --displacement"
        )
    with ensemble_of(args, comm) as ensemble:
        found = cohort(scene_path, args.cohort, args.output, setting, ensemble, comm, _reading(args), args.model)
    if comm.rank == 0:
        for row in found:
            if row.get("failed"):
                print(f"lungmech: {row['patient']}: failed: {row['failed']}")
                continue
            values = ", ".join(
                f"{name} = {p['value']:.4g}{'' if p['unit'] in ('', '1') else ' ' + p['unit']}"
                for name, p in row["parameters"].items()
            )
            print(f"lungmech: {row['patient']}: {values} ({row['seconds']:.0f} s)")
        print(f"lungmech: cohort of {len(found)} in {Path(args.output).resolve() / 'cohort.csv'}")
    return 1 if any(row.get("failed") for row in found) else 0


def _say(report: dict, output: str) -> None:
    """The estimate in a few lines."""
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
        f"report in {Path(output).resolve() / 'report.json'}"
    )


def _number(key: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ParameterError(f"{key} must be a number or 'none' (got {text!r})") from None
