"""Functionals of the state that a reduced model has exactly, as polynomials of its coordinates.

A reduced state is affine in a few numbers, x = r + Z z (:mod:`lungmech.rom.outputs`). A
functional of the state that is a polynomial of low degree in it is then one of z, with
coefficients from a few full assemblies offline:

* :func:`cubic`: a 0-form of degree ≤ 3 in the state (the current volume ∫ det F dX: F is
  affine in the state, det a cubic; a quadratic in 2-D), from its gradient and Hessians;
* :func:`affine`: a vector functional affine in it (the mass moments ∫ ρ₀ x dX), from k + 1
  evaluations.

Each is checked at a random z, so a functional that is not of its degree is an error, not a
wrong answer.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.fem.quantities import assemble_owned
from lungmech.parallel.linalg import apply, gram

__all__ = ["Cubic", "affine", "cubic"]


@dataclass(frozen=True)
class Cubic:
    """f(z) = c₀ + c₁·z + ½ zᵀC₂z + ⅙ C₃[z, z, z], C₂ and C₃ symmetric."""

    c0: float
    c1: np.ndarray
    c2: np.ndarray
    c3: np.ndarray

    @classmethod
    def of(cls, arrays: tuple[np.ndarray, ...]) -> Cubic:
        """The cubic of its :meth:`arrays` (c₀ as a 0-d array)."""
        c0, c1, c2, c3 = arrays
        return cls(float(c0), c1, c2, c3)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(c₀, c₁, C₂, C₃) as arrays: what a model file keeps."""
        return np.array(self.c0), self.c1, self.c2, self.c3

    def __call__(self, z: np.ndarray) -> float:
        pairs = self._pairs(z)
        second, third = self.on_pairs
        return float(self.c0 + self.c1 @ z + pairs @ (0.5 * second + (third @ z) / 6))

    def gradient(self, z: np.ndarray) -> np.ndarray:
        """∂f/∂z = c₁ + C₂z + ½ C₃[·, z, z]."""
        return self.c1 + self.c2 @ z + 0.5 * (self._pairs(z) @ self.on_pairs[1])

    def _pairs(self, z: np.ndarray) -> np.ndarray:
        """zⱼ zₖ for j ≤ k."""
        j, k = self.pairs
        return z[j] * z[k]

    @functools.cached_property
    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """The index pairs j ≤ k (NumPy's ``triu_indices``) :attr:`on_pairs` is on."""
        return np.triu_indices(len(self.c1))

    @functools.cached_property
    def on_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """C₂ and C₃ on the :attr:`pairs` j ≤ k of their (symmetric) last two indices, an
        off-diagonal pair's twice: zᵀC₂z = Σ_{j≤k} C₂ⱼₖ' zⱼzₖ and C₃[·, z, z] likewise (pairs × m),
        with half the products and memory of the full C₃ — read whole at every answer, the bulk
        of one at fifty modes."""
        j, k = self.pairs
        twice = np.where(j < k, 2.0, 1.0)
        return twice * self.c2[j, k], twice[:, None] * np.moveaxis(self.c3, 0, -1)[j, k]


def cubic(model: Model, functional: ufl.Form, start: np.ndarray, directions: np.ndarray, check: float = 1e-9) -> Cubic:
    """The functional f(start + Z z) (a 0-form of ``model.state``, a polynomial of degree ≤ 3 in
    it) as a :class:`Cubic` in z, from its derivatives: ``start`` a full local state array,
    ``directions`` Z the owned rows of the directions (columns). Collective; the model's state is
    kept. A functional that is not a cubic of the state (off by more than ``check`` relative at
    a random z) is an error."""
    state, comm = model.state, model.geometry.mesh.comm
    owned, size = directions.shape
    gradient = ufl.derivative(functional, state, ufl.TestFunction(model.space))
    compiled = jit.form(functional), jit.form(gradient)
    hessian = jit.form(ufl.derivative(gradient, state, ufl.TrialFunction(model.space)))
    scratch = fem.Function(model.space).x

    def at(z: np.ndarray) -> None:
        state.x.array[:] = start
        state.x.array[:owned] += directions @ z
        state.x.scatter_forward()

    def value() -> float:
        return comm.allreduce(fem.assemble_scalar(compiled[0]), op=MPI.SUM)

    def projected_hessian() -> np.ndarray:
        H = assemble_matrix(hessian)
        H.assemble()
        reduced = gram(directions, apply(H, directions, comm), comm)
        H.destroy()
        return reduced

    with model.kept_state():
        at(np.zeros(size))
        c0 = value()
        c1 = gram(directions, assemble_owned(compiled[1], scratch, owned)[:, None], comm)[:, 0]
        c2 = projected_hessian()
        c3 = np.empty((size, size, size))
        for i in range(size):
            at(np.eye(size)[i])
            c3[i] = projected_hessian() - c2
        result = Cubic(c0, c1, c2, c3)
        z = _test_point(directions, comm)
        at(z)
        exact = value()
    off = comm.allreduce(abs(result(z) - exact), op=MPI.MAX)  # one decision for all ranks
    if off > check * max(abs(exact), abs(c0), np.finfo(float).tiny):
        raise ParameterError(
            f"this functional is not a cubic polynomial of the state (off by {off:.2e} at a test "
            "point): it cannot be reduced exactly"
        )
    return result


def affine(
    model: Model, evaluate: Callable[[], np.ndarray], start: np.ndarray, directions: np.ndarray, check: float = 1e-9
) -> tuple[np.ndarray, np.ndarray]:
    """(f₀, F₁) with f(start + Z z) = f₀ + F₁ z for a vector functional ``evaluate()`` of the
    model's state that is affine in it (e.g. ∫ρ₀ x dX): k + 2 evaluations, the last a check at
    a random z (a functional that is not affine is an error). Collective; the state is kept."""
    state, comm = model.state, model.geometry.mesh.comm
    owned, size = directions.shape

    def at(z: np.ndarray) -> np.ndarray:
        state.x.array[:] = start
        state.x.array[:owned] += directions @ z
        state.x.scatter_forward()
        return np.asarray(evaluate(), dtype=float).reshape(-1)

    with model.kept_state():
        f0 = at(np.zeros(size))
        F1 = np.column_stack([at(unit) - f0 for unit in np.eye(size)]) if size else np.zeros((f0.size, 0))
        z = _test_point(directions, comm)
        found = at(z)
        off = np.abs(found - (f0 + F1 @ z)).max(initial=0.0)
    size = max(np.abs(f0).max(initial=0.0), np.abs(found).max(initial=0.0), np.finfo(float).tiny)  # f₀ = 0 at rest
    if off > check * size:
        raise ParameterError(f"this functional is not affine in the state (off by {off:.2e} at a test point)")
    return f0, F1


def _test_point(directions: np.ndarray, comm: MPI.Comm) -> np.ndarray:
    """A random z of moderate size, the same on every rank: each direction moves the body ~10 %."""
    largest = np.empty(directions.shape[1])
    comm.Allreduce(np.abs(directions).max(axis=0, initial=0.0), largest, op=MPI.MAX)
    return np.random.default_rng(0).uniform(-0.1, 0.1, directions.shape[1]) / np.where(largest > 0, largest, 1.0)
