"""A reduced model is a model: ``solve(μ)`` in k unknowns, with the outputs of the full one.

A :class:`ReducedModel` holds a basis V of the state space (orthonormal in the energy or mass
inner product), the start state x₀ the basis is relative to, the load path and the parameters it
was trained over. Its states are x = x₀(t, μ) + V q; each load step solves the Galerkin equations
Vᵀ R(x₀ + V q; μ) = 0 by Newton's method in q (:class:`~lungmech.rom.galerkin.ReducedSolver`).
It answers :meth:`solve` with the same :class:`~lungmech.fem.parametric.Solution` as
:class:`~lungmech.fem.parametric.FullOrderModel` — outputs at the same output times, its states
being the coordinates q — so the two can be swapped and compared; :meth:`reconstruct` gives the
full field of any state.

Without hyper-reduction the reduced residual and tangent are still assembled on the full mesh,
so the model keeps the full model's forms; it is made by :func:`lungmech.rom.reductor.reduce`
and saved and loaded by :mod:`lungmech.rom.store` with its start state and training box. With an
ECSW ``sample`` (:mod:`lungmech.rom.ecsw`) it is hyper-reduced: Newton in q on a reduced mesh of
the sampled cells, outputs from reduced operators (:mod:`lungmech.rom.outputs`), so that a solve
never touches the full mesh; :meth:`reconstruct` forms a full field on request.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

from petsc4py import PETSc

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.parametric import Outputs, Solution, Step, output_times, trajectory
from lungmech.fem.quantities import Probe
from lungmech.fem.sensitivity import output_derivatives, reduced_state_derivatives, value_derivatives
from lungmech.fem.solver import NewtonOptions, Stepping
from lungmech.fem.start import StartReport, approach
from lungmech.rom.basis import Basis, inner_product, reference_state
from lungmech.rom.ecsw import Sample
from lungmech.rom.galerkin import ReducedSolver
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.imaged import ReducedImage
from lungmech.rom.indicator import EnrichedIndicator, relative
from lungmech.rom.outputs import ReducedOutputs
from lungmech.rom.whole import Whole

__all__ = ["ReducedModel"]


class ReducedModel:
    """The reduced Galerkin model of ``model`` on ``basis`` (collective).

    Args:
        model: the full :class:`~lungmech.fem.model.Model` whose forms are projected.
        basis: a :class:`~lungmech.rom.basis.Basis` of its state space, zero on imposed dofs.
        stepping: the load path (the same as the full model's, so outputs meet at the same times).
        newton: options of the reduced Newton solves.
        start: the state the basis is relative to (full state array; default: the unloaded state).
        probes: points whose displacement is an output.
        training: the parameter points the basis was trained on (what the model has seen).
        sample: an ECSW sample of the model's cells (trained on this basis): hyper-reduced.
        enrichment: directions beyond the basis (owned rows; the POD vectors next after it):
            every answer then carries its error indicator
            (:class:`~lungmech.rom.indicator.EnrichedIndicator`; a hyper-reduced model's sample
            must be trained on them too).
        described: what the start state is, for the answers' :class:`StartReport` (its
            ``description`` and ``details``, e.g. the image's volume ``imaged_volume`` in m³
            when the start is an imaged body unloaded at the default parameters).
        whole: what a hyper-reduced model needs of the whole body (:mod:`lungmech.rom.whole`):
            computed on ``model``'s mesh by default; given back from a model file for a model of
            the sampled cells alone (:func:`lungmech.rom.store.load_body`).
        image: for a model of an image's motion (``Image.motion``), the reduced inverse motion
            that places its start at every μ (:class:`~lungmech.rom.imaged.ReducedImage`):
            ``start`` is then the start at the defaults, and the basis is relative to the start
            at μ, the image with that μ's other fields.
    """

    def __init__(
        self,
        model: Model,
        basis: Basis,
        stepping: Stepping,
        newton: NewtonOptions | None = None,
        start: np.ndarray | None = None,
        probes: Sequence[Sequence[float]] | Probe = (),
        training: Sequence[Mapping[str, float]] = (),
        sample: Sample | None = None,
        enrichment: np.ndarray | None = None,
        described: StartReport | None = None,
        whole: Whole | None = None,
        image: ReducedImage | None = None,
    ) -> None:
        self.model, self.basis, self.stepping, self.sample, self.image = model, basis, stepping, sample, image
        self.described = described or StartReport(
            "equilibrium", "the reduced model's start (an equilibrium at the default parameters), moved to μ"
        )
        if enrichment is not None and (enrichment.ndim != 2 or enrichment.shape[0] != basis.vectors.shape[0]):
            raise ParameterError(
                f"the enrichment must have the basis' {basis.vectors.shape[0]} owned rows (got shape {enrichment.shape})"
            )
        self.enrichment = None if enrichment is None or not enrichment.shape[1] else enrichment
        self.parameters = model.parameters
        self.probes = probes  # points, or a Probe of material points located already
        self.start = reference_state(model) if start is None else np.array(start, dtype=float)
        self.solver: ReducedSolver | HyperReducedSolver
        self.outputs: Outputs | ReducedOutputs
        if sample is None:
            self.solver = ReducedSolver(model, basis, newton, start=self.start, enrichment=self.enrichment)
            self.outputs = Outputs(model, probes)
        else:
            self.solver = HyperReducedSolver(model, basis, sample, newton, self.start, self.enrichment, whole)
            self.outputs = ReducedOutputs(self.solver, probes, image)
        self.indicator: EnrichedIndicator | None = None
        if self.enrichment is not None:
            kept = self.solver.whole if isinstance(self.solver, HyperReducedSolver) else None
            self.indicator = EnrichedIndicator(model, basis.vectors, self.enrichment, kept)
        self.times = output_times(model, stepping)
        self.training = [dict(point) for point in training]
        self.built: dict = {}  # how the reductor made it (basis recipe, inner product, training, hyper-reduction)
        self.full_size: dict[str, int] | None = None  # a model on a body alone: the full model's dofs and cells
        with model.kept_state():
            self.restart()
            self.start_volume = self.outputs()["volume"]  # m³, of the start state

    def restart(self) -> None:
        """The solver at the start state: the model's state for the Galerkin solver, q = 0 (the
        basis is relative to it) for the hyper-reduced one, which leaves the model's alone; an
        imaged body's at its reference at the defaults."""
        if self.image is not None:
            self.image.reset(self.model)
            self.solver.set_start(self.start)
        elif self.sample is None:
            self.model.state.x.array[:] = self.start
            self.model.state.x.scatter_forward()
        else:
            self.solver.set_state(np.zeros(self.basis.size))

    def truncated(self, size: int) -> ReducedModel:
        """The same model on the first ``size`` basis vectors (a POD basis is nested: the smaller
        model is the one a smaller build would give). Shares the full model's forms."""
        smaller = ReducedModel(
            self.model,
            self.basis.truncate(size),
            self.stepping,
            self.solver.options,
            self.start,
            self.probes,
            self.training,
            self.sample,
            self.enrichment,
            self.described,
            image=self.image,
        )
        smaller.built = dict(self.built)
        return smaller

    @functools.cached_property
    def energy_product(self) -> PETSc.Mat:
        """The energy inner product at rest (PETSc matrix), for the errors of :mod:`lungmech.rom.accuracy`."""
        return inner_product(self.model, "energy")

    @property
    def size(self) -> int:
        """The number of reduced unknowns k."""
        return self.basis.size

    @property
    def probe_points(self) -> tuple[tuple[float, ...], ...]:
        """The points whose displacement is an output (m)."""
        return self.outputs.probe_points

    def solve(
        self,
        mu: Mapping[str, float] | None = None,
        *,
        sensitivities: bool = False,
        on_step: Callable[[Step], None] | None = None,
        scale: float | Sequence[float] = 1.0,
        times: Sequence[float] | None = None,
        progress: Callable[[float, str], None] | None = None,
    ) -> Solution:
        """Outputs and reduced coordinates q at the output times — or at ``times`` (s) — for the
        parameters ``mu``, the loads' change from the start scaled by ``scale``; with an
        enrichment, the answer's error indicator too (of its output times and an imaged body's start; a
        :class:`~lungmech.fem.parametric.Step`'s ``indicator()``: of the states so far). ``on_step`` sees
        every accepted state (:class:`~lungmech.fem.parametric.Step`); ``progress`` is unused
        (the start is a reduced continuation, not long work). As
        :meth:`FullOrderModel.solve <lungmech.fem.parametric.FullOrderModel.solve>`."""
        values = self.parameters.values(mu)
        estimates = []  # (η̂, ‖V q‖_E) at the output times: the answer's indicator
        path = []  # and at every state a Step's indicator() was asked for: the path's so far

        estimate = self.estimate
        # an imaged body's start, the image at the reduced reference, is not solved for: the
        # indicator there (its release) is the reference's error, unless an output is there anyway
        outputs = self.times if times is None else np.asarray(times, dtype=float)
        at_start = estimate is not None and not np.isclose(outputs, self.stepping.start).any()

        def start(on_approach: Callable | None) -> StartReport:
            if self.image is not None:  # its reference at μ: the image is the start
                placed = self.image.place(self.model, self.solver, values, self.stepping.start, progress, on_approach)
                if at_start:
                    assert estimate is not None
                    estimates.append(estimate())
                    path.append(estimates[-1])
                return placed
            defaults = self.parameters.defaults
            self.model.set_parameters(defaults)
            self.restart()
            # reduced Newton straight at μ; continuation only where it fails
            iterations = approach(self.model, self.solver, values, defaults, self.stepping.start, on_approach, 1.0)
            return replace(self.described, newton_iterations=iterations)

        def so_far() -> float | None:
            if estimate is None:
                return None
            path.append(estimate())
            return relative(path)

        solution = trajectory(
            self,
            values,
            start,
            state=lambda: self.solver.coordinates.copy(),
            derivatives=self._sensitivities if sensitivities else None,
            on_step=on_step,
            scale=scale,
            times=times,
            observe=None if estimate is None else lambda: estimates.append(estimate()),
            indicator=so_far,
        )
        return replace(solution, indicator=relative(estimates) if estimate is not None else None)

    def describe(self) -> dict[str, object]:
        """What solves it, for summaries: the reduced solver (and for a model on a body of
        sampled cells, the full model's ``dofs`` and ``cells``)."""
        solver: dict[str, object] = {"solver": self.solver.description, "linear_solver": None}
        return solver | (self.full_size or {})

    def fields(self, state: np.ndarray, time: float) -> None:
        """The model's state the full field x₀ + V q of ``state`` (q) at ``time`` (O(mesh);
        collective)."""
        self.model.set_time(time, *self.model.scaling)
        self.solver.reconstruct(state)

    @property
    def estimate(self) -> Callable[[], tuple[float, float]] | None:
        """(η̂(t), ‖V q(t)‖_E) at the solver's current state, or None without an enrichment
        (:class:`~lungmech.rom.indicator.EnrichedIndicator`; collective)."""
        if self.indicator is None:
            return None
        return functools.partial(self.indicator.at, self.solver)

    def start_at(self, parameters: Mapping[str, float]) -> np.ndarray:
        """The full state the basis is relative to at ``parameters`` (a full local array): the
        start, or an imaged body's start at μ, its reduced inverse motion placed there (which
        then holds ξ(μ) in the model's forms; collective)."""
        if self.image is None:
            return self.start
        if self.image.placed_at != dict(parameters):
            values = self.parameters.values(parameters)
            self.image.place(self.model, self.solver, values, self.stepping.start)
        return self.solver.reference

    def reconstruct(self, solution: Solution, index: int) -> np.ndarray:
        """The full state x₀ + V q of output ``index`` of ``solution``, as the model's state
        (owned entries returned). Sets the model's parameters and time to that output's (an
        imaged body's ξ and start too: :meth:`start_at`)."""
        model = self.model
        self.start_at(solution.parameters)
        model.set_parameters(solution.parameters)
        model.set_time(float(solution.times[index]))
        self.solver.reconstruct(solution.states[index])  # the full field: O(mesh)
        return model.state.x.array[: self.basis.vectors.shape[0]].copy()

    def _sensitivities(self) -> dict[str, object]:
        """Reduced sensitivities: dx/dμ = V dq/dμ + dx₀/dμ, dq/dμ = −(VᵀKV)⁻¹Vᵀ(∂R/∂μ + K dx₀/dμ);
        hyper-reduced, with the sample's r and K, and the outputs' from reduced operators; on an
        image, ∂R/∂μ and dx₀/dμ with the reduced inverse motion's dξ/dμ and start."""
        model, V = self.model, self.basis.vectors
        moved = self.image.moved(model) if self.image is not None else None  # dξ/dμ and the start's
        if self.sample is not None:  # θ of state-dependent loads from the sample
            assert isinstance(self.solver, HyperReducedSolver) and isinstance(self.outputs, ReducedOutputs)
            derivatives = value_derivatives(model, moved, update=self.solver.update_coefficients)
            return self.outputs.derivatives(self.solver.sensitivities.state(derivatives), derivatives)
        derivatives = value_derivatives(model, moved)
        dq = reduced_state_derivatives(model, V, self.solver.jacobian_form, derivatives)
        dx = V @ dq + derivatives.start_state(V.shape[0])
        return output_derivatives(model, self.outputs, None, state_derivative=dx, derivatives=derivatives)
