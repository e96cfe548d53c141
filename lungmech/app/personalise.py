"""A patient's lung parameters from pairs of segmentations: what ``lungmech personalise`` does.

scene (its lung, physics and parameter box) + one or more pairs of end-expiration and
end-inspiration segmentations, each in a position (supine, prone, …) → for each pair
(:func:`prepare`, the offline step, timed apart):

1. **registration**: the scene's reference lung mapped onto the end-expiration segmentation
   (:func:`lungmech.registration.sobolev.register`); that mesh is the lung as imaged, posed as
   an imaged body (its unloaded reference found at every μ: the inverse motion);
2. **the pair's reduced model**: POD of ``training`` full breaths over the box (the
   position's parameters fixed), Galerkin or ECSW at τ — or a PGD fitted to them (the breath
   and the lung's reference ξ(μ): :mod:`lungmech.pgd.imaged`) —, its probes the surface nodes; checked at 3 further points against the full model, and that against the
   full model on the lung refined once (the mesh's own error): the model's error δr on each
   datum, signed, is the refined model's residual less the reduced one's;

then, every pair at once (:func:`estimated`):

3. **the estimate** (:mod:`lungmech.twin`): bounded least squares on the surface distances to
   the end-inspiration segmentations and their volumes, with the reduced models' exact
   sensitivities, the estimated parameters shared; the Laplace intervals in the parameters'
   box, widened by the model's error carried through the fit as a bias; the
   identifiability; a check by resampling;
4. **confirmation**: one full-order solve per pair at the estimate, its residual beside the
   reduced one's; the pictures (:mod:`lungmech.app.twin_pictures`).

The application talks to the models through ``solve(μ)`` only.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from mpi4py import MPI

import dolfinx
import numpy as np

from lungmech.app import personalise_report, twin_pictures
from lungmech.app.output import write_json
from lungmech.app.run import build_model, full_order_model
from lungmech.app.scene import Scene, build_geometry
from lungmech.errors import ImageError, ParameterError
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.placement import Image as Placement
from lungmech.mesh import nodes
from lungmech.mesh.refine import refined
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.pgd.fitted import fitted
from lungmech.pgd.fitting import FIT
from lungmech.pgd.model import PGDModel
from lungmech.registration import metrics
from lungmech.registration import side as sides
from lungmech.registration.image import Image
from lungmech.registration.sobolev import Options, register
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet
from lungmech.twin.displacement import Displacement, interior_points
from lungmech.twin.fit import Fit, Interior, View, estimate
from lungmech.twin.model_error import model_error
from lungmech.twin.surface import surface_data, surface_nodes
from lungmech.twin.synthetic import surface_noise
from lungmech.twin.uncertainty import laplace, resampled

__all__ = [
    "POSITIONS",
    "Pair",
    "Patient",
    "Preparation",
    "Setting",
    "check_pair",
    "checked_request",
    "estimated",
    "personalise",
    "position_values",
    "prepare",
]

POSITIONS = {"supine": -90.0, "upright": 0.0, "prone": 90.0}  # the weight's pitch (deg) in each position


@dataclass(frozen=True)
class Pair:
    """One pair of a patient's segmentations, end-expiration and end-inspiration, taken in one
    ``position`` (supine, upright or prone); with a ``displacement`` field between them,
    computed elsewhere from the intensity images (:mod:`lungmech.twin.displacement`); ``side``:
    the lung they hold, "right" or "left" (its reference, the scene's lung of that side), or
    None for the scene's own lung."""

    expiration: Image
    inspiration: Image
    position: str = "supine"
    displacement: Displacement | None = None
    side: str | None = None

    def name(self, pairs: Sequence[Pair]) -> str:
        """Its name among ``pairs``: the position (and the side), numbered when not unique."""
        base = self.position if self.side is None else f"{self.position}-{self.side}"
        alike = [p for p in pairs if (p.position, p.side) == (self.position, self.side)]
        return base if len(alike) == 1 else f"{base}-{next(k for k, p in enumerate(alike) if p is self) + 1}"


@dataclass(frozen=True)
class Setting:
    """How to personalise: ``estimate`` (parameter names; default: every parameter no pair's
    position fixes), ``inspiration`` (s, the path's time of end-inspiration; default: the
    path's end), ``training`` breaths and basis ``size`` of each pair's model, ``tau`` (ECSW;
    None: Galerkin), ``method`` "pod" (those) or "pgd" (a PGD fitted to the breaths, at most
    ``size`` terms), ``level`` of the intervals, ``resamples`` of the check, ``seed``;
    ``mesh_check``: the model error also holds the mesh's own, the full model's against the same
    lung refined once at the 3 check points (8 times the unknowns); ``full_fit``: also fit the full
    model on the same mesh to the same images (from the estimate), whose distance from the
    truth is the discretisation's gap (twin experiments; minutes, not seconds); ``noise``
    (twin experiments): Gaussian noise added to every surface datum, its standard deviation
    this fraction of the RMS of the surface's observed motion (seeded by ``seed``); ``recipe``:
    where the recipe ``training``, ``size`` and ``tau`` came from (a model file, a trade's
    measured recipe for a tolerance), for the report."""

    estimate: tuple[str, ...] = ()
    inspiration: float | None = None
    training: int = 8
    size: int = 10
    tau: float | None = 1e-4
    level: float = 0.95
    resamples: int = 20
    seed: int = 0
    full_fit: bool = False
    mesh_check: bool = True
    noise: float = 0.0
    recipe: str | None = None
    method: str = "pod"


@dataclass(frozen=True)
class Patient:
    """A patient made ready for estimates (:func:`prepare`): per pair, the ``views`` of its
    reduced model and of its full model on the same mesh (``full_views``), the model's error
    on each datum at each check point (``errors``: points × rows, m; every pair at the same
    points), each check point's numbers (``checked``) and registration summary
    (``registered``); the ``estimated`` parameters' names, the ``box``, the offline
    ``seconds``, each reduced model's basis size and each pair's end-inspiration segmentation
    (``inspirations``, for the pictures)."""

    box: Parameters
    estimated: tuple[str, ...]
    views: tuple[View, ...]
    full_views: tuple[View, ...]
    errors: np.ndarray
    checked: tuple[dict, ...]
    registered: tuple[dict, ...]
    seconds: dict[str, float]
    basis_sizes: tuple[int, ...]
    inspirations: tuple[Image, ...] = ()

    def fit(self, full: bool = False) -> Fit:
        """The least-squares problem of every pair, on the reduced models (or the full ones)."""
        return Fit(self.full_views if full else self.views, self.estimated)

    def weighed(self, residual: np.ndarray) -> Patient:
        """The patient with each pair's interior data weighed by ω = σ_surface / σ_interior, the
        noise of each as ``residual`` (this patient's, at an estimate) shows it; its model
        errors too."""
        fit = self.fit()
        surface = np.concatenate([np.append(residual[rows], residual[rows[-1] + 1]) for rows in fit.surface_rows()])
        noise = float(np.sqrt(np.mean(surface**2)))
        weights: list[float | None] = []
        errors = self.errors.copy()
        for view, rows in zip(self.views, fit.interior_rows()):
            if view.interior is None:
                weights.append(None)
                continue
            own = float(np.sqrt(np.mean((residual[rows] / view.interior.weight) ** 2)))
            weight = noise / own if own > 0 else 1.0
            weights.append(weight)
            errors[:, rows] *= weight / view.interior.weight

        def weigh(views: tuple[View, ...]) -> tuple[View, ...]:
            return tuple(
                view if w is None or view.interior is None else replace(view, interior=replace(view.interior, weight=w))
                for view, w in zip(views, weights)
            )

        return replace(
            self,
            views=weigh(self.views),
            full_views=weigh(self.full_views),
            errors=errors,
        )


def personalise(
    scene: Scene,
    pairs: Sequence[Pair],
    out: str | Path,
    setting: Setting = Setting(),
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Estimate ``scene``'s parameters from the segmentations of ``pairs`` (see the module's
    doc); write ``report.json`` into the folder ``out`` (replaced only on success) and return
    the report. Collective."""
    pairs = tuple(pairs)
    names, end = checked_request(scene, pairs, setting)
    inputs = [image.source for p in pairs for image in (p.expiration, p.inspiration) if image.source is not None]
    with output_folder(out, comm, inputs=inputs, command="lungmech personalise") as staging:
        patient = prepare(scene, pairs, setting, comm, names, end)
        report = estimated(patient, setting, staging, comm)
        hold_signals_until_swap()
        write_json(staging / "report.json", report, comm)
    return report


@dataclass
class Preparation:
    """What :func:`prepare` gathers pair by pair, made a :class:`Patient` at the end: each
    pair's views and its model's error at the check points, and the offline seconds."""

    box: Parameters
    estimated: tuple[str, ...]
    views: list[View] = field(default_factory=list)
    full_views: list[View] = field(default_factory=list)
    errors: list[np.ndarray] = field(default_factory=list)
    checked: list[dict] = field(default_factory=list)
    registered: list[dict] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=lambda: {"registration": 0.0, "offline": 0.0, "check": 0.0})

    def check(self, name: str, chain: Sequence[View], points: Sequence[dict], started: float) -> None:
        """Pair ``name``'s ``chain`` of views (its reduced model, its full model, then any
        finer) kept, and the model's error at ``points`` (:func:`lungmech.twin.model_error`);
        the check's time counted from ``started`` (``time.perf_counter``). Collective."""
        error, found = model_error(list(chain), list(points))
        self.views.append(chain[0])
        self.full_views.append(chain[1])
        self.errors.append(error)
        self.checked.extend({"pair": name} | point for point in found)
        self.seconds["check"] += time.perf_counter() - started

    def patient(self, basis_sizes: Sequence[int], inspirations: Sequence[Image]) -> Patient:
        """The patient these pairs make (their reduced models' ``basis_sizes``, their
        end-inspiration segmentations)."""
        return Patient(
            self.box,
            self.estimated,
            tuple(self.views),
            tuple(self.full_views),
            np.hstack(self.errors),
            tuple(self.checked),
            tuple(self.registered),
            self.seconds,
            tuple(basis_sizes),
            tuple(inspirations),
        )


