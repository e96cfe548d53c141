"""The reductor: a full-order model and a recipe in, a :class:`~lungmech.rom.reduced.ReducedModel` out.

In pyMOR's manner, one call makes every reduced model lungmech has::

    reduced = reduce(full, POD(20), TrainingSet(points, scales), hyper=ECSW(1e-3, size=5))

* the **basis** recipe: :class:`POD` of the full model's load paths at the training points and
  load scales (every accepted state of the approach to μ and of the path, minus the start),
  :class:`Modal` (the lowest modes of K y = λ M y at the start, with their modal derivatives on
  request), :class:`Polynomial` (monomials of the coordinates), or :class:`Enriched` (several of
  these, re-orthonormalised), truncated to its ``size``;
* the **training**: parameter points (a Sobol' sample of the box, :meth:`~lungmech.fem.
  parameters.Parameters.sample`) × load scales, or with ``tolerance`` a weak greedy over those
  points as candidates (:mod:`lungmech.rom.greedy`) until the error indicator meets it;
* an optional **hyper-reduction** :class:`ECSW`: a sample of cells trained on every Newton iterate
  of the training solves for the basis and its enrichment, at τ (``tolerance``; a greedy judges
  at ``judge`` and the last sample is re-sampled at τ from the same iterates), the basis then
  truncated to ``size`` vectors (the sample stays the one of the whole basis).

:func:`reduce` is one :class:`Reductor`'s one model. The :class:`Reductor` keeps the offline
work — the training, the basis and the ECSW training of its Newton iterates — so that models at
several τ and basis sizes, and the Galerkin one, come from one training without solving the
full model again.

The inner product of the bases is the energy one by default (the tangent at rest on the
constrained space, :func:`~lungmech.rom.basis.inner_product`), in which the tolerance, the
indicator and the errors are measured; where it is not positive definite the build is refused
in one line naming ``mass``. The reduced model starts where the full one starts at the default
parameters (its start must be one state: :func:`~lungmech.fem.start.one_state`), says so in its
answers, and carries what it was built from (:attr:`ReducedModel.built`). Collective.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import FullOrderModel
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.start import Equilibrium, Rest, StartReport
from lungmech.rom import ecsw, imaged, indicator, load_paths
from lungmech.rom.accuracy import Errors, errors
from lungmech.rom.basis import INNER_PRODUCTS, Basis, enrich, require_positive_definite
from lungmech.rom.greedy import Greedy, greedy
from lungmech.rom.imaged import ReducedImage
from lungmech.rom.load_paths import Paths
from lungmech.rom.modes import modal_basis, with_modal_derivatives
from lungmech.rom.pod import pod
from lungmech.rom.polynomial import polynomial_basis
from lungmech.rom.reduced import ReducedModel

__all__ = ["ECSW", "Enriched", "Errors", "Modal", "POD", "Polynomial", "Reductor", "TrainingSet", "errors", "reduce"]


def _size(size: object) -> int:
    if isinstance(size, bool) or not (isinstance(size, int | np.integer) and size >= 1):
        raise ParameterError(f"basis size must be a positive integer (got {size!r})")
    return int(size)


@dataclass(frozen=True)
class POD:
    """The POD of the training load paths, at most ``size`` vectors (fewer when the snapshots have
    fewer directions above the noise)."""

    size: int = 20
    kind = "pod"

    def __post_init__(self) -> None:
        _size(self.size)


@dataclass(frozen=True)
class Modal:
    """The ``size`` lowest modes of K y = λ M y at the start (``density`` in kg/m³ scales M only),
    with their static modal derivatives when ``derivatives``."""

    size: int = 20
    density: float = 1.0
    derivatives: bool = False

    def __post_init__(self) -> None:
        _size(self.size)
        checks.real("density", self.density)

    @property
    def kind(self) -> str:
        return "modal+derivatives" if self.derivatives else "modal"


@dataclass(frozen=True)
class Polynomial:
    """Monomials of the coordinates up to ``order`` for every component, at most ``size``."""

    order: int = 2
    size: int = 20
    kind = "polynomial"

    def __post_init__(self) -> None:
        _size(self.size)


@dataclass(frozen=True)
class Enriched:
    """The bases of ``parts`` in order, re-orthonormalised, at most ``size`` vectors."""

    parts: tuple = (POD(), Modal())
    size: int = 20
    kind = "enriched"

    def __post_init__(self) -> None:
        _size(self.size)
        if not self.parts or not all(isinstance(part, POD | Modal | Polynomial) for part in self.parts):
            raise ParameterError("an enriched basis is made of POD, Modal and Polynomial parts")


Recipe = POD | Modal | Polynomial | Enriched


@dataclass(frozen=True)
class TrainingSet:
    """Where the full model is solved: each parameter point (a mapping of names to values, the
    others at their defaults) at each load scale (a factor on the loads' change from the start,
    or one per load). With ``tolerance`` (a relative energy-norm error), the points are a
    greedy's candidates instead, at the scene's loads, and ``batch`` of them solved at each of
    its rounds (together, where the training's paths are solved by an ensemble)."""

    points: Sequence[Mapping[str, float]] = ({},)
    scales: Sequence[float | Sequence[float]] = (1.0,)
    tolerance: float | None = None
    batch: int = 1

    def __post_init__(self) -> None:
        if not self.points:
            raise ParameterError("give at least one training parameter point")
        if not self.scales:
            raise ParameterError("give at least one training load scale")
        if self.tolerance is not None:
            checks.real("tolerance", self.tolerance)
            if not 0 < self.tolerance < 1:
                raise ParameterError(
                    f"the tolerance (a relative energy-norm error) must lie in (0, 1) (got {self.tolerance!r})"
                )
            if list(self.scales) != [1.0]:
                raise ParameterError(
                    "a greedy training trains at the scene's loads over its [parameters] box; put a load's "
                    "amplitude in [parameters] instead of giving load scales"
                )
        checks.integer("greedy batch", self.batch, minimum=1)
        if self.batch > 1 and self.tolerance is None:
            raise ParameterError("a batch is the full solves of a greedy's round: give a tolerance")


@dataclass(frozen=True)
class ECSW:
    """Hyper-reduction by energy-conserving sampling at τ = ``tolerance``; ``judge``: the τ a
    greedy judges its rounds at (default τ); ``size``: the basis truncated to these many vectors
    after the sample was trained on the whole."""

    tolerance: float = 1e-4
    judge: float | None = None
    size: int | None = None

    def __post_init__(self) -> None:
        for name in ("tolerance", "judge"):
            value = getattr(self, name)
            if value is not None:
                checks.real(f"ECSW {name}", value)
                if not 0 < value < 1:
                    raise ParameterError(f"the ECSW {name} must lie in (0, 1) (got {value!r})")
        if self.size is not None:
            _size(self.size)


class Reductor:
    """The offline work of a reduction, done once and kept; each :meth:`reduce` makes a reduced
    model of it (pyMOR's ``reductor.reduce``)::

        with Reductor(full, POD(), TrainingSet(candidates, tolerance=1e-3), judge=1e-4) as reductor:
            galerkin = reductor.reduce()
            fast = {tau: reductor.reduce(ECSW(tau, size=5)) for tau in (1e-3, 1e-4, 1e-5)}

    On construction: the training solves (or the greedy over the candidates, judging its
    rounds' hyper-reduced models at τ = ``judge`` when given) and the basis by the ``basis``
    recipe, in the ``inner`` product ("energy", "mass" or "l2") — or, ``basis`` a trained
    :class:`~lungmech.rom.greedy.Greedy` (one kept from an earlier run, say), its basis,
    training points, inner product and judging τ, the other arguments unused. On the first hyper-reduced
    model: the ECSW training on the basis and its enrichment, from the greedy's Newton
    iterates or from a second pass of the training solves; every τ is then an NNLS on it
    alone, and every truncation is free — the full model is not solved again. ``paths``: where
    the training's full solves run (:data:`~lungmech.rom.load_paths.Paths`; default: one after
    another on ``full``; an ensemble's: :mod:`lungmech.app.training_paths`). ``timings``
    holds the seconds of each part so far. Collective; the kept ECSW training is freed on
    leaving the block (or by :meth:`destroy`).
    """

    def __init__(
        self,
        full: FullOrderModel,
        basis: Recipe | Greedy = POD(),
        training: TrainingSet = TrainingSet(),
        inner: str = "energy",
        judge: float | None = None,
        paths: Paths | None = None,
    ) -> None:
        if isinstance(basis, Greedy):  # trained already: its own training, inner product and τ
            training = TrainingSet(basis.training, tolerance=basis.tolerance)
            inner, judge = basis.basis.inner_product, basis.sample.tolerance if basis.sample is not None else None
        if inner not in INNER_PRODUCTS:
            raise ParameterError(f"inner product must be one of {', '.join(INNER_PRODUCTS)} (got {inner!r})")
        if training.tolerance is not None and not isinstance(basis, POD | Greedy):
            raise ParameterError(f"a greedy training (a tolerance) trains a POD basis (got a {basis.kind} basis)")
        if training.tolerance is not None and not len(full.parameters):
            raise ParameterError(
                "a greedy training trains over the model's parameter box, and this model has none: add parameters "
                "(e.g. a load amplitude), or give a basis size"
            )
        if judge is not None:
            ECSW(judge)  # its checks
        self.full, self.training, self.inner, self.judge = full, training, inner, judge
        self.kind = "pod" if isinstance(basis, Greedy) else basis.kind
        model = full.model
        self.imaged = isinstance(full.start, InverseMotion)  # two unknowns: ξ(μ), then the breath
        if self.imaged and (training.tolerance is not None or not isinstance(basis, POD)):
            raise ParameterError(
                "an imaged body's reduced model is trained on POD bases of given size (its greedy is not built yet)"
            )
        # refused before any work where there is none
        self.start = load_paths.relative_to(full)
        self.paths = paths or load_paths.serial(full, self.start)  # where the training's full solves run
        require_positive_definite(model, inner)
        self.timings: dict[str, float] = {}
        self.full_solves = 0  # of the full model, so far: a model's offline cost beside its seconds
        self.modes: Basis | None = None  # every POD direction: the basis leads them, the enrichment follows
        self.trained: Greedy | None = basis if isinstance(basis, Greedy) else None
        self.points = [full.parameters.values(p) for p in training.points]
        self._runs = [(point, scale) for point in self.points for scale in training.scales]
        if self.trained is None and training.tolerance is not None:
            assert isinstance(basis, POD)  # (a greedy trains a POD basis: refused above otherwise)
            tic = time.perf_counter()
            self.trained = greedy(
                full,
                self.points,
                training.tolerance,
                size=basis.size,
                inner=inner,
                timings=self.timings,
                hyper=judge,
                batch=training.batch,
                paths=self.paths,
            )
            self.timings["greedy"] = time.perf_counter() - tic
        elif self.imaged:
            assert isinstance(basis, POD)  # (refused above otherwise)
            self.basis = self._imaged_bases(basis.size)
        elif self.trained is None:
            assert not isinstance(basis, Greedy)  # (a Greedy is trained already)
            self.basis = _basis(full, basis, self._runs, inner, self)
        if self.trained is not None:  # trained here or before: its full solves are the model's cost
            self.full_solves += len(self.trained.training)
            self.modes, self.points = self.trained.modes, self.trained.training
            self._runs = [(point, 1.0) for point in self.points]
            self.basis = self.trained.basis
        self.enrichment = indicator.enrichment(self.basis, self.modes if self.basis.kind == "pod" else None)
        self._ecsw: ecsw.Training | None = None  # of [V W], made on the first hyper-reduced model
        self._samples: dict[float, tuple[ecsw.Sample, float]] = {}  # τ: (its sample, the NNLS's seconds)
        self._images: dict[float | None, ReducedImage] = {}  # an imaged body's reduced inverse motion, per τ
        self._inverse_ecsw: ecsw.Training | None = None  # and its ECSW training, made with the breath's
        self._rest()

    def _imaged_bases(self, size: int) -> Basis:
        """An imaged body's two bases from one pass of the training solves: the breath's (returned;
        its every POD direction in :attr:`modes`) and the inverse motion's (:attr:`inverse_basis`,
        relative to its solution at the defaults, :attr:`inverse_start`)."""
        full, tic = self.full, time.perf_counter()
        assert isinstance(full.start, InverseMotion)  # (self.imaged)
        trained = imaged.snapshots(full, self._runs, self.paths)
        self.timings["snapshots"] = time.perf_counter() - tic
        self.full_solves += len(self._runs)
        tic = time.perf_counter()
        self.modes, self.inverse_basis, self.inverse_known = imaged.bases(full, trained, self._runs, self.inner, size)
        self.start, self.inverse_start = trained.start, trained.inverse_start
        self.timings["svd"] = time.perf_counter() - tic
        return self.modes.truncate(min(size, self.modes.size))

    def _reduced_image(self, tolerance: float | None) -> ReducedImage:
        """The reduced inverse motion a reduced model of an imaged body starts from: Galerkin, or
        hyper-reduced at τ = ``tolerance`` (its sample from the same ECSW training pass as the
        breath's). Made once per τ."""
        if tolerance not in self._images:
            start = self.full.start
            assert isinstance(start, InverseMotion)  # (self.imaged)
            sample = None
            if tolerance is not None:
                self._ecsw_training()
                assert self._inverse_ecsw is not None  # (made with the breath's)
                sample = self._inverse_ecsw.sample(tolerance)
            options = self.full.solver.options
            self._images[tolerance] = ReducedImage(
                self.full.model, self.inverse_basis, self.inverse_start, options, start.body, sample, self.inverse_known
            )
        return self._images[tolerance]

    def __enter__(self) -> Reductor:
        return self

    def __exit__(self, *exception: object) -> None:
        self.destroy()

    def destroy(self) -> None:
        """Free the kept ECSW training (collective)."""
        for training in (self._ecsw, self._inverse_ecsw):
            if training is not None:
                training.destroy()
        self._ecsw = self._inverse_ecsw = None

    def reduce(self, hyper: ECSW | None = None, size: int | None = None) -> ReducedModel:
        """The reduced model on the basis (Galerkin: its forms on the full mesh), or with
        ``hyper`` hyper-reduced at its τ; truncated to the leading ``size`` vectors (a
        hyper-reduction's own ``size``; its sample stays the one of the whole basis and its
        enrichment): the model a smaller POD would give, its indicator's enrichment made anew.
        Collective."""
        vectors, enrichment = self.basis, self.enrichment
        sample, seconds = self.sample(hyper.tolerance) if hyper is not None else (None, None)
        size = hyper.size if hyper is not None else (None if size is None else _size(size))
        if size is not None and size < vectors.size:
            vectors = vectors.truncate(size)
            enrichment = indicator.enrichment(vectors, self.modes)
            if hyper is not None:  # as wide as the one the sample was trained on, with the basis
                enrichment = enrichment[:, : self.enrichment.shape[1]]
        full, start = self.full, self.full.start
        self._rest()
        image, described = None, None
        if self.imaged:
            image = self._reduced_image(hyper.tolerance if hyper is not None else None)
        else:
            assert isinstance(start, Rest | Equilibrium)  # (one_state refused the others on construction)
            described = StartReport(start.kind, start.description, details=dict(start.details))
        reduced = ReducedModel(
            full.model,
            vectors,
            full.stepping,
            full.solver.options,
            self.start,
            full.outputs.probe or (),
            self.points,
            sample,
            enrichment,
            described,
            image=image,
        )
        judge = self.judge or (hyper.tolerance if hyper is not None else None)
        reduced.built = {
            "basis": self.kind,
            "inner": self.inner,
            "scales": [np.asarray(s, dtype=float).tolist() for s in self.training.scales],
            "training": self.points,
            "greedy": _greedy_record(self.trained, self.training.tolerance, full.parameters),
            "hyper": None if hyper is None else {"method": "ecsw", "tolerance": hyper.tolerance, "judge": judge},
            "timings": self.timings | ({} if seconds is None else {"nnls": seconds}),
            "full_solves": self.full_solves,
        }
        return reduced

    def sample(self, tolerance: float) -> tuple[ecsw.Sample, float]:
        """The ECSW sample of [V W] at τ = ``tolerance`` and the seconds its NNLS took (0 when
        it is the greedy's own, judged at that τ); each τ is made once. Collective."""
        ECSW(tolerance)  # its checks
        if tolerance not in self._samples:
            trained = self.trained
            if trained is not None and trained.sample is not None and self.judge == tolerance:
                self._samples[tolerance] = (trained.sample, 0.0)
            else:
                training = self._ecsw_training()
                tic = time.perf_counter()
                self._samples[tolerance] = (training.sample(tolerance), time.perf_counter() - tic)
                self._rest()
        return self._samples[tolerance]

    def _ecsw_training(self) -> ecsw.Training:
        """G of ECSW on [V W], from the greedy's Newton iterates or a second pass of the
        training solves watched (made once)."""
        if self._ecsw is None:
            full, tic = self.full, time.perf_counter()
            training = ecsw.Training(full.model, np.hstack([self.basis.vectors, self.enrichment]))
            try:
                if self.imaged:  # the breath's and the inverse motion's, from one pass
                    self._inverse_ecsw = imaged.ecsw_training(full, training, self.inverse_basis, self._runs)
                    self.timings["ecsw_training"] = time.perf_counter() - tic
                    self.full_solves += len(self._runs)
                elif self.trained is not None:
                    training.replay(self.trained.iterates)
                    self.timings["ecsw_replay"] = time.perf_counter() - tic
                else:
                    with training.watching(cast(NewtonSolver, full.solver)):  # (ECSW watches a full Newton solver)
                        load_paths.collected(full, self._runs)
                    self.timings["ecsw_training"] = time.perf_counter() - tic
                    self.full_solves += len(self._runs)
            except BaseException:
                training.destroy()
                raise
            self.timings |= {f"ecsw_{part}": seconds for part, seconds in training.seconds.items()}
            self._ecsw = training
        return self._ecsw

    def _rest(self) -> None:
        """The full model back at its start: the defaults, the start time."""
        self.full.reset()
        self.full.model.set_time(self.full.stepping.start)


def reduce(
    full: FullOrderModel,
    basis: Recipe = POD(),
    training: TrainingSet = TrainingSet(),
    hyper: ECSW | None = None,
    inner: str = "energy",
    timings: dict[str, float] | None = None,
) -> ReducedModel:
    """The reduced model of ``full`` by the ``basis`` recipe, trained by ``training``, optionally
    hyper-reduced (see the module's doc): one :class:`Reductor`'s one model, a greedy judging at
    ``hyper.judge`` (default: its τ). ``inner``: the bases' inner product ("energy", "mass" or
    "l2"). ``timings`` receives the seconds of each part. Collective."""
    judge = None if hyper is None else hyper.judge or hyper.tolerance
    with Reductor(full, basis, training, inner, judge) as reductor:
        reduced = reductor.reduce(hyper)
    if timings is not None:
        timings.update(reduced.built["timings"])
    return reduced


def _basis(full: FullOrderModel, recipe: Recipe, runs: list, inner: str, made: Reductor) -> Basis:
    """The basis of ``recipe`` (the POD part's modes kept in ``made.modes``)."""
    model = full.model
    parts = recipe.parts if isinstance(recipe, Enriched) else (recipe,)
    bases = []
    for part in parts:
        tic = time.perf_counter()
        if isinstance(part, POD):
            data = np.hstack([path.snapshots for path in made.paths(runs, False)])
            made._rest()
            made.timings["snapshots"] = time.perf_counter() - tic
            made.full_solves += len(runs)
            tic = time.perf_counter()
            made.modes = pod(model, data, inner=inner, source={"training": made.points})
            bases.append(made.modes.truncate(min(part.size, made.modes.size)))
            made.timings["svd"] = time.perf_counter() - tic
        else:
            full.reset()  # modes and monomials at the start state, at the defaults
            model.set_time(full.stepping.start)
            if isinstance(part, Modal):
                modes = modal_basis(model, part.size, density=part.density)
                bases.append(with_modal_derivatives(model, modes) if part.derivatives else modes)
                made.timings["eigensolve"] = time.perf_counter() - tic
            else:
                found = polynomial_basis(model, part.order, inner=inner)
                bases.append(found.truncate(min(part.size, found.size)))
                made.timings["basis"] = time.perf_counter() - tic
    combined = enrich(model, *bases, inner=inner) if len(bases) > 1 else bases[0]
    if isinstance(recipe, Modal) and recipe.derivatives:
        return combined  # every mode and derivative pair: its size counts the modes
    return combined.truncate(min(recipe.size, combined.size))


def _greedy_record(trained: Greedy | None, tolerance: float | None, parameters: Parameters) -> dict | None:
    """What a greedy training did, as plain values (an indicator of inf — the reduced solve
    failed there — as None)."""
    if trained is None:
        return None
    return {
        "tolerance": tolerance,
        "batch": trained.batch,
        "met": trained.met,
        "safety": trained.safety,
        "full_solves": len(trained.training),
        "rounds": [
            {
                "size": r.size,
                "point": r.point,
                "where": parameters.text(r.point),
                "indicator": r.indicator if np.isfinite(r.indicator) else None,
                "error": r.error,
            }
            for r in trained.rounds
        ],
    }
