"""Finite-strain boundary-value problems: laws, formulations, loads, imposed displacements, the
model, its Newton solver and load stepping, and quantities of interest."""

from lungmech.fem.constraints import Displacement, clamp, symmetry
from lungmech.fem.formulations import PureDisplacement, TaylorHood
from lungmech.fem.loads import BodyForce, FollowerPressure, Traction
from lungmech.fem.materials import (
    CiarletGeymonat,
    ExponentialCiarletGeymonat,
    LinearElastic,
    MooneyRivlin,
    NeoHookean,
    SaintVenantKirchhoff,
    StableNeoHookean,
    Sum,
    lame_from_young,
)
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, deformed_volume, reaction, strain_energy
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonOptions, NewtonResult, NewtonSolver, Solver, Stepping, solve

__all__ = [
    "BodyForce",
    "CiarletGeymonat",
    "Displacement",
    "ExponentialCiarletGeymonat",
    "FollowerPressure",
    "LinearElastic",
    "Model",
    "MooneyRivlin",
    "NeoHookean",
    "NewtonOptions",
    "NewtonResult",
    "NewtonSolver",
    "Probe",
    "PureDisplacement",
    "Ramp",
    "SaintVenantKirchhoff",
    "Solver",
    "StableNeoHookean",
    "Stepping",
    "Sum",
    "TaylorHood",
    "Traction",
    "clamp",
    "deformed_volume",
    "lame_from_young",
    "reaction",
    "solve",
    "strain_energy",
    "symmetry",
]