def prepare(
    scene: Scene,
    pairs: Sequence[Pair],
    setting: Setting = Setting(),
    comm: MPI.Comm = MPI.COMM_WORLD,
    estimated: Sequence[str] | None = None,
    end: float | None = None,
) -> Patient:
    """Each pair's registration, reduced model and its check (the steps 1–2 of the module's
    doc). Collective."""
    if estimated is None or end is None:
        estimated, end = checked_request(scene, tuple(pairs), setting)
    box = Parameters(scene.parameters)
    gathered = Preparation(box, tuple(estimated))
    seconds = gathered.seconds
    # the check points: the estimated parameters drawn in their box (the others at their
    # defaults, as the estimate leaves them), the same for every pair
    checks = [{name: point[name] for name in estimated} for point in box.sample(3, setting.seed + 1)]
    sizes: list[int] = []
    for pair in pairs:
        name = pair.name(pairs)
        fixed = position_values(scene, pair.position)
        tic = time.perf_counter()
        geometry = build_geometry(lung_geometry(scene, pair.side), comm)
        if pair.side is not None and (found := sides.of_mesh(geometry.mesh).side) not in (None, pair.side):
            raise ParameterError(
                f"personalise: pair {name} holds a {pair.side} lung; the scene's lung is a {found} one"
            )
        registration = register(geometry.mesh, pair.expiration, Options())
        nodes.move_nodes(registration.displacement)  # the lung as imaged at end-expiration
        gathered.registered.append(
            {"pair": name} | metrics.report(geometry.mesh, pair.expiration) | registration.summary()
        )
        seconds["registration"] += time.perf_counter() - tic

        tic = time.perf_counter()
        model = build_model(scene, comm, geometry=geometry, image=Placement.motion(scene.stepping.start))
        surface = surface_nodes(geometry.mesh)
        interior = _interior(pair.displacement, geometry.mesh)
        inside = np.zeros((0, 3)) if interior is None else interior.points
        probes = np.vstack([surface.points, inside]).tolist()
        full = full_order_model(scene, comm, start="inverse_motion", model=model, probes=probes)
        reduced = _reduced(full, setting, fixed, probes)
        sizes.append(reduced.size)
        seconds["offline"] += time.perf_counter() - tic

        data, baseline = surface_data(pair.inspiration), surface_data(pair.expiration)
        tic = time.perf_counter()
        chain = [
            View(reduced, surface, data, end, fixed, name, baseline, interior),
            View(full, surface, data, end, fixed, name, baseline, interior),
        ]
        if setting.mesh_check:  # the mesh's own error: the same lung refined once
            finer = build_model(
                scene, comm, geometry=refined(geometry).geometry, image=Placement.motion(scene.stepping.start)
            )
            finest = full_order_model(scene, comm, start="inverse_motion", model=finer, probes=probes)
            chain.append(View(finest, surface, data, end, fixed, name, baseline, interior))
        gathered.check(name, chain, [point | fixed for point in checks], tic)
    return gathered.patient(sizes, [pair.inspiration for pair in pairs])


