"""A reduced basis: vectors of the model's state space, orthonormal in a chosen inner product.

The vectors are the owned rows of a distributed n × k matrix (numpy, one block per rank), so a
product with a PETSc operator is one MatMatMult and a reduction to k × k is a local product and
an Allreduce. Each basis carries what it is (kind, inner product, mesh fingerprint, source) and
the importance of its vectors (singular values, eigenvalues), so it can be truncated later
without recomputing anything.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Literal, overload

from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.parallel.linalg import NotPositive, apply, gram_schmidt
from lungmech.parallel.owned import owned_size

INNER_PRODUCTS = ("l2", "mass", "energy")


@dataclass(frozen=True)
class Basis:
    """k vectors of a model's state space (owned rows), orthonormal in ``inner_product``.

    ``values`` rank the vectors (POD singular values, eigenvalues); the first ones matter most.
    """

    vectors: np.ndarray  # (owned dofs, k)
    values: np.ndarray  # (k,)
    kind: str  # "modal", "pod", "polynomial", "modal+derivatives", "enriched"
    inner_product: str
    fingerprint: str
    source: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return self.vectors.shape[1]

    def truncate(self, size: int | None = None, energy: float | None = None) -> Basis:
        """The first ``size`` vectors, or the fewest whose squared values keep the fraction
        ``energy`` of the total (POD: the captured snapshot energy)."""
        if (size is None) == (energy is None):
            raise ParameterError("truncate: give either size or energy")
        if energy is not None:
            if not 0 < energy <= 1:
                raise ParameterError(f"truncate: energy must lie in (0, 1] (got {energy})")
            if self.kind != "pod":
                raise ParameterError(f"truncate by energy needs a POD basis (this one is {self.kind})")
            captured = np.cumsum(self.values**2) / np.sum(self.values**2)
            size = int(np.searchsorted(captured, energy * (1 - 1e-14)) + 1)
        if not (isinstance(size, int | np.integer) and 1 <= size <= self.size):
            raise ParameterError(f"truncate: size must be an integer in [1, {self.size}] (got {size!r})")
        return replace(self, vectors=self.vectors[:, :size].copy(), values=self.values[:size].copy())


@overload
def inner_product(model: Model, kind: Literal["mass", "energy"]) -> PETSc.Mat: ...
@overload
def inner_product(model: Model, kind: str) -> PETSc.Mat | None: ...


def inner_product(model: Model, kind: str) -> PETSc.Mat | None:
    """The Gram operator W of ``kind`` on the state space (None for l2, i.e. W = I).

    mass: ∫ Σ_fields a·b dX; energy: the second variation of the stored energy ∫ψ at the
    unloaded state and the default parameters (on an image's motion: at rest on the image, ξ = 0) (positive definite for a stable law with enough
    imposed displacements): one norm for every parameter point, so that a basis stays
    orthonormal, and errors compare, across the box. Imposed dofs get 1 on the diagonal: basis
    vectors vanish there anyway.
    """
    if kind not in INNER_PRODUCTS:
        raise ParameterError(f"inner product must be one of {', '.join(INNER_PRODUCTS)} (got {kind!r})")
    if kind == "l2":
        return None
    a, b = ufl.TrialFunction(model.space), ufl.TestFunction(model.space)
    if kind == "mass":
        pairs = zip(ufl.split(a), ufl.split(b)) if model.multi_field else [(a, b)]
        form = sum(ufl.inner(x, y) for x, y in pairs) * ufl.dx(domain=model.geometry.mesh)  # exact quadrature
    else:
        stored = model.energy_density * model.dx
        form = ufl.derivative(ufl.derivative(stored, model.state, b), model.state, a)
    current = model.parameter_values
    reference_map = model.reference_map  # an image's motion: at rest on the image, whatever ξ it holds now
    xi = None if reference_map is None else reference_map.x.array.copy()
    with model.kept_state():
        model.set_parameters(model.parameters.defaults)
        if reference_map is not None:
            reference_map.x.array[:] = 0.0
        model.reset()
        try:
            W = assemble_matrix(jit.form(form), bcs=model.bcs, diag=1.0)
            W.assemble()
        finally:
            model.set_parameters(current)
            if reference_map is not None and xi is not None:
                reference_map.x.array[:] = xi
    return W


def require_positive_definite(model: Model, kind: str) -> None:
    """Refuse, in one line naming the way out, an inner product ``kind`` that is not positive
    definite on the model's constrained space: its Cholesky factorisation's inertia (MUMPS) has a
    negative or zero pivot (the energy of a saddle point — the mixed formulation's pressure — or
    of a body free to move rigidly). Collective; one factorisation of W."""
    W = inner_product(model, kind)
    if W is None:
        return
    ksp = PETSc.KSP().create(W.getComm())
    try:
        ksp.setOperators(W)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        factor.setMumpsIcntl(13, 1)  # the inertia over all ranks, not the root's block only
        factor.setMumpsIcntl(24, 1)  # null pivots detected (and counted)
        ksp.setUp()
        negative, zero, _ = factor.getInertia()
    finally:
        ksp.destroy()
        W.destroy()
    if negative or zero:
        raise _not_positive(kind, f"{negative} negative and {zero} zero pivots")


def _not_positive(kind: str, seen: str) -> ParameterError:
    return ParameterError(
        f"the {kind} inner product is not positive definite on this model's states ({seen}: a saddle point, as the "
        "mixed formulation's pressure, or a body free to move rigidly): use the mass inner product (--inner mass)"
    )


@contextlib.contextmanager
def positive(inner: str) -> Iterator[None]:
    """Within the block, an inner product found not positive definite
    (:class:`~lungmech.parallel.linalg.NotPositive`) is refused in one line that names the way out."""
    try:
        yield
    except NotPositive as error:
        raise _not_positive(inner, str(error)) from None


def enrich(model: Model, *bases: Basis, inner: str | None = None) -> Basis:
    """One basis spanning all of ``bases`` (in order), re-orthonormalised; repeats are dropped."""
    if not bases:
        raise ParameterError("enrich: give at least one basis")
    inner = inner or bases[0].inner_product
    if len({b.fingerprint for b in bases}) > 1:
        raise ParameterError("enrich: the bases belong to different meshes or spaces")
    comm = model.geometry.mesh.comm
    W = inner_product(model, inner)
    try:
        with positive(inner):
            vectors, kept = gram_schmidt(np.hstack([b.vectors for b in bases]), W, comm)
    finally:
        if W is not None:
            W.destroy()
    values = np.concatenate([b.values for b in bases])[kept]
    kinds = "+".join(dict.fromkeys(b.kind for b in bases))
    source = {"parts": [{"kind": b.kind, "size": b.size, **b.source} for b in bases]}
    return Basis(vectors, values, "enriched" if len(bases) > 1 else kinds, inner, bases[0].fingerprint, source)


def dual(model: Model, basis: Basis) -> np.ndarray:
    """W V, owned rows: the coordinates of a state are q = (W V)ᵀ (x − x₀), V being W-orthonormal
    (collective; one assembly of W)."""
    W = inner_product(model, basis.inner_product)
    result = apply(W, np.ascontiguousarray(basis.vectors), model.geometry.mesh.comm)
    if W is not None:
        W.destroy()
    return result


def zero_imposed(model: Model, vectors: np.ndarray) -> np.ndarray:
    """The vectors with every imposed (Dirichlet) dof set to 0: the homogeneous directions."""
    owned = vectors.shape[0]
    for bc in model.bcs:
        dofs, _ = bc.dof_indices()
        vectors[dofs[dofs < owned]] = 0.0
    return vectors


def reference_state(model: Model) -> np.ndarray:
    """The model's unloaded state (u = 0, other fields at their initial values), as an array."""
    with model.kept_state():
        model.reset()
        return model.state.x.array.copy()


def origin(model: Model, reference: np.ndarray) -> np.ndarray:
    """The affine offset of the reduced state at the model's time: the unloaded state with the
    imposed displacements set, so that origin + V q meets them for every q."""
    x = reference.copy()
    for bc in model.bcs:
        bc.set(x)
    return x


def snapshot(model: Model, start: np.ndarray) -> np.ndarray:
    """The model's state minus ``start`` (with the imposed displacements of the current time):
    one column of snapshots, owned rows."""
    owned = owned_size(model.space)
    return (model.state.x.array - origin(model, start))[:owned].copy()
