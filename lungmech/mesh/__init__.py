"""Meshes with named boundaries: the :class:`Geometry`, its builders, mesh files, and its nodes.

``geometry`` (the class and its measures) · ``builders`` (box, rectangle, Cook's membrane, quarter annulus, plate with holes, sphere, ellipsoid, lung phantom) ·
``files`` (.msh in; .vtu and .xdmf in and out), ``vtu`` (the mesh file every tool opens) · ``nodes`` (the one owner of node moves) · ``lung_shape``.
"""

from lungmech.mesh.builders import (
    box,
    cook_membrane,
    ellipsoid,
    lung_phantom,
    plate_with_holes,
    quarter_annulus,
    rectangle,
    sphere,
)
from lungmech.mesh.files import companions, from_file, is_lungmech_mesh, write
from lungmech.mesh.geometry import Geometry, diameter
from lungmech.mesh.lung_shape import LungShape
from lungmech.mesh.nodes import node_dofs

__all__ = [
    "Geometry",
    "LungShape",
    "box",
    "companions",
    "cook_membrane",
    "diameter",
    "ellipsoid",
    "from_file",
    "is_lungmech_mesh",
    "lung_phantom",
    "node_dofs",
    "plate_with_holes",
    "quarter_annulus",
    "rectangle",
    "sphere",
    "write",
]
