"""Why a load path ended: an inverted cell, a loss of stability, or neither.

When the load stepping cannot go on even with its smallest step, the reason is usually physical.
Two are recognised:

* **an inverted cell**: J = det F ≤ 0 (or undefined) somewhere in the last Newton iterate — the
  load or the law drives an element through itself;
* **a loss of stability**: the body's response to the load runs away — its tangent
  compliance along the load, |K⁻¹ ∂R/∂t| on the displacement, has grown at least 10 times
  since the start of the load path (Bergan's current stiffness parameter below 0.1): a limit
  point, past which it cannot carry more of this load (an inflated rubber balloon, say); or the
  tangent stiffness K has (nearly) lost its smallest eigenvalue, |λ_min(K)| ≤ 5 % of its value
  at rest: a bifurcation.

λ_min is the eigenvalue of K nearest 0 on the free dofs (SLEPc, shift-and-invert with MUMPS);
"at rest" means the unloaded state of the same model. Everything here is collective.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING

from petsc4py import PETSc

import basix
import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.fem.linear import factorised, use_lu

if TYPE_CHECKING:
    from mpi4py import MPI

    import dolfinx.mesh

    from lungmech.fem.model import Model
    from lungmech.fem.solver_interface import Solver

__all__ = [
    "RUNAWAY",
    "STABILITY_LOST",
    "Inversion",
    "at_quadrature_points",
    "compliance",
    "diagnose",
    "displacement_gradient",
    "min_jacobian",
    "quadrature_degree",
    "smallest",
    "smallest_eigenvalue",
]

STABILITY_LOST = 0.1  # |λ_min| below this fraction of its value at rest
RUNAWAY = 10.0  # the load path's compliance grew this many times


def at_quadrature_points(
    expression: ufl.core.expr.Expr,
    mesh: dolfinx.mesh.Mesh,
    degree: int,
    cells: np.ndarray | None = None,
    entity_maps: list[dolfinx.mesh.EntityMap] | None = None,
) -> Callable[[], np.ndarray]:
    """A function returning ``expression`` at the degree-``degree`` quadrature points of the
    owned cells of ``mesh`` (or of ``cells``, local indices), shaped (cells, points) + the value
    shape; ``entity_maps`` reach coefficients of a parent mesh (a submesh's)."""
    points, _ = basix.make_quadrature(basix.CellType[mesh.topology.cell_name()], max(degree, 1))
    points = np.asarray(points)  # an array already: basix's hint says any array-like
    compiled = jit.expression(expression, points, entity_maps=entity_maps)
    if cells is None:
        cells = np.arange(mesh.topology.index_map(mesh.topology.dim).size_local, dtype=np.int32)
    shape = (len(cells), len(points), *expression.ufl_shape)
    return lambda: compiled.eval(mesh, cells).reshape(shape)


def quadrature_degree(model: Model) -> int:
    """The quadrature degree of the model's cell integrals (2 if it leaves it to UFL)."""
    return model.dx.metadata().get("quadrature_degree", 2)


def smallest(values: Callable[[], np.ndarray], comm: MPI.Comm) -> Callable[[], float]:
    """A function returning the smallest of ``values()`` over all ranks (nan if any is nan or
    infinite; collective)."""

    def evaluate() -> float:
        found = values()
        local = float(np.min(found)) if found.size else np.inf
        if found.size and not np.isfinite(found).all():
            local = np.nan
        every = comm.allgather(local)
        return np.nan if any(np.isnan(v) for v in every) else float(min(every))

    return evaluate


def min_jacobian(model: Model, cells: np.ndarray | None = None) -> Callable[[], float]:
    """A function returning the smallest J = det F at the quadrature points of the owned cells
    (or of ``cells``) (nan if undefined; collective)."""
    mesh = model.geometry.mesh
    return smallest(at_quadrature_points(ufl.det(model.F), mesh, quadrature_degree(model), cells), mesh.comm)


def displacement_gradient(model: Model) -> Callable[[], np.ndarray]:
    """A function returning F = I + ∇u at this rank's quadrature points, (cells, points, d, d);
    compiled once per model."""
    if model not in _gradients:
        _gradients[model] = at_quadrature_points(model.F, model.geometry.mesh, quadrature_degree(model))
    return _gradients[model]


_gradients: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class Inversion:
    """Whether the model's state turns a cell inside out: J = det F ≤ 0 (or undefined) at a
    quadrature point. Such a state is no equilibrium of a real body, even where a law without a
    barrier on J (Saint Venant–Kirchhoff) balances it. Small-strain laws are not checked.
    ``smallest`` returns the smallest J where the state is checked (default: every owned cell's
    quadrature points, :func:`min_jacobian`); a hyper-reduced model checks its sample."""

    def __init__(self, model: Model, smallest: Callable[[], float] | None = None) -> None:
        self._smallest = None
        if not getattr(model.material, "small_strain", False):
            self._smallest = smallest or min_jacobian(model)

    def __call__(self) -> str:
        """ "" for a state without inverted cells, else what is wrong with it (collective)."""
        if self._smallest is None:
            return ""
        smallest = self._smallest()
        if smallest > 0:
            return ""
        return f"an inverted state (smallest J = det F = {smallest:.3g}), not an equilibrium of a real body"


def smallest_eigenvalue(model: Model, jacobian: fem.Form) -> float:
    """The real part of the eigenvalue of the tangent nearest 0, on the free dofs (collective)."""
    from slepc4py import SLEPc

    K = assemble_matrix(jacobian, bcs=model.bcs, diag=1.0)
    K.assemble()
    # Constrained rows hold 1 on the diagonal: lift them far above the spectrum near 0.
    rows = K.getOwnershipRange()[0] + model.constrained_dofs()
    K.zeroRowsColumns(rows.astype(PETSc.IntType), diag=1e6 * K.norm(PETSc.NormType.NORM_INFINITY))
    eps = SLEPc.EPS().create(model.geometry.mesh.comm)
    eps.setOperators(K)
    eps.setProblemType(SLEPc.EPS.ProblemType.NHEP)
    eps.setDimensions(1, 12)
    eps.setTolerances(1e-6, 100)
    eps.setTarget(0.0)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    st = eps.getST()
    st.setType(SLEPc.ST.Type.SINVERT)
    use_lu(st.getKSP())
    try:
        eps.solve()
        value = eps.getEigenvalue(0).real if eps.getConverged() > 0 else 0.0
    except Exception:  # noqa: BLE001 - an exactly singular tangent: the factorisation breaks down
        value = 0.0
    finally:
        eps.destroy()
        K.destroy()
    return float(value)


def compliance(
    model: Model, residual: fem.Form, jacobian: fem.Form, drive: Callable[[float], None], t: float, delta: float
) -> float:
    """|K⁻¹ ∂R/∂t| on the displacement at the model's state and time t (collective): how far the
    body moves per unit of load time. ∂R/∂t is a difference quotient over ``delta``."""
    from dolfinx.fem.petsc import assemble_vector

    constrained = model.constrained_dofs()

    def residual_at(time: float) -> PETSc.Vec:
        drive(time)
        vector = assemble_vector(residual)
        vector.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
        vector.getArray()[constrained] = 0.0
        return vector

    rate = residual_at(t + delta)
    rate.axpy(-1.0, residual_at(t))
    rate.scale(1.0 / delta)
    drive(t)
    K = assemble_matrix(jacobian, bcs=model.bcs, diag=1.0)
    K.assemble()
    ksp = factorised(K)
    response = rate.duplicate()
    try:
        ksp.solve(rate, response)
        moved = response.getArray(readonly=True)[model.field_dofs()["u"]]
        value = float(np.sqrt(model.geometry.mesh.comm.allreduce(float(moved @ moved))))
    finally:
        for obj in (ksp, K, rate, response):
            obj.destroy()
    return value


def diagnose(
    model: Model,
    solver: Solver,
    drive: Callable[[float], None],
    t: float,
    start: tuple[np.ndarray, float],
    failed_min_jacobian: float,
    tried: float | None = None,
) -> str:
    """What stopped the load path at ``t``, for a failure message ("" if nothing physical).

    ``model`` holds the last converged state at ``t``; ``start`` is the state and time the path
    began from; ``failed_min_jacobian`` the smallest J of the failed iterate, at the time
    ``tried``. ``solver`` gives the compiled forms (``residual_form``, ``jacobian_form``). The
    model's state and time are restored. A load's formula that is not finite then is named first.
    """
    for load in model.loads:
        check = getattr(load, "undefined", None)  # loads with formulas say where they leave the reals
        if check is not None and (undefined := check(model, (t,) if tried is None else (t, tried))):
            return undefined
    if not model.bcs:
        return (
            "nothing holds the body (no imposed displacement), so it can move rigidly and its tangent is "
            "singular: clamp a boundary, or impose symmetry conditions"
        )
    # A limit point or a bifurcation is the cause, an iterate thrown inside out past it only the
    # symptom: stability is judged first, at the last converged state.
    stability = _stability(model, solver, drive, t, start)
    if stability:
        return stability
    if not failed_min_jacobian > 0:  # <= 0 or nan
        shown = "undefined (nan)" if np.isnan(failed_min_jacobian) else f"{failed_min_jacobian:.3g}"
        return (
            f"an element inverted: J = det F reached {shown} in the last Newton iterate (the load is too large "
            "for the material there, or the mesh too coarse)"
        )
    return ""


def _stability(
    model: Model, solver: Solver, drive: Callable[[float], None], t: float, start: tuple[np.ndarray, float]
) -> str:
    """A loss of stability at the model's (last converged) state, or ""."""
    state, begin = start
    delta = 1e-6 * max(abs(t - begin), 1.0)
    try:
        now = compliance(model, solver.residual_form, solver.jacobian_form, drive, t, delta)
        with model.kept_state():
            model.state.x.array[:] = state
            model.state.x.scatter_forward()
            before = compliance(model, solver.residual_form, solver.jacobian_form, drive, begin, delta)
        drive(t)
        if before > 0 and now / before >= RUNAWAY:
            return (
                f"loss of stability: the body's response to the load is running away (its tangent compliance "
                f"along the load grew {now / before:.0f} times since the start: a limit point, past which it "
                "cannot carry more of this load)"
            )
        loaded = smallest_eigenvalue(model, solver.jacobian_form)
        with model.kept_state():
            model.reset()
            model.set_time(t, load_factor=0.0)
            unloaded = smallest_eigenvalue(model, solver.jacobian_form)
    except Exception:  # noqa: BLE001 - a diagnosis must not hide the failure it explains
        return ""
    finally:
        drive(t)
    if unloaded != 0 and loaded / unloaded < 0:
        return (
            "loss of stability: the tangent stiffness has an eigenvalue of the wrong sign (buckling, or a bifurcation)"
        )
    if unloaded != 0 and loaded / unloaded < STABILITY_LOST:
        return (
            f"loss of stability: the tangent stiffness kept {100 * loaded / unloaded:.2g} % of its smallest "
            "eigenvalue at rest (buckling, or a bifurcation)"
        )
    return ""
