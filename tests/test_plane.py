"""2-D bodies: plane strain and plane stress against the same 3-D body.

Independent reference: a homogeneous uniaxial stretch is exact on any mesh, in 2-D and in 3-D. A
3-D block with its z faces held (u_z = 0) is in plane strain; a 3-D block with its z faces free is
in plane stress. The 2-D model must give the same lateral stretch, thickness stretch and energy
per unit thickness, for every law.
"""

from mpi4py import MPI

import numpy as np
import pytest

from lungmech.errors import ParameterError
from lungmech.fem.constraints import Displacement, clamp, symmetry
from lungmech.fem.formulations import TaylorHood
from lungmech.fem.loads import Traction
from lungmech.fem.materials import LinearElastic, MooneyRivlin, NeoHookean, SaintVenantKirchhoff
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe, deformed_volume, strain_energy
from lungmech.fem.solver import NewtonOptions, Stepping, solve
from lungmech.lung import skeleton
from lungmech.mesh import box, cook_membrane, rectangle

STRETCH = 0.3  # u_x on x = 1 of a unit square / cube
LAWS = {
    "neo-Hookean": NeoHookean.from_young(1.0, 0.3),
    "Mooney-Rivlin": MooneyRivlin.from_young(1.0, 0.35),
    "Saint Venant-Kirchhoff": SaintVenantKirchhoff.from_young(1.0, 0.25),
    "lung skeleton": skeleton(0.16, 0.5, 0.2, 0.4),
}


def _uniaxial(geometry, law, plane=None, held_z=False) -> Model:
    constraints = [symmetry("x0", "x"), symmetry("y0", "y"), Displacement("x1", STRETCH, "x")]
    if geometry.mesh.geometry.dim == 3:
        constraints += [symmetry("z0", "z")] + ([symmetry("z1", "z")] if held_z else [])
    model = Model(geometry, law, constraints=constraints, plane=plane)
    solve(model, Stepping(), monitor=lambda step: None)
    return model


def _lateral_stretch(model) -> float:
    """1 + u_y/y at the node (1, 1): the body is homogeneous."""
    space = model.displacement_space if not model.multi_field else model.displacement_space.collapse()[0]
    x = space.tabulate_dof_coordinates()
    corner = np.flatnonzero(np.all(np.isclose(x[:, :2], 1.0), axis=1))
    u = model.displacement().x.array.reshape(-1, model.geometry.mesh.geometry.dim)
    found = [1.0 + u[corner[0], 1]] if corner.size else []
    values = MPI.COMM_WORLD.allgather(found)
    return next(v[0] for v in values if v)


@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
def test_plane_strain_is_the_3d_body_with_its_faces_held(law):
    flat = _uniaxial(rectangle(MPI.COMM_WORLD, cells=(2, 2)), law, plane="strain")
    solid = _uniaxial(box(MPI.COMM_WORLD, cells=(2, 2, 1)), law, held_z=True)
    assert _lateral_stretch(flat) == pytest.approx(_lateral_stretch(solid), rel=1e-9)
    assert strain_energy(flat)() == pytest.approx(strain_energy(solid)(), rel=1e-9)
    assert deformed_volume(flat)() == pytest.approx(deformed_volume(solid)(), rel=1e-9)
    assert abs(_lateral_stretch(flat) - 1) > 1e-3  # the law does contract sideways


@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
def test_plane_stress_is_the_3d_plate_with_its_faces_free(law):
    flat = _uniaxial(rectangle(MPI.COMM_WORLD, cells=(2, 2)), law, plane="stress")
    solid = _uniaxial(box(MPI.COMM_WORLD, cells=(2, 2, 1)), law)
    assert _lateral_stretch(flat) == pytest.approx(_lateral_stretch(solid), rel=1e-9)
    assert strain_energy(flat)() == pytest.approx(strain_energy(solid)(), rel=1e-9)
    assert deformed_volume(flat)() == pytest.approx(deformed_volume(solid)(), rel=1e-9)
    thickness = flat.state.sub(1).collapse().x.array
    assert np.allclose(thickness, thickness[0]) and abs(thickness[0] - 1) > 1e-3


@pytest.mark.slow
def test_plane_stress_differs_from_plane_strain():
    law = LAWS["neo-Hookean"]
    strain = _uniaxial(rectangle(MPI.COMM_WORLD, cells=(2, 2)), law, plane="strain")
    stress = _uniaxial(rectangle(MPI.COMM_WORLD, cells=(2, 2)), law, plane="stress")
    assert strain_energy(stress)() < 0.99 * strain_energy(strain)()  # free faces: a softer body


def test_linear_cook_membrane_in_plane_stress_matches_the_classical_value():
    """E = 1, ν = 1/3, total shear 1 on x = 48: v(48, 52) = 23.96 (VERIFICATION.md), P2."""
    geometry = cook_membrane(MPI.COMM_WORLD, cells=(16, 16))
    model = Model(
        geometry,
        LinearElastic.from_young(1.0, 1.0 / 3.0),
        degree=2,
        plane="stress",
        constraints=[clamp("clamped")],
        loads=[Traction("loaded", (0.0, 1.0 / 16.0))],
    )
    solve(model, Stepping(), monitor=lambda step: None)
    v = Probe(geometry.mesh, [[48.0, 52.0]])(model.displacement())[0, 1]
    assert v == pytest.approx(23.96, rel=2e-3)


def test_plane_stress_iterative_condenses_the_thickness_stretch():
    """P1 plane stress: λ₃ in DG0 is cell-local, condensed like the lung's Φs; the iterative
    solver reaches the direct solver's state. (Lamé's cylinder: tests/test_loads.py.)"""
    states = []
    for linear_solver in ("direct", "iterative"):
        model = Model(
            cook_membrane(MPI.COMM_WORLD, cells=(8, 8)),
            NeoHookean.from_young(10.0, 0.3),
            plane="stress",
            constraints=[clamp("clamped")],
            loads=[Traction("loaded", (0.0, 0.125))],
        )
        solve(model, Stepping(), NewtonOptions(linear_solver=linear_solver), monitor=lambda step: None)
        states.append(model.state.x.array.copy())
    assert np.allclose(states[1], states[0], rtol=0, atol=1e-10 * np.abs(states[0]).max())


def test_two_dimensional_inputs_are_checked():
    flat = rectangle(MPI.COMM_WORLD, cells=(1, 1))
    law = NeoHookean.from_young(1.0, 0.3)
    with pytest.raises(ParameterError, match="a 2-D mesh needs plane = 'strain'"):
        Model(flat, law)
    with pytest.raises(ParameterError, match="is for 2-D meshes; this mesh is 3-D"):
        Model(box(MPI.COMM_WORLD, cells=(1, 1, 1)), law, plane="strain")
    with pytest.raises(ParameterError, match="plane stress works with the displacement formulation only"):
        Model(flat, law, degree=2, formulation=TaylorHood(), plane="stress")
    with pytest.raises(ParameterError, match="its value has 3 components, the mesh is 2-D"):
        Model(flat, law, plane="strain", loads=[Traction("x1", (0.0, 0.0, 1.0))])
    with pytest.raises(ParameterError, match="component z does not exist on a 2-D mesh"):
        Model(flat, law, plane="strain", constraints=[symmetry("x0", "z")])
