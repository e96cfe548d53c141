"""A patient's lung parameters from a pair of segmentations: what ``lungmech personalise`` does.

scene (its lung, physics and parameter box) + the end-expiration and end-inspiration
segmentations →

1. **registration**: the scene's reference lung mapped onto the end-expiration segmentation
   (:func:`lungmech.registration.sobolev.register`); that mesh is the lung as imaged, posed as
   an imaged body (its unloaded reference found at every μ: the inverse motion);
2. **the patient's reduced model** (the offline step, timed apart): POD of ``training`` full
   breaths over the box (the position's parameters fixed), Galerkin or ECSW at τ, its probes the
   registered lung's surface nodes; checked at 3 further points against the full model, and
   that against the full model on the lung refined once (the mesh's own error): their sum is
   ε, the model's error on each datum;
3. **the estimate** (:mod:`lungmech.twin`): bounded least squares on the surface distances to
   the end-inspiration segmentation and its volume, with the reduced model's exact
   sensitivities; the Laplace intervals widened by ε as a bias; the identifiability; a check
   by resampling;
4. **confirmation**: one full-order solve at the estimate, its residual beside the reduced one's.

The application talks to the models through ``solve(μ)`` only.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

import numpy as np

from lungmech.app.output import write_json
from lungmech.app.run import build_model, full_order_model
from lungmech.app.scene import Scene, build_geometry
from lungmech.errors import ImageError, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import ParametricModel
from lungmech.fem.placement import Image as Placement
from lungmech.mesh import nodes
from lungmech.mesh.refine import refined
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.registration import metrics
from lungmech.registration import side as sides
from lungmech.registration.image import Image
from lungmech.registration.sobolev import Options, register
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet
from lungmech.twin.fit import Estimate, Fit, View, estimate
from lungmech.twin.surface import surface_data, surface_nodes
from lungmech.twin.uncertainty import Uncertainty, laplace, resampled

__all__ = ["POSITIONS", "Setting", "check_pair", "personalise", "position_values"]

POSITIONS = {"supine": -90.0, "upright": 0.0, "prone": 90.0}  # the weight's pitch (deg) in each position


@dataclass(frozen=True)
class Setting:
    """How to personalise: ``estimate`` (parameter names; default: every parameter the position
    does not fix), ``position`` (fixes a gravity pitch parameter, if the scene has one),
    ``inspiration`` (s, the path's time of end-inspiration; default: the path's end),
    ``training`` breaths and basis ``size`` of the patient's reduced model, ``tau`` (ECSW; None:
    Galerkin), ``level`` of the intervals, ``resamples`` of the check, ``seed``;
    ``mesh_check``: ε also holds the mesh's own error, the full model's against the same lung
    refined once at the 3 check points (8 times the unknowns); ``full_fit``:
    also fit the full model on the same mesh to the same images (from the estimate), whose
    distance from the truth is the discretisation's gap (twin experiments; minutes, not
    seconds)."""

    estimate: tuple[str, ...] = ()
    position: str = "supine"
    inspiration: float | None = None
    training: int = 8
    size: int = 10
    tau: float | None = 1e-4
    level: float = 0.95
    resamples: int = 20
    seed: int = 0
    full_fit: bool = False
    mesh_check: bool = True


def personalise(
    scene: Scene,
    expiration: Image,
    inspiration: Image,
    out: str | Path,
    setting: Setting = Setting(),
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Estimate ``scene``'s parameters from the segmentations ``expiration`` and ``inspiration``
    (see the module's doc); write ``report.json`` into the folder ``out`` (replaced only on
    success) and return the report. Collective."""
    fixed = position_values(scene, setting.position)
    box = Parameters(scene.parameters)
    names = setting.estimate or tuple(p.name for p in box if p.name not in fixed)
    for name in names:
        box.named(name)
    if not names:
        raise ParameterError("personalise: the scene has no parameter to estimate (give it [parameters])")
    if scene.inverse is None:
        raise ParameterError(
            "personalise: the scene must pose the imaged lung ([inverse]): the image is its loaded state"
        )
    end = float(scene.stepping.end) if setting.inspiration is None else float(setting.inspiration)
    if not scene.stepping.start < end <= scene.stepping.end:
        raise ParameterError(
            f"personalise: end-inspiration at {end:g} s lies outside the scene's load path "
            f"({scene.stepping.start:g}, {scene.stepping.end:g}] s"
        )
    check_pair(expiration, inspiration, scene.geometry.get("side"))
    seconds: dict[str, float] = {}
    inputs = [image.source for image in (expiration, inspiration) if image.source is not None]
    with output_folder(out, comm, inputs=inputs, command="lungmech personalise") as staging:
        tic = time.perf_counter()
        geometry = build_geometry(scene.geometry, comm)
        registration = register(geometry.mesh, expiration, Options())
        nodes.move_nodes(registration.displacement)  # the lung as imaged at end-expiration
        registered = metrics.report(geometry.mesh, expiration) | registration.summary()
        seconds["registration"] = time.perf_counter() - tic

        tic = time.perf_counter()
        model = build_model(scene, comm, geometry=geometry, image=Placement.motion(scene.stepping.start))
        surface = surface_nodes(geometry.mesh)
        full = full_order_model(scene, comm, start="inverse_motion", model=model, probes=surface.points.tolist())
        training = [box.values(dict(point) | fixed) for point in box.sample(setting.training, setting.seed)]
        with Reductor(full, POD(setting.size), TrainingSet(training)) as reductor:
            reduced = reductor.reduce(None if setting.tau is None else ECSW(setting.tau))
        seconds["offline"] = time.perf_counter() - tic

        data = surface_data(inspiration)
        checks = [box.values(dict(point) | fixed) for point in box.sample(3, setting.seed + 1)]
        tic = time.perf_counter()
        chain: list[ParametricModel] = [reduced, full]
        if setting.mesh_check:  # the mesh's own error: the same lung refined once
            finer = build_model(
                scene, comm, geometry=refined(geometry).geometry, image=Placement.motion(scene.stepping.start)
            )
            chain.append(
                full_order_model(scene, comm, start="inverse_motion", model=finer, probes=surface.points.tolist())
            )
        error, checked = model_error(chain, checks, end, surface.area)
        seconds["check"] = time.perf_counter() - tic

        baseline = surface_data(expiration)
        view = View(reduced, surface, data, end, fixed, setting.position, baseline)
        fit = Fit([view], names)
        found = estimate(fit)
        seconds["estimate"] = found.seconds
        tic = time.perf_counter()
        uncertainty = laplace(found, fit, error, setting.level)
        draws = (
            resampled(fit, found, setting.resamples, setting.seed) if setting.resamples else np.zeros((0, len(names)))
        )
        seconds["uncertainty"] = time.perf_counter() - tic

        tic = time.perf_counter()
        confirm = Fit([View(full, surface, data, end, fixed, setting.position, baseline)], names)
        full_residual = confirm.residual(found.unit)
        seconds["confirmation"] = time.perf_counter() - tic
        full_values = estimate(confirm, start=found.values).values if setting.full_fit else None

        report = _report(box, names, fixed, found, uncertainty, draws, full_residual, checked, registered, seconds)
        report["model"] = {"basis_size": reduced.size, "tau": setting.tau, "training": setting.training}
        report["full_order_estimate"] = full_values
        hold_signals_until_swap()
        write_json(staging / "report.json", report, comm)
    return report


