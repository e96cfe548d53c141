"""Newton's method on one model: a PETSc SNES with line search, compiled once and reused for every
step (:class:`NewtonSolver`). Its convergence test is lungmech's (:mod:`lungmech.fem.convergence`);
"auto" chooses the direct (MUMPS) or iterative linear solver (:mod:`lungmech.fem.preconditioners`)
by size and memory, and leaves a factorisation that ran out of memory."""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import NonlinearProblem, assemble_matrix, assign

from lungmech import jit
from lungmech.errors import Interrupted, SolverError
from lungmech.fem import convergence, limits, linear
from lungmech.fem.linearised_pressure import LinearisedPressure
from lungmech.fem.preconditioners import available_layout, iterative_layout
from lungmech.fem.residual import residual as lifted_where_needed
from lungmech.fem.solver_interface import NewtonResult, StepsModelState
from lungmech.fem.solver_options import (
    SETTINGS_ERRORS,
    NewtonOptions,
    configure,
    persistent_options,
    petsc_message,
)
from lungmech.fem.state_dependent import StateDependent

if TYPE_CHECKING:
    from lungmech.fem.model import Model

__all__ = ["ITERATIVE_FROM_DOFS", "NOT_CONVERGED", "NewtonSolver"]

log = logging.getLogger("lungmech")


_REASONS = {
    getattr(PETSc.SNES.ConvergedReason, name): name
    for name in dir(PETSc.SNES.ConvergedReason)
    if name.isupper() or name.startswith(("CONVERGED", "DIVERGED", "ITERATING"))
}
_prefixes = itertools.count()
# What SNES.getFunction() and getJacobian() return (petsc4py's stubs say the callback alone): the
# residual vector (the operator and the preconditioner's matrix), and the callback with its arguments
_Callback = tuple[Callable[..., None], tuple[Any, ...], dict[str, Any]]
_Function = tuple[PETSc.Vec, _Callback]
_Jacobian = tuple[PETSc.Mat, PETSc.Mat, _Callback]


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