def _reduced(full: FullOrderModel, setting: Setting, fixed: dict[str, float], probes: list) -> ReducedModel | PGDModel:
    """A pair's model of ``full`` by ``setting``, trained on breaths with the position's ``fixed``
    values, probing ``probes`` (collective)."""
    if setting.method == "pgd":
        options = replace(FIT, max_terms=setting.size)
        return fitted(full, setting.training, None, options, probes, setting.seed, fixed=fixed)[0]
    box = full.model.parameters
    training = [box.values(dict(point) | fixed) for point in box.sample(setting.training, setting.seed)]
    with Reductor(full, POD(setting.size), TrainingSet(training)) as reductor:
        return reductor.reduce(None if setting.tau is None else ECSW(setting.tau))


def estimated(
    patient: Patient, setting: Setting = Setting(), pictures: Path | None = None, comm: MPI.Comm = MPI.COMM_WORLD
) -> dict:
    """The estimate, its uncertainty and its confirmation (steps 3–4 of the module's doc), as
    the report's plain values with their units; with a folder for ``pictures``, each pair's
    fitted surface and P–V curve with its band drawn there
    (:mod:`lungmech.app.twin_pictures`). Collective."""
    seconds = dict(patient.seconds)
    fit = patient.fit()
    offset = surface_noise(fit, setting.noise, setting.seed) if setting.noise else None
    found = estimate(fit, offset=offset)
    seconds["estimate"] = found.seconds
    if any(view.interior is not None for view in patient.views):  # again, each datum weighed by its noise
        patient = patient.weighed(found.residual)
        fit = patient.fit()
        found = estimate(fit, start=found.values, offset=offset)
        seconds["estimate"] += found.seconds
    tic = time.perf_counter()
    uncertainty = laplace(found, fit, patient.errors, setting.level, setting.seed)
    draws = (
        resampled(fit, found, setting.resamples, setting.seed) if setting.resamples else np.zeros((0, len(fit.names)))
    )
    seconds["uncertainty"] = time.perf_counter() - tic

    tic = time.perf_counter()
    confirm = patient.fit(full=True)
    full_residual = confirm.residual(found.unit) + found.offset
    seconds["confirmation"] = time.perf_counter() - tic
    full_values = estimate(confirm, start=found.values, offset=offset).values if setting.full_fit else None

    report = personalise_report.report(patient, fit, found, uncertainty, draws, full_residual, seconds)
    report["model"] = {
        "method": setting.method,
        "basis_sizes": list(patient.basis_sizes),
        "tau": setting.tau if setting.method == "pod" else None,
        "training": setting.training,
        "recipe_from": setting.recipe,
    }
    report["data_noise"] = setting.noise
    report["full_order_estimate"] = full_values
    if pictures is not None:
        tic = time.perf_counter()
        report["pictures"] = twin_pictures.pictures(
            fit, found, uncertainty.intervals, Path(pictures), comm, patient.full_views, patient.inspirations
        )
        seconds["pictures"] = time.perf_counter() - tic
    return report