def check_pair(expiration: Image, inspiration: Image, side: str | None) -> None:
    """Refuse, in one line naming the image, a pair that cannot be one lung breathing in: images
    whose physical extents do not overlap, an end-inspiration lung smaller than the
    end-expiration one, a lung of the other side than the scene's (where the image's header
    tells its side)."""
    names = {
        "expiration": _name(expiration, "the end-expiration image"),
        "inspiration": _name(inspiration, "the end-inspiration image"),
    }
    (low, high), (other_low, other_high) = expiration.bounds(), inspiration.bounds()
    if np.any(high < other_low) or np.any(other_high < low):
        raise ImageError(
            f"{names['expiration']} and {names['inspiration']} do not overlap in space (their boxes span "
            "[{}] and [{}] m): check their origins and orientations".format(
                ", ".join(f"{a:.3f}..{b:.3f}" for a, b in zip(low, high)),
                ", ".join(f"{a:.3f}..{b:.3f}" for a, b in zip(other_low, other_high)),
            )
        )
    volumes = [image.mask.sum() * image.voxel_volume for image in (expiration, inspiration)]
    if volumes[1] <= volumes[0]:
        raise ImageError(
            f"{names['inspiration']} holds {1e3 * volumes[1]:.3f} L, no more than {names['expiration']}'s "
            f"{1e3 * volumes[0]:.3f} L: the images are swapped, or not one lung breathing in"
        )
    for which, image in (("expiration", expiration), ("inspiration", inspiration)):
        found = sides.of_image(image).side
        if side is not None and found is not None and found != side:
            raise ImageError(f"{names[which]} holds a {found} lung; the scene's lung is a {side} one")


def _name(image: Image, default: str) -> str:
    return f"'{Path(image.source).name}'" if image.source is not None else default


