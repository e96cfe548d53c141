"""Reduced-order models: bases (modal, POD, modal derivatives, polynomial), reduced Galerkin
Newton solves on PETSc, and reduced models saved with their metadata.

Offline: ``snapshots`` → ``pod`` (or ``modal_basis``, ``with_modal_derivatives``,
``polynomial_basis``, ``enrich``) → ``save``; hyper-reduction samples cells (:mod:`lungmech.rom.ecsw`).
Online: ``load`` → ``ReducedSolver`` (or ``HyperReducedSolver``) → the usual load stepping
(:func:`lungmech.fem.solver.solve`).
"""

from lungmech.rom.basis import Basis, enrich, inner_product
from lungmech.rom.galerkin import ReducedSolver, reduced_solver
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.modes import modal_basis, modal_derivatives, with_modal_derivatives
from lungmech.rom.pod import pod, snapshots
from lungmech.rom.polynomial import polynomial_basis
from lungmech.rom.store import load, save

__all__ = [
    "Basis",
    "HyperReducedSolver",
    "ReducedSolver",
    "enrich",
    "inner_product",
    "load",
    "modal_basis",
    "modal_derivatives",
    "pod",
    "polynomial_basis",
    "reduced_solver",
    "save",
    "snapshots",
    "with_modal_derivatives",
]
