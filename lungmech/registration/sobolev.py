"""Shape registration of a mesh onto a segmented image by Sobolev-gradient descent.

The reference mesh Ω is mapped to ω = Φ(Ω), Φ = Id + u, so as to minimise

    Ψ(u) = ∫_ω I dx = ∫_Ω I(Φ(X)) J dX,                      J = det F, F = I + ∇u,

with I < 0 inside the segmentation and > 0 outside (:mod:`lungmech.registration.field`). Its
shape derivative (Gangl et al. 2021) is

    DΨ(u)[v] = ∫_Ω ∇I(Φ)·v J dX + ∫_Ω I(Φ) F⁻ᵀ : ∇v J dX,

and the descent direction is the Sobolev gradient g, the Riesz representative of DΨ for

    (g, v)_H = ∫_ω 2 ε(g) : ε(v) + α g·v dx                    (on the current configuration),

which is smooth even where DΨ is not: the boundary is pushed "in the right direction" while the
interior follows like an elastic body. α = 1/ℓ² sets the length ℓ below which the update is
smoothed; by default ℓ is a quarter of the mesh's diagonal. The Riesz map of this inner product
preconditions L-BFGS, whose first step is the plain Sobolev gradient.

Ψ depends on the mapped boundary only, so nodes may slide along the surface at no cost, and
how far they slide would depend on the path of the descent. A small shape-distortion energy
(isochoric neo-Hookean, zero for similarity maps) picks the least distorted mapping instead.

Steps are controlled by backtracking (Armijo), and every step is rejected that would make
det F fall below ``min_jacobian`` anywhere; the distortion energy carries a barrier on det F,
zero above j_min + (1 − j_min)/6 and infinite at j_min, so that the minimum lies inside that
limit rather than on it; when det F gets low, the interior nodes are re-placed
by the elastic extension of the boundary displacement. The descent stops when an accepted step moves no
node by more than ``step_tolerance`` voxels, or when Ψ stagnates (for a ±1 image the gradient
never vanishes, so its norm is no criterion). Either counts as converged only if the det F
limit cut none of the last ``window`` steps: a descent held by the constraint, or stopped by
the step control (no acceptable step), is reported as not converged, with the reason. It starts from a moments-based similarity fit, and
optionally goes coarse to fine through a sequence of image smoothings. Everything is collective.
On any number of MPI ranks the registered surface is the same; node positions agree to a
fraction of a voxel, as round-off differs and flat directions of Ψ let the descent amplify it.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from mpi4py import MPI
from petsc4py import PETSc

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.fem import petsc as fem_petsc

from lungmech import jit
from lungmech.errors import ParameterError, RegistrationError
from lungmech.mesh import diameter
from lungmech.registration import field as image_field
from lungmech.registration.align import Similarity, moments_fit
from lungmech.registration.image import Image

__all__ = ["Options", "Registration", "ShapeEnergy", "register"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Options:
    """Settings of :func:`register`; lengths in voxels of the image unless stated otherwise.

    Args:
        stages: Gaussian smoothing of the image function, in voxels, one descent per entry
            (coarse to fine).
        image_function: ``"distance"`` (smoothed signed distance) or ``"binary"`` (±1).
        smoothing_length: ℓ in metres, α = 1/ℓ²; ``None``: a quarter of the mesh's diagonal.
        min_jacobian: Steps making det F smaller than this anywhere are rejected.
        max_iterations: Per stage.
        step_tolerance: Converged when an accepted step moves no node by more than this.
        stagnation: Converged when Ψ fell by less than ``stagnation`` · V · h over the last
            ``window`` iterations (V the segmented volume, h the voxel size; V alone for the
            ±1 image, where Ψ is a volume).
        first_step, max_step: The largest nodal move of the first trial step, and of any step.
        memory: Number of L-BFGS correction pairs (0: plain Sobolev-gradient descent).
        regularisation: Weight of the shape-distortion energy ∫_Ω ψ_iso(F) dX, in voxels for
            the signed distance (0: the bare Ψ; then how nodes slide along the surface depends
            on the descent's path).
        relax_below: When min det F falls below this, the interior is re-placed by the elastic
            extension of the boundary displacement (if that helps).
        similarity, rotation: Start from the moments fit; with the principal-axes rotation.
        quadrature_degree: For the image terms.
        solver: PETSc options of the Sobolev-gradient solve and of the elastic extension
            (default: MUMPS LU, 2-7× faster than PETSc's own LU here).
    """

    stages: Sequence[float] = (2.0, 1.0)
    image_function: str = "distance"
    smoothing_length: float | None = None
    min_jacobian: float = 0.25
    max_iterations: int = 200
    step_tolerance: float = 0.02
    stagnation: float = 1e-5
    window: int = 5
    first_step: float = 2.0
    max_step: float = 4.0
    memory: int = 10
    regularisation: float = 1.0
    relax_below: float = 0.5
    similarity: bool = True
    rotation: bool = True
    quadrature_degree: int = 2
    solver: dict = field(
        default_factory=lambda: {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
    )

    def __post_init__(self) -> None:
        if self.image_function not in ("distance", "binary"):
            raise ParameterError(f"image_function must be 'distance' or 'binary', got {self.image_function!r}")
        if not self.stages or any(not (s >= 0) for s in self.stages):
            raise ParameterError(f"stages must be non-negative smoothings (voxels), got {list(self.stages)}")
        if self.smoothing_length is not None and not self.smoothing_length > 0:
            raise ParameterError(f"smoothing_length must be positive (metres), got {self.smoothing_length}")
        if not (np.isfinite(self.regularisation) and self.regularisation >= 0):
            raise ParameterError(f"regularisation must be non-negative, got {self.regularisation}")
        if not 0 < self.min_jacobian < 1:
            raise ParameterError(f"min_jacobian must lie in (0, 1), got {self.min_jacobian}")
        if self.memory < 0:
            raise ParameterError(f"memory must be non-negative, got {self.memory}")
        for name in ("max_iterations", "window"):
            if getattr(self, name) < 1:
                raise ParameterError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("step_tolerance", "stagnation", "first_step", "max_step"):
            if not getattr(self, name) > 0:
                raise ParameterError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class Registration:
    """The result of :func:`register`: the mapping Φ = Id + displacement of the reference mesh,
    and ``psi``, the final objective (Ψ plus the distortion term)."""

    displacement: fem.Function
    similarity: Similarity
    psi: float
    min_jacobian: float
    iterations: int
    seconds: float
    converged: bool
    stages: list[dict]
    history: list[dict]

    def summary(self) -> dict:
        return {
            "psi": self.psi,
            "min_det_F": self.min_jacobian,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "converged": self.converged,
            "stages": self.stages,
            "initial_similarity": self.similarity.as_dict(),
        }


def register(mesh: dmesh.Mesh, image: Image, options: Options = Options()) -> Registration:
    """Map ``mesh`` (the reference Ω) onto the segmentation in ``image`` (collective)."""
    start = time.perf_counter()
    if mesh.topology.cell_type.name != "tetrahedron" or mesh.geometry.dim != 3 or mesh.geometry.cmaps[0].degree != 1:
        raise RegistrationError("registration needs a 3-D mesh of straight (order 1) tetrahedra")
    degree = 1
    space = fem.functionspace(mesh, ("Lagrange", degree, (3,)))
    u = fem.Function(space, name="displacement")
    similarity = moments_fit(mesh, image, options.rotation) if options.similarity else Similarity()
    u.interpolate(lambda x: (similarity(x.T) - x.T).T)
    voxel = float(image.spacing.min())
    length = options.smoothing_length or 0.25 * diameter(mesh)
    energy = ShapeEnergy(u, 1.0 / length**2, options)
    stages: list[dict] = []
    history: list[dict] = []
    try:
        for smoothing in options.stages:
            build = image_field.signed_distance if options.image_function == "distance" else image_field.binary
            # I is a length (distance) or a number (binary): weigh the distortion alike.
            scale = voxel if options.image_function == "distance" else 1.0
            energy.use(build(image, smoothing), options.regularisation * scale)
            stage = _descend(energy, options, voxel, image.volume * scale, history)
            stages.append({"smoothing": smoothing} | stage)
            log.info(
                "registration stage (smoothing %g voxels): %d iterations, %s, min det F %.3f",
                smoothing,
                stage["iterations"],
                stage["reason"],
                stage["min_det_F"],
            )
        psi = energy.value()
        jacobian = energy.min_jacobian()
    finally:
        energy.destroy()
    return Registration(
        u,
        similarity,
        psi,
        jacobian,
        sum(s["iterations"] for s in stages),
        time.perf_counter() - start,
        stages[-1]["converged"],  # the finest stage's: the coarser ones only lead it there
        stages,
        history,
    )


def _descend(energy: ShapeEnergy, options: Options, voxel: float, scale: float, history: list) -> dict:
    """Backtracking descent on one image function, along L-BFGS directions preconditioned by
    the Sobolev inner product (the first direction is the Sobolev gradient itself)."""
    x, psi = energy.state(), energy.value()
    derivative = energy.derivative()
    pairs: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=options.memory)
    psis = [psi]
    reason, iterations = "max_iterations", 0
    held = []  # per accepted iteration: whether the det F limit cut its step (a constrained descent)
    for iterations in range(1, options.max_iterations + 1):
        direction = -_two_loop(derivative, pairs, energy)
        slope = energy.dot(derivative, direction)
        if slope >= 0.0:  # the quasi-Newton model went bad: restart from the gradient
            pairs.clear()
            direction = -energy.riesz(derivative)
            slope = energy.dot(derivative, direction)
        largest = energy.largest_move(direction)
        if largest == 0.0 or slope >= 0.0:
            reason = "stationary"
            break
        step = 1.0 if pairs else options.first_step * voxel / largest
        step = min(step, options.max_step * voxel / largest)
        limited = False
        trial: float | None
        while True:
            energy.set_state(x + step * direction)
            trial, jacobian = energy.value(), energy.min_jacobian()
            if jacobian >= options.min_jacobian and trial <= psi + 1e-4 * step * slope:
                break
            limited |= jacobian < options.min_jacobian
            step *= 0.5
            if step * largest < 1e-3 * options.step_tolerance * voxel:
                trial = None
                break
        if trial is None:
            energy.set_state(x)
            if pairs:  # retry along the plain gradient before giving up
                pairs.clear()
                continue
            if energy.relax():  # retry from a less distorted interior
                x, psi = energy.state(), energy.value()
                derivative = energy.derivative()
                continue
            reason, iterations = "line search", iterations - 1
            break
        moved = step * largest
        if jacobian < options.relax_below and energy.relax():
            x, psi, jacobian = energy.state(), energy.value(), energy.min_jacobian()
            derivative = energy.derivative()
            pairs.clear()
            psis.append(psi)
            history.append({"psi": psi, "move": moved, "min_det_F": jacobian, "relaxed": True})
            continue
        previous = derivative
        derivative = energy.derivative()
        update = step * direction
        change = derivative - previous
        if energy.dot(update, change) > 0.0:  # keep the model positive definite
            pairs.append((update, change))
        x, psi = x + update, trial
        psis.append(psi)
        # Held: the limit cut the step, and the step taken ends near it (an overshooting trial
        # far from the limit says nothing).
        held.append(limited and jacobian < options.min_jacobian + 0.1 * (1 - options.min_jacobian))
        history.append({"psi": psi, "move": moved, "min_det_F": jacobian, "held": held[-1]})
        log.debug("  %3d: Ψ = %.8e, largest move %.3g voxels, min det F %.3f", iterations, psi, moved / voxel, jacobian)
        if moved < options.step_tolerance * voxel:
            reason = "step"
            break
        if len(psis) > options.window and psis[-options.window - 1] - psi < options.stagnation * scale:
            reason = "stagnation"
            break
    # A descent whose last steps the det F limit cut stopped on the constraint, not at a minimum:
    # its small steps and flat Ψ say nothing of convergence.
    if reason in ("step", "stagnation") and any(held[-options.window :]):
        reason = f"held by the det F limit (min det F {energy.min_jacobian():.3f}, limit {options.min_jacobian:g})"
    return {
        "iterations": iterations,
        "reason": reason,
        "converged": reason in ("step", "stagnation", "stationary"),
        "psi": psi,
        "min_det_F": energy.min_jacobian(),
    }


def _two_loop(derivative: np.ndarray, pairs: deque, energy: ShapeEnergy) -> np.ndarray:
    """H̃⁻¹ · derivative for the L-BFGS inverse-Hessian model whose initial guess is the scaled
    Sobolev Riesz map (Nocedal & Wright, Algorithm 7.4)."""
    q = derivative.copy()
    alphas = []
    for s, y in reversed(pairs):
        alpha = energy.dot(s, q) / energy.dot(s, y)
        q -= alpha * y
        alphas.append(alpha)
    r = energy.riesz(q)
    if pairs:
        s, y = pairs[-1]
        r *= energy.dot(s, y) / energy.dot(y, energy.riesz(y))
    for (s, y), alpha in zip(pairs, reversed(alphas)):
        beta = energy.dot(y, r) / energy.dot(s, y)
        r += (alpha - beta) * s
    return r


class ShapeEnergy:
    """Ψ, its shape derivative and Sobolev gradient, and min det F, for the displacement u."""

    def __init__(self, u: fem.Function, alpha: float, options: Options):
        self.u = u
        mesh = u.function_space.mesh
        cell = mesh.basix_cell()
        degree = options.quadrature_degree
        self.cells = np.arange(mesh.topology.index_map(mesh.topology.dim).size_local, dtype=np.int32)
        points = np.asarray(basix.make_quadrature(cell, degree)[0])
        # I and ∇I at the quadrature points of the deformed configuration.
        self.image = fem.Function(fem.functionspace(mesh, basix.ufl.quadrature_element(cell, (), degree=degree)))
        self.image_gradient = fem.Function(
            fem.functionspace(mesh, basix.ufl.quadrature_element(cell, (3,), degree=degree))
        )
        self.dofs = self.image.function_space.dofmap.list[self.cells]
        self.field: image_field.ImageFunction | None = None

        X = ufl.SpatialCoordinate(mesh)
        F = ufl.Identity(3) + ufl.grad(u)
        J = ufl.det(F)
        self.positions = jit.expression(X + u, points)
        self.jacobian = jit.expression(J, points)
        dx = ufl.Measure("dx", mesh, metadata={"quadrature_degree": degree, "quadrature_scheme": "default"})
        v = ufl.TestFunction(u.function_space)
        g = ufl.TrialFunction(u.function_space)
        I, dI = self.image, self.image_gradient
        # A shape-distortion energy (isochoric neo-Hookean: zero for any similarity map) picks,
        # among the mappings of one boundary, the least distorted one: without it, how nodes
        # slide along the surface depends on the path of the descent.
        self.weight = fem.Constant(mesh, 0.0)
        distortion = 0.5 * (J ** (-2.0 / 3.0) * ufl.tr(F.T * F) - 3.0)
        # A barrier on det F, zero (with zero slope) above j_on and infinite at the limit: the
        # minimum then lies inside the constraint, where the descent can converge, instead of
        # on it, where where it stops depends on its path.
        low, on = options.min_jacobian, options.min_jacobian + (1.0 - options.min_jacobian) / 6.0
        distortion += ufl.conditional(ufl.lt(J, on), (on - J) ** 2 / ((J - low) * (on - low)), 0.0)
        exact = ufl.dx(domain=mesh)
        self.psi = jit.form(I * J * dx + self.weight * distortion * exact)
        self.derivative_form = jit.form(
            (ufl.dot(dI, v) + I * ufl.inner(ufl.inv(F).T, ufl.grad(v))) * J * dx
            + self.weight * ufl.derivative(distortion, u, v) * exact
        )

        def eps(w: ufl.Argument) -> ufl.core.expr.Expr:  # the symmetric gradient on the current configuration
            return ufl.sym(ufl.grad(w) * ufl.inv(F))

        self.inner = jit.form((2.0 * ufl.inner(eps(g), eps(v)) + alpha * ufl.inner(g, v)) * J * exact)
        self.matrix = fem_petsc.create_matrix(self.inner)
        self.rhs = fem_petsc.create_vector(u.function_space)
        self.gradient = self.rhs.duplicate()
        self.owned = u.function_space.dofmap.index_map.size_local * 3
        # The elastic extension of the boundary displacement (see relax), on the reference.
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim - 1, tdim)
        boundary = fem.locate_dofs_topological(u.function_space, tdim - 1, dmesh.exterior_facet_indices(mesh.topology))
        self.relaxed = fem.Function(u.function_space)
        w = ufl.TrialFunction(u.function_space)
        # The reference never moves: one matrix, factorised once.
        self.elastic = jit.form(
            (2.0 * ufl.inner(ufl.sym(ufl.grad(w)), ufl.sym(ufl.grad(v))) + ufl.div(w) * ufl.div(v)) * exact
        )
        self.boundary = [fem.dirichletbc(u, boundary)]  # the current boundary displacement
        self.extension_matrix = fem_petsc.assemble_matrix(self.elastic, bcs=self.boundary)
        self.extension_matrix.assemble()
        self.extension = _direct_solver(self.extension_matrix, options.solver, f"lungmech_extension_{id(self)}_")
        self.ksp = _direct_solver(self.matrix, options.solver, f"lungmech_registration_{id(self)}_")

    def use(self, image_function: image_field.ImageFunction, distortion: float = 0.0) -> None:
        """Minimise ∫_ω I dx + distortion · ∫_Ω ψ_iso(F) dX from now on."""
        self.field = image_function
        self.weight.value = distortion  # type: ignore[assignment]  # a Constant's value takes a number

    def _sample(self, with_gradient: bool) -> None:
        x = self.positions.eval(self.u.function_space.mesh, self.cells).reshape(-1, 3)
        if self.field is None:
            raise RegistrationError("the shape energy has no image function: call use() first")
        value, gradient = self.field(x)
        self.image.x.array[self.dofs.ravel()] = value
        if with_gradient:
            blocked = self.image_gradient.x.array.reshape(-1, 3)
            blocked[self.image_gradient.function_space.dofmap.list[self.cells].ravel()] = gradient

    def relax(self, gain: float = 0.05) -> bool:
        """Re-place the interior nodes by the linear elastic extension, from the reference, of
        the boundary displacement; keep it if min det F rises by ``gain``. Ψ depends on the
        mapped boundary only, so this undoes the interior distortion
        that the descent accumulates (affine maps, the initial similarity among them, are
        extended exactly)."""
        before, jacobian = self.state(), self.min_jacobian()
        with self.rhs.localForm() as local:
            local.set(0.0)
        fem_petsc.apply_lifting(self.rhs, [self.elastic], bcs=[self.boundary])
        self.rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
        fem_petsc.set_bc(self.rhs, self.boundary)
        self.extension.solve(self.rhs, self.relaxed.x.petsc_vec)
        self.set_state(self.relaxed.x.array[: self.owned])
        if self.min_jacobian() > jacobian + gain:
            return True
        self.set_state(before)
        return False

    def state(self) -> np.ndarray:
        """The owned displacement dofs."""
        return self.u.x.array[: self.owned].copy()

    def set_state(self, values: np.ndarray) -> None:
        self.u.x.array[: self.owned] = values
        self.u.x.scatter_forward()

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        """Σ a_i b_i over all ranks' owned dofs (a primal and a dual vector, or two alike)."""
        return self.u.function_space.mesh.comm.allreduce(float(a @ b), op=MPI.SUM)

    def largest_move(self, displacement: np.ndarray) -> float:
        """The largest nodal length of an owned displacement vector (collective)."""
        local = float(np.linalg.norm(displacement.reshape(-1, 3), axis=1).max()) if len(displacement) else 0.0
        return self.u.function_space.mesh.comm.allreduce(local, op=MPI.MAX)

    def value(self) -> float:
        """Ψ(u) (collective)."""
        self._sample(with_gradient=False)
        comm = self.u.function_space.mesh.comm
        return comm.allreduce(fem.assemble_scalar(self.psi), op=MPI.SUM)

    def min_jacobian(self) -> float:
        """The smallest det F over the quadrature points of all cells (collective)."""
        local = self.jacobian.eval(self.u.function_space.mesh, self.cells)
        comm = self.u.function_space.mesh.comm
        return comm.allreduce(float(local.min()) if local.size else np.inf, op=MPI.MIN)

    def derivative(self) -> np.ndarray:
        """The owned entries of DΨ(u)[φ_i]; also assembles the Sobolev inner product at u."""
        self._sample(with_gradient=True)
        self.matrix.zeroEntries()
        fem_petsc.assemble_matrix(self.matrix, self.inner)  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
        self.matrix.assemble()
        self.ksp.setOperators(self.matrix)
        with self.rhs.localForm() as local:
            local.set(0.0)
        fem_petsc.assemble_vector(self.rhs, self.derivative_form)  # type: ignore[arg-type]  # the into-a-vector overload, as above
        self.rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)  # type: ignore[arg-type]  # petsc4py's stubs type the enums as int
        return self.rhs.array.copy()

    def riesz(self, dual: np.ndarray) -> np.ndarray:
        """g with (g, v)_H = ⟨dual, v⟩ for all v, for the inner product of the last derivative()."""
        self.rhs.array[:] = dual
        self.ksp.solve(self.rhs, self.gradient)
        if self.ksp.getConvergedReason() < 0:  # type: ignore[operator]  # an int at run time; the stubs say a class
            raise RegistrationError(f"the Sobolev-gradient solve failed (PETSc reason {self.ksp.getConvergedReason()})")
        return self.gradient.array.copy()

    def destroy(self) -> None:
        self.ksp.destroy()
        self.extension.destroy()
        self.extension_matrix.destroy()
        self.matrix.destroy()
        self.rhs.destroy()
        self.gradient.destroy()


def _direct_solver(matrix: PETSc.Mat, settings: dict, prefix: str) -> PETSc.KSP:
    """A KSP on ``matrix`` configured from ``settings`` (PETSc options, set under ``prefix``)."""
    ksp = PETSc.KSP().create(matrix.getComm())
    ksp.setOperators(matrix)
    ksp.setOptionsPrefix(prefix)
    opts = PETSc.Options()
    for key, value in settings.items():
        opts.setValue(prefix + key, value)
    ksp.setFromOptions()
    for key in settings:
        opts.delValue(prefix + key)
    return ksp
