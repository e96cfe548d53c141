"""The lung: the poromechanical model of Patte, Genet & Chapelle (2022) with its output fields,
gravity balanced by pleural pressure, and the inverse (unloaded-configuration) problem."""

from lungmech.lung.gravity import Gravity
from lungmech.lung.inverse import InverseOptions, InverseReport, node_displacements, unloaded_reference
from lungmech.lung.poromechanics import (
    AlveolarPressure,
    Poromechanics,
    averages,
    fields,
    reference_fraction,
    skeleton,
    stresses,
)

__all__ = [
    "AlveolarPressure",
    "Gravity",
    "InverseOptions",
    "InverseReport",
    "Poromechanics",
    "averages",
    "fields",
    "node_displacements",
    "reference_fraction",
    "skeleton",
    "stresses",
    "unloaded_reference",
]