def _interior(displacement: Displacement | None, mesh: dolfinx.mesh.Mesh) -> Interior | None:
    """A displacement field's data on the lung as imaged: at its interior vertices, one per
    smoothing length (weighed later, by its noise)."""
    if displacement is None:
        return None
    points = interior_points(mesh, displacement.smoothing)
    if len(points) == 0:
        raise ParameterError(
            f"the displacement field's smoothing, {1e3 * displacement.smoothing:g} mm, leaves no interior point of the "
            "lung as meshed: it is as coarse as the lung"
        )
    return Interior(points, displacement.field.at(points), smoothing=displacement.smoothing)


def checked_request(scene: Scene, pairs: tuple[Pair, ...], setting: Setting) -> tuple[tuple[str, ...], float]:
    """The estimated names and end-inspiration's time, or one line on what cannot be asked."""
    if not pairs:
        raise ParameterError("personalise: give at least one pair of segmentations")
    fixed = [position_values(scene, pair.position) for pair in pairs]
    box = Parameters(scene.parameters)
    names = setting.estimate or tuple(p.name for p in box if not any(p.name in f for f in fixed))
    for name in names:
        box.named(name)
    if not names:
        raise ParameterError("personalise: the scene has no parameter to estimate (give it [parameters])")
    if scene.inverse is None:
        raise ParameterError(
            "personalise: the scene must pose the imaged lung ([inverse]): the image is its loaded state"
        )
    if len({pair.side for pair in pairs} - {None}) > 1 and scene.geometry.get("builder") != "lung_phantom":
        raise ParameterError(
            "personalise: the right and the left lung each need a reference lung of their side, and the scene's "
            "lung comes from a file: give --lung right or --lung left, with a scene of that lung"
        )
    end = float(scene.stepping.end) if setting.inspiration is None else float(setting.inspiration)
    if not scene.stepping.start < end <= scene.stepping.end:
        raise ParameterError(
            f"personalise: end-inspiration at {end:g} s lies outside the scene's load path "
            f"({scene.stepping.start:g}, {scene.stepping.end:g}] s"
        )
    if not 0 <= setting.noise < 10:
        raise ParameterError(
            f"personalise: the data noise is a fraction of the surface's motion in [0, 10) (got {setting.noise})"
        )
    if setting.method not in ("pod", "pgd"):
        raise ParameterError(f"personalise: the patient's model is made by 'pod' or 'pgd' (got {setting.method!r})")
    if setting.method == "pgd" and setting.training < 8:
        raise ParameterError(
            f"personalise: a PGD is fitted to at least 8 training breaths (got {setting.training}): give --training"
        )
    for pair in pairs:
        check_pair(pair.expiration, pair.inspiration, pair.side or scene.geometry.get("side"))
    return tuple(names), end


