"""Which parts of the coupled lung problem derive from a potential: a gradient's tangent is
symmetric, so the asymmetry of the assembled tangent on the free dofs says what is not.

- The laws, dead loads, the alveolar pressure and a follower pressure on a surface whose rim is
  held (the pleura, with the hilum clamped) are conservative: the tangent is symmetric to
  round-off.
- A follower pressure on a surface with a free rim is not (the rim term of its load stiffness).
- Balanced gravity is not: with its coefficients θ frozen its pressure is conservative, but
  θ = Θ(u) follows the state, and the low-rank term U Vᵀ of the tangent is far from symmetric.
"""

from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix
from fem import MESHES

from lungmech.fem.constraints import clamp
from lungmech.fem.loads import FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.solver import Stepping, solve
from lungmech.fem.state_dependent import StateDependent
from lungmech.lung import AlveolarPressure, Gravity, Poromechanics, skeleton
from lungmech.mesh import box, from_file

QUIET = {"monitor": lambda step: None}


def asymmetry(model) -> float:
    """‖K − Kᵀ‖_F / ‖K‖_F of the tangent at the model's state (constrained rows and columns are
    the identity's, so only the free dofs count)."""
    K = assemble_matrix(fem.form(model.jacobian), bcs=model.bcs)
    K.assemble()
    difference = K.duplicate(copy=True)
    difference.transpose()  # in place
    difference.axpy(-1.0, K)
    return difference.norm() / K.norm()


def low_rank_asymmetry(model) -> float:
    """‖A − Aᵀ‖_F / ‖A‖_F of A = U Vᵀ, the state-dependent part of the tangent, on the free dofs:
    ‖A‖² = tr(UᵀU VᵀV), tr(A A) = tr((VᵀU)²) (Gram matrices: A itself is never formed)."""
    coupled = StateDependent(model)
    coupled.update()
    U, V = coupled.low_rank()
    V[model.constrained_dofs()] = 0.0
    comm = model.geometry.mesh.comm
    UU, VV, VU = (comm.allreduce(a.T @ b, op=MPI.SUM) for a, b in ((U, U), (V, V), (V, U)))
    square = np.trace(UU @ VV)
    return float(np.sqrt(max(2 * square - 2 * np.trace(VU @ VU), 0.0) / square))


SURROUNDING = ("pleura", "diaphragm", "mediastinum")  # the lung's surface but the hilum


def _lung(gravity: bool) -> Model:
    loads = [FollowerPressure(SURROUNDING, -300.0), AlveolarPressure(100.0)]
    if gravity:
        loads.append(Gravity(315.0, (0.0, 0.0, -9.81), balanced_on=SURROUNDING))
    return Model(
        from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD),
        skeleton(160.0, 0.5, 200.0, 400.0),
        formulation=Poromechanics(1e4, 0.3),
        loads=loads,
        constraints=[clamp("hilum")],
    )


def test_a_follower_pressure_on_a_held_rim_is_conservative():
    """The lung's surface under suction, the hilum clamped, the alveolar pressure: symmetric tangent."""
    model = _lung(gravity=False)
    solve(model, Stepping(), **QUIET)
    assert asymmetry(model) <= 1e-12


def test_a_follower_pressure_on_a_free_rim_is_not():
    geometry = box(MPI.COMM_WORLD, lengths=(2.0, 1.0, 1.0), cells=(4, 2, 2))
    model = Model(
        geometry, NeoHookean.from_young(10.0, 0.3), constraints=[clamp("x0")], loads=[FollowerPressure("z1", 0.5)]
    )
    solve(model, Stepping(), **QUIET)
    assert asymmetry(model) > 1e-3


@pytest.mark.slow
def test_balanced_gravity_is_not_conservative():
    """With θ frozen the tangent is symmetric; the rank-12 term U Vᵀ from θ = Θ(u) is not."""
    model = _lung(gravity=True)
    solve(model, Stepping(), **QUIET)
    assert asymmetry(model) <= 1e-12  # K: θ frozen (the balancing pressure as a pressure field)
    assert low_rank_asymmetry(model) > 0.5
