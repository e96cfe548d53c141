"""Meshes with named boundaries.

A :class:`Geometry` is a DOLFINx mesh together with its facet tags and a map from boundary
names to tag values, so that physics code can say ``geometry.ds("hilum")`` rather than
``ds(4)``. Geometries are made by :mod:`lungmech.mesh.builders` or read by
:mod:`lungmech.mesh.files`.

Measuring (``volume``, ``area``, ``size``) is collective: under MPI, call it on all ranks of the
communicator; it returns global values.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from mpi4py import MPI

import dolfinx
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
import ufl

from lungmech import jit
from lungmech.errors import GeometryError

__all__ = ["Geometry", "diameter", "from_meshdata"]


@dataclass(frozen=True, eq=False)  # eq=False: compared and hashed by identity, like the mesh
class Geometry:
    """A mesh whose boundary pieces have names.

    Args:
        mesh: The mesh.
        facet_tags: Integer markers on (some of) the facets.
        boundaries: Boundary name -> facet tag value.
        cell_tags: Optional integer markers on cells.
        source: Where the mesh came from, for messages (e.g. "mesh file 'lung.msh'").
        whole: For a piece of a body (the cells a hyper-reduced model keeps,
            :mod:`lungmech.rom.body`): the whole body's measures, ``size`` and ``volume``, which
            :attr:`size` and :meth:`volume` give instead of the piece's. None for a whole body.
    """

    mesh: dolfinx.mesh.Mesh
    facet_tags: dolfinx.mesh.MeshTags
    boundaries: Mapping[str, int]
    cell_tags: dolfinx.mesh.MeshTags | None = None
    source: str = ""
    whole: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        fdim = self.mesh.topology.dim - 1
        if self.facet_tags.dim != fdim:
            raise GeometryError(f"facet_tags are on entities of dimension {self.facet_tags.dim}, not {fdim}")
        # Read-only: the values are baked into the facet tags, so editing the map would break it.
        names = MappingProxyType({str(name): int(tag) for name, tag in self.boundaries.items()})
        object.__setattr__(self, "boundaries", names)

    def tag(self, name: str) -> int:
        """Facet tag value of the boundary called ``name``."""
        try:
            return self.boundaries[name]
        except KeyError:
            available = ", ".join(self.boundaries) or "(no named boundaries)"
            raise GeometryError(
                f"unknown boundary {name!r}; {self.source or 'this geometry'} has: {available}"
            ) from None

    def facets(self, name: str) -> npt.NDArray[np.int32]:
        """Process-local indices of the facets on boundary ``name``."""
        return self.facet_tags.find(self.tag(name))

    def ds(self, name: str | Sequence[str]) -> ufl.Measure:
        """Surface measure on boundary ``name`` (or on several), e.g. ``p * v * geometry.ds("pleura")``."""
        tags = self.tag(name) if isinstance(name, str) else tuple(self.tag(n) for n in name)
        return ufl.Measure("ds", domain=self.mesh, subdomain_data=self.facet_tags)(tags)

    def volume(self) -> float:
        """Volume of the (reference) mesh: of the whole body, for a piece of one."""
        if self.whole is not None:
            return float(self.whole["volume"])
        return _integrate(self.mesh, ufl.dx(domain=self.mesh))

    def area(self, name: str) -> float:
        """Area of boundary ``name``."""
        return _integrate(self.mesh, self.ds(name))

    @property
    def size(self) -> float:
        """Characteristic length: the diagonal of the mesh's (the whole body's) bounding box."""
        if self.whole is not None:
            return float(self.whole["size"])
        return diameter(self.mesh)


def diameter(mesh: dolfinx.mesh.Mesh) -> float:
    """The diagonal of the mesh's bounding box (collective)."""
    x = mesh.geometry.x
    # A rank may own no nodes; +-inf leave the reduction untouched.
    local = np.concatenate([x.min(axis=0), -x.max(axis=0)]) if len(x) else np.full(6, np.inf)
    bounds = np.empty_like(local)
    mesh.comm.Allreduce(np.ascontiguousarray(local, dtype=np.float64), bounds, op=MPI.MIN)
    return float(np.linalg.norm(-bounds[3:] - bounds[:3]))


def _integrate(mesh: dolfinx.mesh.Mesh, measure: ufl.Measure) -> float:
    """Global integral of 1 over ``measure``."""
    one = dolfinx.fem.Constant(mesh, dolfinx.default_scalar_type(1.0))
    local = dolfinx.fem.assemble_scalar(jit.form(one * measure))
    return float(mesh.comm.allreduce(float(np.real(local)), op=MPI.SUM))


def from_meshdata(data: Any) -> Geometry:
    """Geometry from ``dolfinx.io.gmsh`` MeshData, its boundaries named by the physical groups of
    the facets (surfaces of a 3-D mesh, curves of a 2-D one)."""
    fdim = data.mesh.topology.dim - 1
    boundaries = {name: group.tag for name, group in data.physical_groups.items() if group.dim == fdim and name}
    return Geometry(data.mesh, data.facet_tags, boundaries, data.cell_tags)