class NewtonSolver(StepsModelState):
    """One SNES for one model: forms are compiled once, then reused for every step.

    ``residual`` and ``jacobian`` replace the model's own forms (same unknowns), e.g. the
    incremental potential of a time step (:mod:`lungmech.fem.dynamics`). Otherwise a
    displacement model with a volumetrically split law is solved with the tangent of
    :mod:`lungmech.fem.linearised_pressure` (the mixed formulation's Newton path, the same
    solution); :attr:`jacobian_form` stays the exact tangent.
    """

    def __init__(
        self,
        model: Model,
        options: NewtonOptions | None = None,
        residual: ufl.Form | None = None,
        jacobian: ufl.Form | None = None,
    ) -> None:
        self.model = model
        self.options = options or NewtonOptions()
        self._layout = available_layout(model) if self.options.linear_solver != "direct" else None
        if self.options.linear_solver == "iterative" and self._layout is None:
            iterative_layout(model)  # raises, saying why
        self._prefix = prefix = f"lungmech_{next(_prefixes)}_"
        PETSc.garbage_cleanup(model.geometry.mesh.comm)  # collective: free the solvers gone before
        self._pressure = LinearisedPressure.of(model) if residual is None and jacobian is None else None
        tangent = jacobian if jacobian is not None else model.jacobian
        self.problem = _Problem(  # compiled forms: DOLFINx takes them as they are
            jit.form(model.residual if residual is None else residual),
            model.state,
            bcs=model.bcs,
            J=jit.form(tangent if self._pressure is None else self._pressure.tangent),
            petsc_options_prefix=prefix,
        )
        self._exact_tangent = tangent
        chosen = self.options.linear_solver
        self.linear_solver = chosen if chosen != "auto" else self._automatic_choice()  # what this solver uses now
        layout = self._layout if self.linear_solver == "iterative" else None
        petsc = self.options.petsc(layout[0] if layout else None)
        configure(self, self.problem.solver, prefix, petsc, [k for k in self.options.petsc_options if k in petsc])
        if layout is not None:
            layout[1](self.problem.solver.getKSP(), self.problem.A)
        self._residuals: list[float] = []
        snes = self.problem.solver
        vector, (_, args, kargs) = cast(_Function, snes.getFunction())
        snes.setFunction(lifted_where_needed, vector, args=args, kargs=kargs)  # type: ignore[arg-type]  # petsc4py passes args and kargs on; its stub says a 3-argument callback
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

        def converged(snes: PETSc.SNES, it: int, norms: tuple[float, float, float]) -> int:
            reason = test(cast(_Function, snes.getFunction())[0], it, K, snes.getSolution())
            if mode["inexact"] and reason == 0:  # the next linear solve only as exact as Newton needs
                snes.getKSP().setTolerances(rtol=test.forcing())
            return reason

        snes.setConvergenceTest(converged)  # type: ignore[arg-type]  # a converged reason is an int at run time; the stubs say a class
        if self._pressure is not None:
            snes.setUpdate(_pressure_update(self._pressure))
        self.state_dependent = StateDependent(model)
        self._exact_step: Callable[[PETSc.Vec, PETSc.Vec], bool] | None = None
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
            return NewtonResult(False, 0, (), f"PETSc error {error.ierr}: {petsc_message(error)}")  # type: ignore[attr-defined]  # petsc4py's stub of Error has no ierr
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
        vector, (assemble_residual, args, kargs) = cast(_Function, snes.getFunction())

        def take(x: PETSc.Vec) -> None:
            x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
            state.x.array[: coupled.owned] = x.array_r
            state.x.scatter_forward()
            coupled.update()

        def residual(snes: PETSc.SNES, x: PETSc.Vec, b: PETSc.Vec) -> None:
            take(x)
            assemble_residual(snes, x, b, *args, **kargs)

        coupled.update()
        U, V = coupled.low_rank()
        factors = [PETSc.Mat().createDense(((coupled.owned, None), (None, U.shape[1])), comm=K.comm) for _ in "UV"]  # type: ignore[arg-type]  # None (PETSC_DECIDE) in a size is not in petsc4py's stub
        for factor in factors:
            factor.setUp()
        operator = PETSc.Mat().createLRC(K, factors[0], None, factors[1])
        _, _, (assemble_jacobian, jargs, jkargs) = cast(_Jacobian, snes.getJacobian())
        low_rank = {}

        def jacobian(snes: PETSc.SNES, x: PETSc.Vec, J: PETSc.Mat, P: PETSc.Mat) -> None:
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
        snes.setLineSearchPreCheck(exact_step)  # type: ignore[arg-type]  # petsc4py reads the bool (changed); its stub says None
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
        if ksp.getConvergedReason() < 0 and self._out_of_memory():  # type: ignore[operator]  # an int at run time; the stubs say a class
            self._switch_to_iterative()
            ksp.setOperators(operator, K)
            ksp.solve(b, step)
        if ksp.getConvergedReason() < 0:  # type: ignore[operator]  # a singular tangent, say: the callers carry on without (an int at run time; the stubs say a class)
            step.destroy()
            raise PETSc.Error(NOT_CONVERGED)
        if self._exact_step is not None:
            self._exact_step(x, step)
        x.axpy(-1.0, step)
        step.destroy()
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
        assign(x, self.model.state)  # type: ignore[arg-type]  # DOLFINx's vector-to-function overload (singledispatch) is not in its hints

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
            said, code = petsc_message(error), error.ierr  # type: ignore[attr-defined]  # petsc4py's stub of Error has no ierr
            if code in SETTINGS_ERRORS:  # the same at every step: not a numerical failure
                raise SolverError(f"PETSc refused the solver settings (solver.petsc_options?): {said}") from None
            return NewtonResult(False, snes.getIterationNumber(), tuple(self._residuals), f"PETSc error {code}: {said}")
        Interrupted.raise_pending()
        if reason == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE and self._out_of_memory():
            self._switch_to_iterative()
            return self._newton()
        converged = reason > 0 and np.all(np.isfinite(self.model.state.x.array))  # type: ignore[operator]  # an int at run time; the stubs say a class
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
        assert self._layout is not None  # _out_of_memory() said so
        options, configure = self._layout
        database = PETSc.Options()
        for key in ("pc_factor_mat_solver_type", "mat_mumps_icntl_14"):
            database.delValue(self._prefix + key)
        chosen = self.options.petsc(options)
        persistent_options(self, self._prefix, chosen)
        ksp = self.problem.solver.getKSP()
        ksp.getPC().reset()
        ksp.setFromOptions()
        configure(ksp, self.problem.A)
        self.linear_solver = "iterative"
        self._mode["inexact"] = "ksp_rtol" not in self.options.petsc_options
        log.warning("lungmech: the direct factorisation ran out of memory; switching to the iterative linear solver")

    @property
    def residual_form(self) -> fem.Form:
        """The compiled residual form."""
        return cast(fem.Form, self.problem.F)  # one form: not a block problem

    @functools.cached_property
    def jacobian_form(self) -> fem.Form:
        """The compiled exact Jacobian form (sensitivities, stability), which Newton's own tangent
        may differ from away from an equilibrium (:mod:`lungmech.fem.linearised_pressure`)."""
        if self._pressure is None:
            return cast(fem.Form, self.problem.J)  # one form: not a block problem
        return jit.form(self._exact_tangent)  # compiled when first asked for (collective)

    def destroy(self) -> None:
        self.problem.solver.destroy()


def _pressure_update(pressure: LinearisedPressure) -> Callable[[PETSc.SNES, int], None]:
    """SNES's hook at the start of every Newton iteration: the bulk stress moves along the step
    just taken (from the iterate recorded at the previous call; at iteration 0, the solve's
    start, s is already set, see :meth:`NewtonSolver.solve`)."""
    previous: dict[str, np.ndarray] = {}

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

    def __del__(self) -> None:
        pass