def position_values(scene: Scene, position: str) -> dict[str, float]:
    """The parameters a position fixes: a parameter on a gravity load's pitch, at the position's
    angle (none if the scene has no such parameter: then only "supine", its own, is accepted)."""
    if position not in POSITIONS:
        raise ParameterError(f"--position must be one of {', '.join(POSITIONS)} (got {position!r})")
    pitched = [p for p in scene.parameters if p.target.endswith(".pitch")]
    if not pitched:
        if position != "supine":
            raise ParameterError(
                f"personalise: position {position} needs a parameter on the weight's pitch (loads.<gravity>.pitch), "
                "which this scene does not have"
            )
        return {}
    angle = POSITIONS[position]
    for p in pitched:
        p.check(angle, f"its pitch in position {position}")
    return {p.name: angle for p in pitched}


def model_error(
    chain: Sequence[ParametricModel], points: Sequence[Mapping[str, float]], end: float, area: float
) -> tuple[np.ndarray, list[dict]]:
    """ε per datum (m) of the first model of ``chain`` against the truth, bounded by the chain's
    steps (the reduced model against the full one on its mesh, that against the full model on
    a finer mesh: the error of reduction and the mesh's own): over ``points``, the largest sum
    of each step's difference in each surface node's motion to ``end`` and in the volume
    change's mean offset (ΔV / ``area``); and each point's worst numbers per step."""
    start = chain[0].stepping.start
    worst: np.ndarray | None = None
    checked = []
    for point in points:
        answers = [model.solve(point, times=[start, end]) for model in chain]
        motions = [np.asarray(a.outputs["probes"])[1] - np.asarray(a.outputs["probes"])[0] for a in answers]
        changes = [float(a.outputs["volume"][1] - a.outputs["volume"][0]) for a in answers]
        row = np.zeros(len(motions[0]) + 1)
        steps = []
        for k in range(len(chain) - 1):
            node = np.linalg.norm(motions[k] - motions[k + 1], axis=1)
            volume = abs(changes[k] - changes[k + 1]) / area
            row += np.append(node, volume)
            steps.append({"motion_error_max": float(node.max()), "volume_offset": volume})
        worst = row if worst is None else np.maximum(worst, row)
        checked.append({"parameters": dict(point), "steps": steps})
    assert worst is not None  # (three points)
    return worst, checked


def _report(
    box: Parameters,
    names: Sequence[str],
    fixed: Mapping[str, float],
    found: Estimate,
    uncertainty: Uncertainty,
    draws: np.ndarray,
    full_residual: np.ndarray,
    checked: list[dict],
    registered: dict,
    seconds: dict[str, float],
) -> dict:
    """The report's plain values, each with its unit."""
    parameters = {}
    spread = draws.std(axis=0, ddof=1) if len(draws) > 1 else np.full(len(names), np.nan)
    deviation = np.sqrt(np.diag(uncertainty.covariance))
    for i, name in enumerate(names):
        interval = uncertainty.intervals[name]
        parameters[name] = {
            "value": found.values[name],
            "unit": box.named(name).unit or "1",
            "interval": None if interval.low is None else [interval.low, interval.high],
            "note": interval.reason,
            "at_bound": found.active[name],
            "deviation_unit_box": float(deviation[i]),
            "resampled_deviation_unit_box": float(spread[i]),
            "model_bias_unit_box": float(interval.bias),
        }
    residual = found.residual
    return {
        "parameters": parameters,
        "fixed": dict(fixed),
        "level": uncertainty.level,
        "noise_sigma": uncertainty.sigma,
        "correlation": np.asarray(uncertainty.correlation).tolist(),
        "directions": [
            {"combination": d.combination, "deviation_unit_box": d.deviation, "weak": d.weak, "text": d.text()}
            for d in uncertainty.directions
        ],
        "fit": {
            "surface_rms": float(np.sqrt(np.mean(residual[:-1] ** 2))),
            "surface_max": float(np.abs(residual[:-1]).max()),
            "volume_offset": float(residual[-1]),
            "full_order_surface_rms": float(np.sqrt(np.mean(full_residual[:-1] ** 2))),
            "full_order_volume_offset": float(full_residual[-1]),
            "evaluations": found.evaluations,
            "message": found.message,
            "history": found.history,
        },
        "model_check": checked,
        "registration": registered,
        "seconds": seconds,
        "units": UNITS,
    }


UNITS = {
    "value": "the parameter's unit",
    "interval": "the parameter's unit",
    "deviation_unit_box": "1 (fraction of the parameter's range, log range on a log scale)",
    "noise_sigma": "m",
    "surface_rms": "m",
    "surface_max": "m",
    "volume_offset": "m (volume mismatch over the surface area)",
    "motion_error_max": "m",
    "cost": "m^2",
    "seconds": "s",
}
