"""Newton's residual lifted only where a Dirichlet condition does not hold yet
(lungmech.fem.residual): the same path as DOLFINx's own residual to the bit, on a block held on
its symmetry planes and pulled by a prescribed displacement, the lifting left out at most
iterates; on two ranks too (tests/test_mpi.py)."""

from mpi4py import MPI

import numpy as np
from dolfinx.fem.petsc import assemble_residual

from lungmech.fem import residual as own
from lungmech.fem.constraints import Displacement, symmetry
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.solver import Stepping, solve
from lungmech.mesh import box


def pulled_block() -> Model:
    """A block on its three symmetry planes, its end x1 pulled 0.3 along x (a stretch of 1.15)
    and 0.05 along z: conditions that hold from a step's second iterate, and one that does not
    hold at a step's first."""
    geometry = box(MPI.COMM_WORLD, lengths=(2.0, 1.0, 1.0), cells=(6, 3, 3))
    return Model(
        geometry,
        NeoHookean.from_young(10.0, 0.3),
        constraints=[
            symmetry("x0", "x"),
            symmetry("y0", "y"),
            symmetry("z0", "z"),
            Displacement("x1", (0.3, 0.0, 0.05)),
        ],
    )


def test_the_path_is_dolfinxs_to_the_bit_and_most_liftings_are_left_out(monkeypatch):
    """The same states and iterations as with DOLFINx's residual; the lifting at each step's
    first residual (the pulled end not yet where it goes), not at most of the others."""
    residuals, lifted = [], []

    def counted(*args, **kwargs):
        residuals.append(1)
        own.residual(*args, **kwargs)

    def lifting(*args, **kwargs):
        lifted.append(1)
        assemble_residual(*args, **kwargs)

    monkeypatch.setattr(own, "assemble_residual", lifting)
    states, iterations = [], []
    for how in (counted, assemble_residual):
        monkeypatch.setattr("lungmech.fem.newton.lifted_where_needed", how)
        model = pulled_block()
        report = solve(model, Stepping(end=1.0, initial_step=0.25, max_step=0.25))
        states.append(model.state.x.array.copy())
        iterations.append([step.iterations for step in report.accepted])
    # to the bit on one rank; on several, MUMPS's parallel factorisation need not repeat itself to the last digit
    exact = MPI.COMM_WORLD.size == 1
    assert np.allclose(states[0], states[1], rtol=0.0, atol=0.0 if exact else 1e-12) and np.abs(states[0]).max() > 0.2
    assert iterations[0] == iterations[1] and len(iterations[0]) == 4
    assert 4 <= len(lifted) < len(residuals) / 2, (len(lifted), len(residuals), iterations)
