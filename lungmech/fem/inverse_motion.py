"""The start of an imaged body on its fixed mesh: the inverse-motion problem at every μ.

The mesh is the body as imaged at t₀, loaded (:mod:`lungmech.fem.placement`). At parameters μ
its unloaded reference X = x + ξ is the solution of the image's own equilibrium at the loads of
t₀ (Govindjee & Mihalic 1996): R(ξ; μ) = ∂Π/∂w (w = 0, ξ; μ) = 0, solved by Newton on ξ with
the loads raised from zero (ξ = 0 is the solution without load). The breath then starts from
w = 0 — exactly the image — with ξ(μ) a coefficient of its forms. Neither problem moves a
node, and μ reaches both through Constants: nothing is recompiled from one μ to the next.

:class:`InverseMotion` is the start (:class:`lungmech.fem.start.Start`) of a model of the
image's motion (``Image.motion``): it owns the inverse problem's model and solver, and hands ξ
and the other fields (the lung's Φs) to the breath. It answers the problem
:class:`lungmech.lung.inverse.Imaged` answers by its fixed point on a moving mesh; the two
agree to the solvers' tolerances (``tests/test_inverse_motion.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from time import perf_counter
from typing import TYPE_CHECKING

import numpy as np
from dolfinx import fem

from lungmech.errors import ParameterError, SolverError
from lungmech.fem.placement import Image
from lungmech.fem.quantities import integral
from lungmech.fem.sensitivity import Moved, state_derivatives
from lungmech.fem.solver import NewtonOptions, NewtonSolver, Solver, Stepping, StepReport, solve
from lungmech.fem.start import Progress, StartReport
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["Handover", "InverseMotion", "vector_entries"]


class InverseMotion:
    """The start of a model of an image's motion: at μ, the reference map ξ(μ) from the
    inverse-motion problem, and the state the image (w = 0, the other fields the inverse
    problem's). ``newton``: the inverse problem's Newton settings (default: the model's own
    defaults; its line search, one for a potential, is replaced by full steps: the inverse
    residual is no gradient). ``stepping``: how its loads are raised from zero. ``body``: what
    the body is called in messages ("lung"). Built once per model; collective."""

    kind = "imaged"
    refuses_sensitivities: str | None = None

    def __init__(
        self, model: Model, newton: NewtonOptions | None = None, stepping: Stepping | None = None, body: str = "body"
    ) -> None:
        image = model.image
        if image is None or image.unknown != "motion":
            raise ParameterError(
                "InverseMotion starts a model of an image's motion (Model(..., image=Image.motion(t0)))"
            )
        if getattr(model.formulation, "imaged", lambda model: None)(model) is not None:
            # Φs0 would be an unknown of the inverse problem too (Φs = (1 − φ̂f) on the image)
            raise ParameterError(
                "an imaged porosity is matched by the fixed point on a moving mesh (lung.inverse.Imaged), not yet "
                "by the inverse motion: give phi_s0, or start with Imaged"
            )
        self.image, self.body = image, body
        self.inverse = model.variant(Image.inverse(image.time))
        options = newton or NewtonOptions()
        if options.line_search == "cp":  # cp judges a step by R·d, an energy only for a potential
            options = replace(options, line_search="basic")
        # the exact tangent, not a linearised pressure's (that Newton path is the breath's)
        self.solver = NewtonSolver(self.inverse, options, self.inverse.residual, self.inverse.jacobian)
        self.stepping = stepping or Stepping(initial_step=1.0)  # cut back where Newton fails
        mesh = model.geometry.mesh
        self._volume = integral(model.mesh_volume(), mesh.comm)  # the image's (on a template, at its shape)
        self.volume = self._volume()  # m³ (m³/m in 2-D), at the current parameters
        self._reference_volume = integral(fem.Constant(mesh, 1.0) * self.inverse.dx, mesh.comm)
        self._handover = Handover(model, self.inverse)
        self._derivative: np.ndarray | None = None  # dx_ξ/dμ at the last placement, once asked

    def reset(self, model: Model) -> None:
        """The image as the unloaded reference (ξ = 0, w = 0) at the default parameters."""
        model.set_parameters(model.parameters.defaults)
        model.set_reference_map(np.zeros(self._handover.owned_vector))
        model.reset()

    def place(
        self,
        model: Model,
        solver: Solver,
        values: Mapping[str, float],
        time: float,
        progress: Progress | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> StartReport:
        """ξ(μ) for ``values`` and the image's state on it, at ``time`` = t₀ (collective)."""
        self.image.check_start(time, self.body)
        tic = perf_counter()
        inverse = self.inverse
        self._derivative = None
        inverse.set_parameters(values)
        inverse.reset()

        def raised(step: StepReport) -> None:
            if progress is not None and step.converged:
                progress(float(step.time), f"the {self.body}'s reference: loads at {100 * step.time:.0f} %")

        try:
            report = solve(
                inverse, self.stepping, solver=self.solver, drive=lambda s: inverse.set_time(time, s), monitor=raised
            )
        except SolverError as error:
            raise SolverError(
                f"inverse motion: no unloaded reference of the {self.body} at these parameters ({error})"
            ) from None
        model.set_parameters(values)
        self._handover.hand_over(inverse, model)
        model.set_time(time)
        self.volume = self._volume()
        details = {
            "newton_iterations": report.newton_iterations,
            "seconds": perf_counter() - tic,
            "imaged_volume": self.volume,
            "reference_volume": self._reference_volume(),
        }
        return StartReport(
            "imaged",
            f"the imaged {self.body} (its unloaded reference found for these parameters by the inverse motion)",
            report.newton_iterations,
            details,
        )

    def moved(self, model: Model) -> Moved:
        """dξ/dμ and the image's other fields' d/dμ from the inverse problem's direct
        sensitivities at the last placement, K_ξ dx_ξ/dμ = −∂R_ξ/∂μ (its exact, non-symmetric
        tangent, LU; solved once per placement). Collective."""
        if self._derivative is None:
            self._derivative = state_derivatives(self.inverse, self.solver.jacobian_form)
        return self._handover.moved(self.inverse, self._derivative)


class Handover:
    """Where the inverse problem's unknowns go in the breath's model: its vector field (ξ) to
    the reference map, its other fields to the state's, the motion set to zero. The two models
    are built alike on one mesh, so their spaces number the dofs alike (checked). A reduced
    inverse motion (:mod:`lungmech.rom.imaged`) hands over the same way."""

    def __init__(self, motion: Model, inverse: Model) -> None:
        if not np.array_equal(motion.space.dofmap.list, inverse.space.dofmap.list):
            raise SolverError("inverse motion: the inverse problem's dofs are numbered unlike the breath's")
        self.vector = vector_entries(motion)
        assert motion.reference_map is not None  # (a model of an image's motion has one)
        self.reference_map = motion.reference_map
        self.owned_vector = owned_size(self.reference_map.function_space)

    def hand_over(self, inverse: Model, motion: Model) -> None:
        """ξ and the fields of ``inverse``'s state to ``motion``, whose state becomes the image."""
        xi = inverse.state.x.array[self.vector]
        motion.set_reference_map(xi[: self.owned_vector])
        motion.state.x.array[:] = inverse.state.x.array
        motion.state.x.array[self.vector] = 0.0  # w = 0: the image
        motion.state.x.scatter_forward()

    def moved(self, inverse: Model, solution: np.ndarray) -> Moved:
        """What the hand-over sets, with its derivatives, from ``solution`` = dx_ξ/dμ (the
        inverse problem's state derivative, owned rows × parameters): dξ/dμ in the reference
        map, and the other fields' derivative in the start (the motion's is 0)."""
        function, columns = fem.Function(inverse.space), []
        for column in solution.T:  # each with its ghosts
            function.x.array[: column.size] = column
            function.x.scatter_forward()
            columns.append(function.x.array.copy())
        local = np.column_stack(columns) if columns else np.zeros((function.x.array.size, 0))
        start = local.copy()
        start[self.vector] = 0.0
        return Moved({self.reference_map: local[self.vector]}, start)


def vector_entries(model: Model) -> np.ndarray:
    """The local entries of ``model``'s state that hold its vector field (the displacement, or
    an inverse problem's ξ): all of them for a displacement-only model. Those of the first
    owned entries of the field's own space are owned, in its order."""
    if model.multi_field:
        return np.asarray(model.space.sub(0).collapse()[1]).reshape(-1)
    return np.arange(model.state.x.array.size)
