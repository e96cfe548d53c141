"""Polynomial bases: every field component times every monomial of the coordinates up to an order
(order 1 = affine maps, 2 = quadratic, 3 = cubic); zero on imposed dofs; orthonormalised."""

from __future__ import annotations

import itertools

from mpi4py import MPI

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.model import Model
from lungmech.parallel.layout import field_dofs, layout
from lungmech.parallel.linalg import gram_schmidt
from lungmech.parallel.owned import owned_size
from lungmech.rom.basis import Basis, inner_product, positive, zero_imposed


def polynomial_basis(model: Model, order: int, inner: str = "mass") -> Basis:
    """Monomials x^a y^b z^c, a + b + c ≤ ``order``, in centred and scaled coordinates, for each
    component of each field. Directions that the imposed displacements remove are dropped."""
    if not (isinstance(order, int) and 1 <= order <= 6):
        raise ParameterError(f"polynomial basis: order must be an integer in [1, 6] (got {order!r})")
    comm = model.geometry.mesh.comm
    owned = owned_size(model.space)
    x = model.geometry.mesh.geometry.x
    centre = comm.allreduce(x.sum(axis=0)) / comm.allreduce(len(x))
    scale = comm.allreduce(np.abs(x - centre).max(initial=0.0), op=MPI.MAX) or 1.0
    gdim = model.geometry.mesh.geometry.dim
    powers = sorted((p for p in itertools.product(range(order + 1), repeat=gdim) if sum(p) <= order), key=sum)
    fields = []
    for collapsed, parent in field_dofs(model.space):
        bs, nodes = collapsed.dofmap.index_map_bs, collapsed.dofmap.index_map.size_local
        points = (collapsed.tabulate_dof_coordinates()[:nodes, :gdim] - centre[:gdim]) / scale
        fields += [(parent[np.arange(nodes) * bs + component], points) for component in range(bs)]
    columns = []
    for power in powers:  # lowest order first, so truncation keeps the affine part
        for rows, points in fields:
            column = np.zeros(owned)
            column[rows] = np.prod(points ** np.array(power), axis=1)
            columns.append(column)
    vectors = zero_imposed(model, np.column_stack(columns))
    W = inner_product(model, inner)
    try:
        with positive(inner):
            vectors, _ = gram_schmidt(vectors, W, comm)
    finally:
        if W is not None:
            W.destroy()
    return Basis(
        vectors, np.zeros(vectors.shape[1]), "polynomial", inner, layout(model.space).fingerprint, {"order": order}
    )