def check_pair(expiration: Image, inspiration: Image, side: str | None) -> None:
    """Refuse, in one line naming the image, a pair that cannot be one lung breathing in: an
    image whose header does not orient it in the patient, images whose physical extents do not
    overlap, an end-inspiration lung smaller than the end-expiration one, a lung of the other
    side than the scene's (where the image's header tells its side)."""
    names = {
        "expiration": _name(expiration, "the end-expiration image"),
        "inspiration": _name(inspiration, "the end-inspiration image"),
    }
    images = {"expiration": expiration, "inspiration": inspiration}
    for which, image in images.items():
        if not image.oriented:
            raise ImageError(
                f"{names[which]} has no orientation in its header (NIfTI sform and qform codes 0): where the lung "
                "lies in the patient, and so the weight's direction, cannot be read"
            )
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
    for which, image in images.items():
        found = sides.of_image(image).side
        if side is not None and found is not None and found != side:
            raise ImageError(f"{names[which]} holds a {found} lung; the scene's lung is a {side} one")


def lung_geometry(scene: Scene, side: str | None) -> dict:
    """The scene's geometry table for the lung of ``side`` (None: the scene's own): a
    generated lung (builder "lung_phantom") of that side; a lung from a file as it is (its
    side is checked on its mesh)."""
    table = dict(scene.geometry)
    return table | {"side": side} if side is not None and table.get("builder") == "lung_phantom" else table


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
