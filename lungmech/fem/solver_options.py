"""Newton's settings and how they reach PETSc: :class:`NewtonOptions`, and the options database
entries of one solver (prefixed, kept for the solver's lifetime, every user option checked to be
one PETSc uses)."""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field

from petsc4py import PETSc

from lungmech import checks
from lungmech.errors import ParameterError, SolverError

__all__ = ["SETTINGS_ERRORS", "NewtonOptions", "configure", "persistent_options", "petsc_message"]


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

    def __post_init__(self) -> None:
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
            # Nor does a step small beside the state (snes_stol): from a prediction far off, x is
            # huge and every step small beside it, which PETSc took for convergence.
            "snes_stol": 0.0,
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


# PETSc errors of settings, not of numbers: no support, wrong argument, out of range, unknown type.
SETTINGS_ERRORS = (56, 62, 63, 86)


def petsc_message(error: PETSc.Error) -> str:
    """The last line of PETSc's error report (what went wrong, without its call stack)."""
    lines = [line.strip(" [0123456789]") for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else f"error {error.ierr}"  # type: ignore[attr-defined]  # petsc4py's stub of Error has no ierr


# Options of objects made at set-up (factorisation, multigrid levels, sub-solvers): read later.
_READ_LATER = ("mat_", "mg_", "fieldsplit_", "sub_", "redundant_", "pc_factor_mat_solver")


def configure(owner: object, snes: PETSc.SNES, prefix: str, options: dict, given: Sequence[str]) -> None:
    """Set ``options`` on ``snes`` (and its KSP and PC) for ``owner``'s lifetime. A value PETSc
    refuses, or an option of the user's (``given``) it does not use, is a :class:`SolverError`
    naming it (options of the objects made at set-up, such as mat_* or mg_levels_*, are checked
    when they are read, at the first solve)."""
    persistent_options(owner, prefix, options)
    database = PETSc.Options()
    try:
        snes.setFromOptions()
    except PETSc.Error as error:
        raise SolverError(f"solver.petsc_options: PETSc refused them: {petsc_message(error)}") from None
    unknown = [key for key in given if not key.startswith(_READ_LATER) and not database.used(prefix + key)]
    if unknown:
        raise SolverError(
            f"solver.petsc_options: PETSc does not use {', '.join(unknown)} here (misspelt, or an "
            "option of another solver type)"
        )


def persistent_options(owner: object, prefix: str, options: dict) -> None:
    """Set PETSc options that stay until ``owner`` is garbage-collected."""
    database = PETSc.Options()
    for key, value in options.items():
        database.setValue(prefix + key, value)

    def remove() -> None:
        for key in options:
            database.delValue(prefix + key)

    weakref.finalize(owner, remove)
