"""The lung: the poromechanical model of Patte, Genet & Chapelle (2022) with its output fields,
gravity balanced by pleural pressure, and the inverse (unloaded-configuration) problem."""

from lungmech.lung.gravity import Gravity
from lungmech.lung.inverse import Imaged, InverseOptions, InverseReport, node_displacements, unloaded_reference
from lungmech.lung.poromechanics import (
    AlveolarPressure,
    Poromechanics,
    averages,
    fields,
    reference_fraction,
    skeleton,
    stresses,
)
from lungmech.lung.pressure import PressureAxis, pressure_axis

__all__ = [
    "AlveolarPressure",
    "Gravity",
    "Imaged",
    "InverseOptions",
    "InverseReport",
    "Poromechanics",
    "PressureAxis",
    "averages",
    "fields",
    "node_displacements",
    "pressure_axis",
    "reference_fraction",
    "skeleton",
    "stresses",
    "unloaded_reference",
]
