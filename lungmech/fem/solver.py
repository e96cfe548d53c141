"""Newton's method with line search and adaptive load stepping: the solver's pieces in one place.

* :mod:`lungmech.fem.solver_options`: :class:`NewtonOptions`, and how they reach PETSc;
* :mod:`lungmech.fem.newton`: :class:`NewtonSolver`, one SNES per model;
* :mod:`lungmech.fem.stepping`: :class:`Stepping`, :func:`solve` (adaptive load stepping);
* :mod:`lungmech.fem.prediction`: the next step's predicted state;
* :mod:`lungmech.fem.preconditioners` and :mod:`lungmech.fem.nullspace`: the iterative linear
  solver's preconditioners and AMG's rigid-body near-nullspace;
* :mod:`lungmech.fem.solver_interface`: what the load stepping needs of a solver.

Import from here (the names below) or from the module that defines them.
"""

from lungmech.fem.newton import ITERATIVE_FROM_DOFS, NOT_CONVERGED, NewtonSolver
from lungmech.fem.nullspace import rigid_body_modes
from lungmech.fem.preconditioners import AMG, iterative_layout
from lungmech.fem.solver_interface import NewtonResult, Solver, StepsModelState, steps_model_state
from lungmech.fem.solver_options import NewtonOptions
from lungmech.fem.stepping import FIRST_STRAIN_INCREMENT, SolveReport, Stepping, StepReport, first_step, solve

__all__ = [
    "AMG",
    "FIRST_STRAIN_INCREMENT",
    "ITERATIVE_FROM_DOFS",
    "NOT_CONVERGED",
    "NewtonOptions",
    "NewtonResult",
    "NewtonSolver",
    "SolveReport",
    "Solver",
    "StepReport",
    "Stepping",
    "StepsModelState",
    "first_step",
    "iterative_layout",
    "rigid_body_modes",
    "solve",
    "steps_model_state",
]
