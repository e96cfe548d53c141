"""Newton's method (PETSc SNES) with line search and adaptive load stepping.

A step that fails (no convergence, a NaN, a linear-solver breakdown) is undone: the last
converged state is restored and the step is cut. Easy steps make the next one longer. Below the
minimum step the solve stops with a :class:`SolverError` that says where and why. An unconverged
state is never returned as a result.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import NonlinearProblem, assemble_matrix, assign

from lungmech import checks
from lungmech.errors import Interrupted, ParameterError, SolverError
from lungmech.fem import convergence, limits, linear
from lungmech.fem.formulations import incompressible
from lungmech.fem.linearised_pressure import LinearisedPressure
from lungmech.fem.materials import shear_modulus
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.linalg import gram_schmidt

log = logging.getLogger("lungmech")

_REASONS = {
    getattr(PETSc.SNES.ConvergedReason, name): name
    for name in dir(PETSc.SNES.ConvergedReason)
    if name.isupper() or name.startswith(("CONVERGED", "DIVERGED", "ITERATING"))
}
_prefixes = itertools.count()


@dataclass(frozen=True)
class NewtonOptions:
    """Nonlinear and linear solver settings.

    ``linear_solver`` is "auto" (the default: direct below :data:`ITERATIVE_FROM_DOFS` unknowns
    or where no preconditioner fits the formulation, iterative above or where MUMPS's analysis
    says its factorisation would not fit in memory, and iterative after the direct
    factorisation ran out of memory), "direct" (MUMPS LU, robust) or "iterative" (GMRES with
    smoothed-aggregation AMG and the rigid-body near-nullspace on the displacement, for large
    problems; the lung's (u, Φs) is split by blocks, Φs condensed exactly, see
    :func:`iterative_layout`; each linear solve is as exact as Newton's progress and its stopping
    test need, :meth:`lungmech.fem.convergence.Test.forcing`, unless ``ksp_rtol`` is given).
    ``petsc_options`` overrides or extends any PETSc option; one PETSc refuses or does not use
    is an error.

    A Newton solve has converged when every field's residual has fallen to ``rtol`` times its load
    scale, or to ``atol`` (in the residual's own unit; 0: no absolute test), or quadratically to
    its round-off floor (see :mod:`lungmech.fem.convergence`). The default line search, ``cp``,
    judges a step by R·d, an energy, consistent across fields of different units (``bt``'s merit
    ‖R‖² is not).
    """

    linear_solver: str = "auto"
    rtol: float = 1e-10
    atol: float = 0.0
    max_iterations: int = 25
    line_search: str = "cp"
    petsc_options: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.linear_solver not in ("auto", "direct", "iterative"):
            raise ParameterError(f"linear_solver must be 'auto', 'direct' or 'iterative' (got {self.linear_solver!r})")
        if self.line_search not in ("bt", "l2", "cp", "basic", "none"):
            raise ParameterError(f"line_search must be bt, l2, cp, basic or none (got {self.line_search!r})")
        checks.real("rtol", self.rtol, positive=True)
        checks.real("atol", self.atol, nonnegative=True)
        checks.integer("max_iterations", self.max_iterations, minimum=1)
        if not isinstance(self.petsc_options, dict):
            raise ParameterError(f"petsc_options must be a table of PETSc options (got {self.petsc_options!r})")
        for key in self.petsc_options:
            if key in ("snes_rtol", "snes_atol", "snes_stol"):
                raise ParameterError(
                    f"petsc_options.{key}: lungmech stops Newton with its own test; set rtol or atol "
                    "in [solver] instead"
                )
        for key, value in self.petsc_options.items():
            if not isinstance(value, str | bool | int | float) or (
                isinstance(value, float) and not math.isfinite(value)
            ):
                raise ParameterError(f"petsc_options.{key}: expected a string, number or boolean (got {value!r})")

    def petsc(self, iterative: dict | None = None) -> dict:
        """The PETSc options: of the direct solver, or with ``iterative`` (a layout's preconditioner,
        see :func:`iterative_layout`) of the Krylov one."""
        options = {
            "snes_type": "newtonls",
            "snes_linesearch_type": "basic" if self.line_search == "none" else self.line_search,
            # The line searches' own absolute stop (cp's |F·Y| < 1e-15) depends on units: ours decides.
            "snes_linesearch_atol": 0.0,
            "snes_max_it": self.max_iterations,
            "snes_max_funcs": 10 * self.max_iterations + 100,
        }
        if iterative is None:
            options |= {
                "ksp_type": "preonly",
                "pc_type": "lu",
                "pc_factor_mat_solver_type": "mumps",
                "mat_mumps_icntl_14": 200,  # room for pivoting (mixed)
            }
        else:
            options |= {
                "ksp_type": "gmres",
                # right-preconditioned: GMRES stops on the true residual, which the inexact Newton's
                # tolerance is about (left, a weak preconditioner's residual misled it: 17 Newton
                # iterations for 6 on the lung)
                "ksp_pc_side": "right",
                "ksp_rtol": 1e-9,
                "ksp_max_it": 500,
            } | iterative
        # A true flag is set as a bare option (PETSc reads "" as true, and as "on" for a viewer);
        # a false one is left out (off, PETSc's default), also where lungmech would set it.
        given = {k: "" if v is True else v for k, v in self.petsc_options.items() if v is not False}
        off = {k for k, v in self.petsc_options.items() if v is False}
        return {k: v for k, v in options.items() if k not in off} | given


# Above this many unknowns "auto" takes the iterative solver: on the P1 lung (benchmarks/
# large_lung.py, 2 ranks) the two cross near 135k, and at 483k the iterative one was 2.2 times
# faster with half the memory (at 1.1M: 4.9 times, a third).
ITERATIVE_FROM_DOFS = 200_000
# Below, "auto" asks MUMPS's analysis how much memory its factorisation would take, and takes the
# iterative solver when that is more than this share of what a rank may count on (the rest:
# assembly, vectors, other processes). Smaller problems never come near a machine's memory.
MEMORY_CHECK_FROM_DOFS, DIRECT_MEMORY_SHARE = 20_000, 0.5
NOT_CONVERGED = 91  # PETSC_ERR_NOT_CONVERGED: what a linear step raises when its tangent is singular
# MUMPS INFOG(1) of a factorisation that ran out of memory (workspace, allocation, ICNTL(23))
_MUMPS_OUT_OF_MEMORY = (-8, -9, -11, -12, -13, -14, -15, -17, -19, -20)


AMG = {  # smoothed aggregation, Chebyshev–Jacobi smoothing: for an elastic displacement block
    "pc_type": "gamg",
    "pc_gamg_type": "agg",
    "mg_levels_ksp_type": "chebyshev",
    "mg_levels_pc_type": "jacobi",
}


def _prefixed(prefix: str, options: dict) -> dict:
    return {prefix + key: value for key, value in options.items()}


def iterative_layout(model) -> tuple[dict, Callable[[PETSc.KSP, PETSc.Mat], None]]:
    """The Krylov preconditioner of ``model``'s tangent: PETSc options, and a function of the KSP
    and the tangent matrix that gives them what the options need (the index sets of the fields,
    the rigid-body near-nullspace).

    - Displacement only: AMG with the rigid-body modes.
    - The lung (u, Φs): Φs is cell-local — its equation holds cell by cell, and K_ΦΦ is
      diagonal (DG0) — so it is condensed exactly: a Schur-complement field split with Φs first,
      its block solved by Jacobi (exact for a diagonal), and S = K_uu − K_uΦ K_ΦΦ⁻¹ K_Φu formed
      exactly by ``selfp`` (which uses diag(K_ΦΦ), K_ΦΦ itself), solved with AMG.
    - Taylor–Hood (u, p): a Schur-complement field split with u first, K_uu by AMG with the
      rigid-body modes, and the Schur complement S = −M/κ − B K_uu⁻¹ Bᵀ preconditioned by the
      pressure mass matrix it is spectrally equivalent to (Elman, Silvester & Wathen),
      S_p = −∫ (1/μ₀ + 1/κ) p q dX, μ₀ the law's shear modulus where it is (a field for a
      heterogeneous law; 1/κ = 0 when incompressible), reassembled before each solve so that
      it follows the parameters. ``selfp`` (diag(K_uu)⁻¹) with AMG did not converge on a nearly
      incompressible block.
    """
    fields = ("u", *model.formulation.fields)
    if len(fields) == 1:
        space = model.space
        return dict(AMG), lambda ksp, A: A.setNearNullSpace(rigid_body_modes(space))
    if fields == ("u", "phi_s") or fields == ("u", "thickness_stretch") and model.degree == 1:
        local = fields[1]
        order = (local, "u")  # the cell-local field first: A00, inverted exactly
        options = {
            "pc_type": "fieldsplit",
            "pc_fieldsplit_type": "schur",
            "pc_fieldsplit_schur_fact_type": "full",
            "pc_fieldsplit_schur_precondition": "selfp",
            f"fieldsplit_{local}_ksp_type": "preonly",
            f"fieldsplit_{local}_pc_type": "jacobi",
            "fieldsplit_u_ksp_type": "preonly",
        } | _prefixed("fieldsplit_u_", AMG)
    elif fields == ("u", "p"):
        return _taylor_hood_layout(model)
    else:
        raise ParameterError(
            f"the iterative linear solver has no preconditioner for the fields {', '.join(fields)} yet "
            "(plane stress above degree 1); use linear_solver = 'direct'"
        )

    def set_splits(ksp: PETSc.KSP, A: PETSc.Mat) -> None:
        pc = ksp.getPC()
        sets = _field_index_sets(model)
        pc.setFieldSplitIS(*[(name, sets[name]) for name in order])
        modes = rigid_body_modes(model.space.sub(0).collapse()[0])  # in the u block's row order

        def give_modes(ksp, b, x) -> None:
            """Before each solve: AMG on the Schur complement gets the rigid-body modes (its matrix
            is made when the field split is set up, and kept for the next tangents)."""
            pc = ksp.getPC()  # not captured: PETSc holds this function, and would hold the PC
            pc.setUp()  # a no-op once set up for this tangent
            schur = pc.getFieldSplitSubKSP()[-1]  # the u block's solver: its matrices are S, S_p
            S_p = schur.getOperators()[1]
            if S_p.getNearNullSpace().handle == 0:  # before AMG is built on it, at its first use
                S_p.setNearNullSpace(modes)

        ksp.setPreSolve(give_modes)

    return options, set_splits


def _taylor_hood_layout(model) -> tuple[dict, Callable[[PETSc.KSP, PETSc.Mat], None]]:
    """The (u, p) field split of :func:`iterative_layout`: options, and what the KSP needs."""
    options = {
        "pc_type": "fieldsplit",
        "pc_fieldsplit_type": "schur",
        "pc_fieldsplit_schur_fact_type": "upper",
        "pc_fieldsplit_schur_precondition": "user",
        "fieldsplit_u_ksp_type": "preonly",
        "fieldsplit_p_ksp_type": "preonly",
        "fieldsplit_p_pc_type": "jacobi",  # a P_k mass matrix: diagonal up to a bounded factor
    } | _prefixed("fieldsplit_u_", AMG)

    def set_splits(ksp: PETSc.KSP, A: PETSc.Mat) -> None:
        # compiled here, when the iterative solver is set up, not for every mixed model's solver
        pressures = model.space.sub(1).collapse()[0]
        p, q = ufl.TrialFunction(pressures), ufl.TestFunction(pressures)
        compliance = 1 / shear_modulus(model.material, model.geometry.mesh)
        if not incompressible(model.material):
            compliance += 1 / model.material.bulk
        mass = fem.form(-compliance * p * q * model.dx)
        sets = _field_index_sets(model)
        sets["u"].compose("nearnullspace", rigid_body_modes(model.space.sub(0).collapse()[0]))
        S_p = assemble_matrix(mass)
        S_p.assemble()
        pc = ksp.getPC()
        pc.setFieldSplitIS(("u", sets["u"]), ("p", sets["p"]))
        pc.setFieldSplitSchurPreType(PETSc.PC.FieldSplitSchurPreType.USER, S_p)

        def reassemble(ksp, b, x) -> None:
            """Before each solve: S_p at the current parameters (μ₀ and κ may have changed)."""
            S_p.zeroEntries()
            assemble_matrix(S_p, mass)
            S_p.assemble()

        ksp.setPreSolve(reassemble)

    return options, set_splits


def _layout_if_any(model):
    """:func:`iterative_layout`, or None where no preconditioner fits the formulation."""
    try:
        return iterative_layout(model)
    except ParameterError:
        return None


def _field_index_sets(model) -> dict[str, PETSc.IS]:
    """Global rows of each field, owned by this rank, in the order of the field's own collapsed
    space (so the u block's rows follow its rigid-body modes)."""
    space = model.space
    first = space.dofmap.index_map.local_range[0] * space.dofmap.index_map_bs
    sets = {}
    for i, name in enumerate(("u", *model.formulation.fields)):
        collapsed, parent = space.sub(i).collapse()
        owned = collapsed.dofmap.index_map.size_local * collapsed.dofmap.index_map_bs
        rows = np.asarray(parent).ravel()[:owned]
        sets[name] = PETSc.IS().createGeneral((rows + first).astype(PETSc.IntType), comm=space.mesh.comm)
    return sets


@dataclass(frozen=True)
class Stepping:
    """Adaptive pseudo-time stepping from ``start`` to ``end``.

    Steps grow by ``growth`` after a Newton solve of at most ``easy_iterations`` iterations and
    are halved after a failure; ``times`` (and every ramp breakpoint) are hit exactly, so outputs
    can be requested there. ``initial_step`` None (the default) chooses the first step from the
    tangent: the first interval, shortened until one linear solve predicts a displacement-gradient
    increment of at most :data:`FIRST_STRAIN_INCREMENT` anywhere.
    """

    end: float = 1.0
    start: float = 0.0
    initial_step: float | None = None
    min_step: float = 1e-5
    max_step: float = 1.0
    growth: float = 1.5
    easy_iterations: int = 5
    times: tuple[float, ...] = ()

    def __post_init__(self):
        for name in ("end", "start", "min_step", "growth"):
            checks.real(name, getattr(self, name))
        if self.initial_step is not None:
            checks.real("initial_step", self.initial_step)
        checks.real("max_step", self.max_step, infinite=True)
        checks.integer("easy_iterations", self.easy_iterations, minimum=0)
        if not isinstance(self.times, tuple):
            raise ParameterError(f"times must be a list of output times (got {self.times!r})")
        object.__setattr__(self, "times", tuple(checks.real(f"times[{i}]", t) for i, t in enumerate(self.times)))
        if not self.end > self.start:
            raise ParameterError(f"end ({self.end}) must be after start ({self.start})")
        if outside := [t for t in self.times if not self.start < t <= self.end]:
            raise ParameterError(
                f"times {outside} lie outside (start, end] = ({self.start:g}, {self.end:g}]: "
                "outputs can only be asked for inside the run"
            )
        if (
            not 0
            < self.min_step
            <= (self.min_step if self.initial_step is None else self.initial_step)
            <= self.max_step
        ):
            given = "automatic" if self.initial_step is None else f"{self.initial_step:g}"
            raise ParameterError(
                f"need 0 < min_step <= initial_step <= max_step (got {self.min_step:g}, {given}, {self.max_step:g})"
            )
        if not self.growth >= 1:
            raise ParameterError(f"growth must be >= 1 (got {self.growth:g})")


@dataclass(frozen=True)
class StepReport:
    time: float
    step: float
    iterations: int
    residuals: tuple[float, ...]
    reason: str
    seconds: float
    converged: bool


@dataclass
class SolveReport:
    """Every attempted step, accepted or not, and the totals."""

    steps: list[StepReport] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def accepted(self) -> list[StepReport]:
        return [s for s in self.steps if s.converged]

    @property
    def newton_iterations(self) -> int:
        return sum(s.iterations for s in self.steps)

    @property
    def failures(self) -> int:
        return sum(not s.converged for s in self.steps)


class StepsModelState:
    """The :class:`Solver` part of a solver that iterates on the model's own state array (the
    full and the Galerkin solvers): the load stepping keeps, extrapolates and restores it."""

    model: Any

    @property
    def state(self) -> np.ndarray:
        """The model's state array (owned and ghost entries)."""
        return self.model.state.x.array

    def set_state(self, state: np.ndarray) -> None:
        """Set the model's state (owned and ghost entries)."""
        self.model.state.x.array[:] = state
        self.model.state.x.scatter_forward()

    def update_model(self) -> None:
        """Nothing to do: the model's state is this solver's."""

    def deformation_gradient(self) -> np.ndarray:
        """F = I + ∇u at the quadrature points of this rank's cells, (cells, points, d, d)."""
        return limits.displacement_gradient(self.model)()


class NewtonSolver(StepsModelState):
    """One SNES for one model: forms are compiled once, then reused for every step.

    ``residual`` and ``jacobian`` replace the model's own forms (same unknowns), e.g. the
    incremental potential of a time step (:mod:`lungmech.fem.dynamics`). Otherwise a
    displacement model with a volumetrically split law is solved with the tangent of
    :mod:`lungmech.fem.linearised_pressure` (the mixed formulation's Newton path, the same
    solution); :attr:`jacobian_form` stays the exact tangent.
    """

    def __init__(self, model, options: NewtonOptions | None = None, residual=None, jacobian=None):
        self.model = model
        self.options = options or NewtonOptions()
        self._layout = _layout_if_any(model) if self.options.linear_solver != "direct" else None
        if self.options.linear_solver == "iterative" and self._layout is None:
            iterative_layout(model)  # raises, saying why
        self._prefix = prefix = f"lungmech_{next(_prefixes)}_"
        PETSc.garbage_cleanup(model.geometry.mesh.comm)  # collective: free the solvers gone before
        self._pressure = LinearisedPressure.of(model) if residual is None and jacobian is None else None
        tangent = jacobian if jacobian is not None else model.jacobian
        self.problem = _Problem(
            model.residual if residual is None else residual,
            model.state,
            bcs=model.bcs,
            J=tangent if self._pressure is None else self._pressure.tangent,
            petsc_options_prefix=prefix,
        )
        self._exact_tangent = tangent
        chosen = self.options.linear_solver
        self.linear_solver = chosen if chosen != "auto" else self._automatic_choice()  # what this solver uses now
        layout = self._layout if self.linear_solver == "iterative" else None
        options = self.options.petsc(layout[0] if layout else None)
        _configure(self, self.problem.solver, prefix, options, [k for k in self.options.petsc_options if k in options])
        if layout is not None:
            layout[1](self.problem.solver.getKSP(), self.problem.A)
        self._residuals: list[float] = []
        snes = self.problem.solver
        # Callbacks PETSc holds capture no `self`: Python's collector cannot see PETSc's references,
        # so a solver in such a cycle would never be freed (nor its mesh and its MPI communicators).
        residuals = self._residuals
        snes.setMonitor(lambda snes, it, norm: residuals.append(float(norm)))
        self.test = convergence.Test(convergence.Fields(model), self.options.rtol, self.options.atol)
        self.inversion = limits.Inversion(model)
        limits.displacement_gradient(model)  # compiled now, for the first step: later solves compile nothing
        self.description = "full order"
        K = self.problem.A  # the assembled tangent at frozen load coefficients (the round-off floors use it)
        test = self.test
        mode = self._mode = {"inexact": layout is not None and "ksp_rtol" not in self.options.petsc_options}

        def converged(snes, it, norms):
            reason = test(snes.getFunction()[0], it, K, snes.getSolution())
            if mode["inexact"] and reason == 0:  # the next linear solve only as exact as Newton needs
                snes.getKSP().setTolerances(rtol=test.forcing())
            return reason

        snes.setConvergenceTest(converged)
        if self._pressure is not None:
            snes.setUpdate(_pressure_update(self._pressure))
        self.state_dependent = StateDependent(model)
        self._exact_step = None
        if self.state_dependent:
            self._couple_state_dependent()

    def _automatic_choice(self) -> str:
        """ "auto": direct where no preconditioner fits; iterative from ITERATIVE_FROM_DOFS
        unknowns (faster there), or from MEMORY_CHECK_FROM_DOFS where MUMPS's own estimate of
        its factorisation (its analysis of the tangent at the current state) exceeds
        DIRECT_MEMORY_SHARE of the memory a rank may count on; direct otherwise (collective)."""
        model = self.model
        size = model.space.dofmap.index_map.size_global * model.space.dofmap.index_map_bs
        if self._layout is None:
            return "direct"
        if size >= ITERATIVE_FROM_DOFS:
            return "iterative"
        if size < MEMORY_CHECK_FROM_DOFS:
            return "direct"
        K = assemble_matrix(self.problem.J, bcs=model.bcs)
        K.assemble()
        direct = self.options.petsc()
        need = linear.factorisation_memory(K, {k: v for k, v in direct.items() if k.startswith("mat_mumps_")})
        K.destroy()
        have = linear.available_memory(model.geometry.mesh.comm)
        if need is None or have is None or need <= DIRECT_MEMORY_SHARE * have:
            return "direct"
        log.info(
            "lungmech: a direct factorisation would need %.0f MiB per rank of the %.0f MiB available: "
            "the iterative linear solver",
            need,
            have,
        )
        return "iterative"

    def solve(self, start: np.ndarray | None = None) -> NewtonResult:
        """One Newton solve at the current loads: (converged, iterations, residuals, reason).

        It starts from the current state, or from ``start`` (a prediction, owned and ghost
        entries of the state array). Either way the step's load — the residual at the current
        state, the last equilibrium — sets the convergence test's scale, not the residual of a
        prediction (which is small when it is good, and large where a nearly incompressible
        solid leaves its isochoric manifold)."""
        self.test.new_step()
        try:
            self.test.load(self._residual())
        except PETSc.Error as error:  # e.g. a callback of a state-dependent load that failed
            Interrupted.raise_pending()  # or a Ctrl-C inside it
            return NewtonResult(False, 0, (), f"PETSc error {error.ierr}: {_petsc_message(error)}")
        if self._pressure is not None:
            self._pressure.at_equilibrium()
        if start is not None:
            self.set_state(start)
        return self._newton()

    def _residual(self) -> PETSc.Vec:
        """The residual at the current state and loads (the problem's residual vector)."""
        x, b = self.problem.x, self.problem.b
        assign(self.model.state, x)
        self.problem.solver.computeFunction(x, b)
        return b

    def _couple_state_dependent(self) -> None:
        """Newton on R(u, Θ(u)) for loads with state-dependent coefficients θ (balanced gravity):
        θ is recomputed from every iterate before the residual, the operator is the exact tangent
        K + U Vᵀ (a PETSc LRC matrix), and only K is assembled, factorised or preconditioned. With
        a direct solver the step K⁻¹F is made exact by Woodbury's identity before the line search
        (see :mod:`lungmech.fem.state_dependent`); a Krylov solver applies K + U Vᵀ itself."""
        snes, coupled, K = self.problem.solver, self.state_dependent, self.problem.A
        state = self.model.state
        vector, (assemble_residual, args, kargs) = snes.getFunction()

        def take(x: PETSc.Vec) -> None:
            x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            state.x.array[: coupled.owned] = x.array_r
            state.x.scatter_forward()
            coupled.update()

        def residual(snes, x, b):
            take(x)
            assemble_residual(snes, x, b, *args, **kargs)

        coupled.update()
        U, V = coupled.low_rank()
        factors = [PETSc.Mat().createDense(((coupled.owned, None), (None, U.shape[1])), comm=K.comm) for _ in "UV"]
        for factor in factors:
            factor.setUp()
        operator = PETSc.Mat().createLRC(K, factors[0], None, factors[1])
        _, _, (assemble_jacobian, jargs, jkargs) = snes.getJacobian()
        low_rank = {}

        def jacobian(snes, x, J, P):
            take(x)
            assemble_jacobian(snes, x, K, None, *jargs, **jkargs)
            low_rank["U"], low_rank["V"] = coupled.low_rank()
            for factor, values in zip(factors, (low_rank["U"], low_rank["V"])):
                factor.getDenseArray(readonly=False)[:] = values
                factor.assemble()
            operator.assemble()

        rhs, solution = K.createVecRight(), K.createVecRight()  # work vectors of the m + 1 solves

        def exact_step(x: PETSc.Vec, y: PETSc.Vec) -> bool:
            ksp = snes.getKSP()
            if ksp.getType() != PETSc.KSP.Type.PREONLY:  # a Krylov solver had the exact operator
                return False
            pc = ksp.getPC()

            def solve(b: np.ndarray) -> np.ndarray:
                rhs.array[:] = b
                pc.apply(rhs, solution)
                return solution.array.copy()

            y.array[:] = coupled.woodbury(y.array_r.copy(), low_rank["U"], low_rank["V"], solve)
            return True

        snes.setFunction(residual, vector)
        snes.setJacobian(jacobian, operator, K)
        snes.setLineSearchPreCheck(exact_step)
        self._exact_step = exact_step

    def linear_step(self) -> None:
        """Move the state by one Newton step at the current loads, without a line search or a
        convergence test: from an equilibrium, the tangent's response to the change of load."""
        problem, snes = self.problem, self.problem.solver
        x, b = problem.x, problem.b
        if self._pressure is not None:
            self._pressure.at_equilibrium()
        assign(self.model.state, x)
        snes.computeFunction(x, b)
        operator, K, _ = snes.getJacobian()
        snes.computeJacobian(x, operator, K)
        ksp = snes.getKSP()
        ksp.setOperators(operator, K)
        step = x.duplicate()
        ksp.solve(b, step)
        if ksp.getConvergedReason() < 0 and self._out_of_memory():
            self._switch_to_iterative()
            ksp.setOperators(operator, K)
            ksp.solve(b, step)
        if ksp.getConvergedReason() < 0:  # a singular tangent, say: the callers carry on without
            step.destroy()
            raise PETSc.Error(NOT_CONVERGED)
        if self._exact_step is not None:
            self._exact_step(x, step)
        x.axpy(-1.0, step)
        step.destroy()
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        assign(x, self.model.state)

    def start_path(self) -> None:
        """A new load path begins: the fields' load scales start again (see :mod:`lungmech.fem.convergence`)."""
        self.test.start_path()

    def _newton(self) -> NewtonResult:
        self._residuals.clear()
        self.test.start()
        snes = self.problem.solver
        try:
            self.problem.solve()
            reason = snes.getConvergedReason()
        except PETSc.Error as error:  # e.g. a factorisation breakdown on a NaN Jacobian
            Interrupted.raise_pending()  # or a Ctrl-C that arrived inside a PETSc callback
            said = _petsc_message(error)
            if error.ierr in _SETTINGS_ERRORS:  # the same at every step: not a numerical failure
                raise SolverError(f"PETSc refused the solver settings (solver.petsc_options?): {said}") from None
            return NewtonResult(
                False, snes.getIterationNumber(), tuple(self._residuals), f"PETSc error {error.ierr}: {said}"
            )
        Interrupted.raise_pending()
        if reason == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE and self._out_of_memory():
            self._switch_to_iterative()
            return self._newton()
        converged = reason > 0 and np.all(np.isfinite(self.model.state.x.array))
        name = _REASONS.get(reason, str(reason))
        if not converged:
            name = f"{name}: {self.test.describe()}"
        elif wrong := self.inversion():
            converged, name = False, f"{name} to {wrong}"
        return NewtonResult(bool(converged), snes.getIterationNumber(), tuple(self._residuals), name)

    def _out_of_memory(self) -> bool:
        """Whether "auto" may leave a direct factorisation that ran out of memory (collective)."""
        if self.options.linear_solver != "auto" or self.linear_solver != "direct" or self._layout is None:
            return False
        try:
            info = self.problem.solver.getKSP().getPC().getFactorMatrix().getMumpsInfog(1)
        except PETSc.Error:
            return False
        return info in _MUMPS_OUT_OF_MEMORY

    def _switch_to_iterative(self) -> None:
        """From now on, the iterative solver (the state is the last one Newton started from)."""
        options, configure = self._layout
        database = PETSc.Options()
        for key in ("pc_factor_mat_solver_type", "mat_mumps_icntl_14"):
            database.delValue(self._prefix + key)
        chosen = self.options.petsc(options)
        _persistent_options(self, self._prefix, chosen)
        ksp = self.problem.solver.getKSP()
        ksp.getPC().reset()
        ksp.setFromOptions()
        configure(ksp, self.problem.A)
        self.linear_solver = "iterative"
        self._mode["inexact"] = "ksp_rtol" not in self.options.petsc_options
        log.warning("lungmech: the direct factorisation ran out of memory; switching to the iterative linear solver")

    @property
    def residual_form(self):
        """The compiled residual form."""
        return self.problem.F

    @functools.cached_property
    def jacobian_form(self):
        """The compiled exact Jacobian form (sensitivities, stability), which Newton's own tangent
        may differ from away from an equilibrium (:mod:`lungmech.fem.linearised_pressure`)."""
        if self._pressure is None:
            return self.problem.J
        return fem.form(self._exact_tangent)  # compiled when first asked for (collective)

    def destroy(self) -> None:
        self.problem.solver.destroy()


def _pressure_update(pressure: LinearisedPressure) -> Callable[[PETSc.SNES, int], None]:
    """SNES's hook at the start of every Newton iteration: the bulk stress moves along the step
    just taken (from the iterate recorded at the previous call; at iteration 0, the solve's
    start, s is already set, see :meth:`NewtonSolver.solve`)."""
    previous = {}

    def update(snes: PETSc.SNES, iteration: int) -> None:
        x = snes.getSolution().getArray(readonly=True)
        if iteration > 0:
            pressure.advance(previous["x"], x - previous["x"])
        previous["x"] = x.copy()

    return update


class _Problem(NonlinearProblem):
    """DOLFINx's NonlinearProblem, left to petsc4py to free. DOLFINx destroys its PETSc objects
    when Python collects it, which may happen at another moment on each rank (a collector cycle,
    an exception's traceback held on one rank only); destroying a MUMPS factorisation is
    collective, so that could hang. petsc4py instead puts distributed objects on PETSc's garbage
    list, which NewtonSolver empties collectively (``PETSc.garbage_cleanup``)."""

    def __del__(self):
        pass


@dataclass(frozen=True)
class NewtonResult:
    """What a Newton solve did."""

    converged: bool
    iterations: int
    residuals: tuple[float, ...]  # the norm of the whole residual at each iteration
    reason: str  # PETSc's converged reason, and what failed when it did not converge


class Solver(Protocol):
    """What the load stepping (:func:`solve`) and the outputs need of a nonlinear solver: the
    full-order :class:`NewtonSolver` and the reduced :class:`lungmech.rom.galerkin.ReducedSolver`."""

    model: Any
    description: str  # for summaries, e.g. "full order"

    def solve(self, start: np.ndarray | None = None) -> NewtonResult:
        """One Newton solve at the model's current loads, from its :attr:`state` or ``start``
        (a prediction; the current state is the last equilibrium). A failed solve leaves its
        last iterate there (the load stepping restores the last equilibrium)."""
        ...

    @property
    def state(self) -> np.ndarray:
        """The unknowns it iterates on: the load stepping keeps, extrapolates and restores these.
        The full and Galerkin solvers' is the model's state array; a hyper-reduced solver's is q,
        and it reads or writes the model's state only on request (``project()``,
        :meth:`update_model`): code that moves the model's state must move q too."""
        ...

    def set_state(self, state: np.ndarray) -> None: ...

    def update_model(self) -> None:
        """Write the solver's state into the model's (a reduced solver need not keep it there)."""
        ...

    def deformation_gradient(self) -> np.ndarray:
        """F at the quadrature points where the solver evaluates the model, (cells, points, d, d)."""
        ...

    def start_path(self) -> None:
        """A load path begins (the solver may rescale its convergence test)."""
        ...

    def linear_step(self) -> None:
        """One Newton step from the model's current state at its current loads (no line search)."""
        ...

    @property
    def residual_form(self) -> Any: ...

    @property
    def jacobian_form(self) -> Any: ...

    def destroy(self) -> None: ...


# PETSc errors of settings, not of numbers: no support, wrong argument, out of range, unknown type.
_SETTINGS_ERRORS = (56, 62, 63, 86)


def _petsc_message(error: PETSc.Error) -> str:
    """The last line of PETSc's error report (what went wrong, without its call stack)."""
    lines = [line.strip(" [0123456789]") for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else f"error {error.ierr}"


# Options of objects made at set-up (factorisation, multigrid levels, sub-solvers): read later.
_READ_LATER = ("mat_", "mg_", "fieldsplit_", "sub_", "redundant_", "pc_factor_mat_solver")


def _configure(owner, snes: PETSc.SNES, prefix: str, options: dict, given: Sequence[str]) -> None:
    """Set ``options`` on ``snes`` (and its KSP and PC) for ``owner``'s lifetime. A value PETSc
    refuses, or an option of the user's (``given``) it does not use, is a :class:`SolverError`
    naming it (options of the objects made at set-up, such as mat_* or mg_levels_*, are checked
    when they are read, at the first solve)."""
    _persistent_options(owner, prefix, options)
    database = PETSc.Options()
    try:
        snes.setFromOptions()
    except PETSc.Error as error:
        raise SolverError(f"solver.petsc_options: PETSc refused them: {_petsc_message(error)}") from None
    unknown = [key for key in given if not key.startswith(_READ_LATER) and not database.used(prefix + key)]
    if unknown:
        raise SolverError(
            f"solver.petsc_options: PETSc does not use {', '.join(unknown)} here (misspelt, or an "
            "option of another solver type)"
        )


def _persistent_options(owner, prefix: str, options: dict) -> None:
    """Set PETSc options that stay until ``owner`` is garbage-collected."""
    database = PETSc.Options()
    for key, value in options.items():
        database[prefix + key] = value
    weakref.finalize(owner, lambda: [database.delValue(prefix + key) for key in options])


def steps_model_state(solver: Solver) -> bool:
    """Whether ``solver`` iterates on the model's own state array (not on reduced coordinates)."""
    return np.shares_memory(solver.state, solver.model.state.x.array)


def solve(
    model,
    stepping: Stepping | None = None,
    options: NewtonOptions | None = None,
    on_step: Callable[[StepReport], None] | None = None,
    solver: Solver | None = None,
    drive: Callable[[float], None] | None = None,
    monitor: Callable[[StepReport], None] | None = None,
    breakpoints: Sequence[float] | None = None,
) -> SolveReport:
    """Drive ``model`` from ``stepping.start`` to ``stepping.end`` with adaptive steps.

    ``on_step`` is called after every accepted step (outputs, P–V curves, snapshots), and
    ``monitor`` after every attempt, accepted or cut back (default: a log line). Pass a
    ``solver`` to reuse its compiled forms across calls. The stepped variable is the time,
    unless ``drive(s)`` is given to apply it otherwise (e.g. as a load factor). Steps land on
    ``breakpoints`` (default: the model's ramp breakpoints, unless ``drive`` is given). Raises
    :class:`SolverError` when a step below ``stepping.min_step`` still fails; the model then
    holds the last converged state. The path starts from the solver's state (:attr:`Solver.state`)
    and ends there: a hyper-reduced solver iterates on q and writes the model's state only when
    asked (``update_model()``), so that no step touches the full mesh.
    """
    stepping = stepping or Stepping()
    solver = solver or NewtonSolver(model, options)
    if breakpoints is None:
        breakpoints = model.breakpoints if drive is None else []
    drive = drive or model.set_time
    targets = sorted({t for t in (*stepping.times, *breakpoints, stepping.end) if stepping.start < t <= stepping.end})
    report = SolveReport()
    started = time.perf_counter()

    t = stepping.start
    drive(t)
    first = solver.state.copy()  # where the load path starts (for a diagnosis of where it ends)
    solver.start_path()
    dt, rate = stepping.initial_step, None
    if dt is None:
        dt, rate = first_step(model, solver, drive, t, min(stepping.max_step, targets[0] - t), stepping.min_step)
    kinks = [b for b in breakpoints if stepping.start < b < stepping.end]
    path = _Path(t, solver.state)
    for target in targets:
        while t < target - 1e-12 * (stepping.end - stepping.start):
            dt = min(dt, stepping.max_step, target - t)
            drive(t + dt)
            tic = time.perf_counter()
            prediction, linear_solves = path.predict(t + dt, solver, rate)
            result = solver.solve(start=prediction)
            converged = result.converged
            step = StepReport(
                t + dt,
                dt,
                linear_solves + result.iterations,
                result.residuals,
                result.reason,
                time.perf_counter() - tic,
                converged,
            )
            report.steps.append(step)
            (monitor or _log_step)(step)
            if converged:
                t += dt
                rate = None  # the tangent at the start predicts the first step only
                if any(abs(t - kink) <= 1e-12 * (stepping.end - stepping.start) for kink in kinks):
                    path = _Path(t, solver.state)  # the load turns here: extrapolating across it would mislead
                else:
                    path.append(t, solver.state)
                if on_step is not None:
                    on_step(step)
                if step.iterations <= stepping.easy_iterations:
                    dt *= stepping.growth
                continue
            final = dt <= stepping.min_step * (1 + 1e-12)
            if final:  # the diagnosis judges full states, each at its own loads
                solver.update_model()
                smallest_J = limits.min_jacobian(model)()  # of the failed iterate
                drive(stepping.start)
                solver.set_state(first)
                solver.update_model()
                began = model.state.x.array.copy()
            solver.set_state(path.last)
            if final:
                drive(t)
                solver.update_model()
                cause = limits.diagnose(model, solver, drive, t, (began, stepping.start), smallest_J, t + dt)
                report.seconds = time.perf_counter() - started
                raise SolverError(_failure_message(t, dt, step, cause, getattr(solver, "options", None)))
            dt = max(dt / 2, stepping.min_step)
    report.seconds = time.perf_counter() - started
    return report


FIRST_STRAIN_INCREMENT = 0.1  # the largest |ΔF| the tangent may predict for an automatic first step


def first_step(
    model, solver: Solver, drive: Callable[[float], None], t: float, interval: float, min_step: float
) -> tuple[float, np.ndarray | None]:
    """The first step from t, and the tangent's rate of change of the state there.

    The step is ``interval``, shortened to interval · s/|ΔF|_max when one linear solve of the
    tangent at the start state predicts a displacement-gradient increment |ΔF|_max (Frobenius, at
    the quadrature points) above s = FIRST_STRAIN_INCREMENT. Newton converges from the linearised
    response of small strain increments; the estimate is conservative for stiffening laws. The
    rate Δx/interval (None if the tangent was singular) predicts the first step's state: the loads
    are linear in t within the interval, so the tangent's response is too. The state and the loads
    are left as they were."""
    rate = None
    before, start = solver.deformation_gradient(), solver.state.copy()
    drive(t + interval)
    try:
        solver.linear_step()
        change = np.linalg.norm(solver.deformation_gradient() - before, axis=(-2, -1))
        local = float(change.max()) if change.size else 0.0
        if not np.isfinite(change).all():
            local = np.inf
        rate = (solver.state - start) / interval
    except PETSc.Error:  # a singular tangent at the start: no estimate, the stepping adapts
        Interrupted.raise_pending()  # or a Ctrl-C that arrived inside a PETSc callback
        local = 0.0
    finally:
        solver.set_state(start)
        drive(t)
    largest = model.geometry.mesh.comm.allreduce(local, op=MPI.MAX)
    if not np.isfinite(largest) or model.geometry.mesh.comm.allreduce(rate is None, op=MPI.LOR):
        rate = None
    if largest <= FIRST_STRAIN_INCREMENT:
        return interval, rate
    return max(min_step, interval * FIRST_STRAIN_INCREMENT / largest), rate


class _Path:
    """The converged states of one smooth stretch of a load path (from its start or its last
    ramp breakpoint), kept to predict the next step's state (the last three at most)."""

    def __init__(self, t: float, state: np.ndarray):
        self.times, self.states = [t], [state.copy()]

    @property
    def last(self) -> np.ndarray:
        return self.states[-1]

    def append(self, t: float, state: np.ndarray) -> None:
        self.times, self.states = [*self.times[-2:], t], [*self.states[-2:], state.copy()]

    def predict(self, t: float, solver: Solver, rate: np.ndarray | None) -> tuple[np.ndarray | None, int]:
        """A prediction of the state at t (the loads already at t), and how many linear solves it
        cost. With two or three converged states: their Lagrange extrapolation,
        x(t) ≈ Σ_i x_i Π_{j≠i} (t − t_j)/(t_i − t_j), exact for a path of that degree in t. With
        one: the tangent's response x_0 + K⁻¹(load increment), taken in full. Newton's first step
        from an equilibrium is that same response, but a line search judging it by the energy may
        crawl along it where the path curves (a nearly incompressible solid: a tangential step
        leaves the isochoric manifold to second order, at a bulk modulus' cost), while from the
        prediction Newton corrects back onto the path. None: no prediction (a singular tangent)."""
        if len(self.times) > 1:
            return sum(
                x_i * math.prod((t - t_j) / (t_i - t_j) for j, t_j in enumerate(self.times) if j != i)
                for i, (t_i, x_i) in enumerate(zip(self.times, self.states))
            ), 0
        if rate is not None:
            return self.last + (t - self.times[0]) * rate, 0
        try:
            solver.linear_step()
        except PETSc.Error:  # a singular tangent: Newton starts from the last state
            Interrupted.raise_pending()
            return None, 1
        finally:
            predicted = solver.state.copy()
            solver.set_state(self.last)
        return predicted, 1


def _log_step(step: StepReport) -> None:
    status = "ok" if step.converged else f"not converged ({step.reason}): step cut back"
    log.info(
        "t = %.6g s  dt = %.3g s  Newton %2d  %.2f s  %s", step.time, step.step, step.iterations, step.seconds, status
    )


def _failure_message(t: float, dt: float, step: StepReport, cause: str, options: NewtonOptions | None = None) -> str:
    where = f"the load path stopped at t = {t:.6g} s"
    if cause:
        return (
            f"{where}: {cause}. Newton could not take even the minimum step ({dt:.3g} s) beyond it "
            f"({step.reason}). The last converged state, at t = {t:.6g} s, is kept."
        )
    linear = {k: v for k, v in (options.petsc_options if options else {}).items() if k.startswith(("ksp_", "pc_"))}
    if linear:  # the user's linear solver, not the body, is then the first suspect
        shown = ", ".join(f"{k} = {v!r}" for k, v in linear.items())
        return (
            f"{where}: Newton did not converge even at the minimum step ({dt:.3g} s; {step.reason}) with the linear "
            f"solver that solver.petsc_options set ({shown}): a linear solver that does not solve Newton's systems "
            "accurately enough is the likely cause; leave these options out to use lungmech's own. The last "
            "converged state is kept."
        )
    return (
        f"{where}: the minimum step ({dt:.3g} s) was reached and Newton still did not converge ({step.reason}). "
        "The last converged state is kept. Try a smaller min_step or another line search, or check the loads "
        "and material parameters."
    )


def rigid_body_modes(space) -> PETSc.NullSpace:
    """The rigid-body modes of a vector space, orthonormalised: AMG's near-nullspace. Six in
    3-D (three translations, three rotations ω × x), three in a plane (two translations, the
    rotation about z: (−y, x))."""
    index_map, bs = space.dofmap.index_map, space.dofmap.index_map_bs
    n = index_map.size_local
    comm = space.mesh.comm
    x = space.tabulate_dof_coordinates()[:n]
    # Rotations about one point for all ranks (the global centre: better conditioned than the origin).
    total = comm.allreduce(np.concatenate([x.sum(axis=0), [len(x)]]), op=MPI.SUM)
    x = x - total[:3] / total[3]
    rotations = [np.cross(axis, x)[:, :bs] for axis in (np.eye(3) if bs == 3 else [(0.0, 0.0, 1.0)])]
    modes = np.array([*np.eye(bs)[:, None, :].repeat(n, axis=1), *rotations])
    orthonormal, _ = gram_schmidt(modes.reshape(len(modes), -1).T, None, comm, tolerance=0.0)
    vectors = [PETSc.Vec().createWithArray(mode.copy(), bsize=bs, comm=comm) for mode in orthonormal.T]
    return PETSc.NullSpace().create(vectors=vectors, comm=comm)
