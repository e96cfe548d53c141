"""The body's shape as parameters (lungmech.fem.shape): a model written on a template mesh with
shape modes is, at any coefficients a, the model on the template's mesh moved by Σ aᵢ mᵢ.

Independent reference: the same model built on a second copy of the template whose nodes are
moved (``lungmech.mesh.nodes.move_nodes``) — no shape map, the forms lungmech always wrote.
With modes of the mesh's degree the two are one discrete problem: energy, residual and tangent
agree to round-off at any state, and the solutions to Newton's tolerance. Both ranks' parts of
the mesh are alike in the two copies (the same mesh made twice), so it also holds on 2 ranks.
"""

from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix, assemble_vector
from fem import MESHES

from lungmech.errors import ParameterError
from lungmech.fem.constraints import clamp
from lungmech.fem.loads import BodyForce, FollowerPressure
from lungmech.fem.materials import NeoHookean
from lungmech.fem.model import Model
from lungmech.fem.parameters import HalfSpace, Parameter
from lungmech.fem.placement import Image
from lungmech.fem.quantities import deformed_volume, integral
from lungmech.fem.solver import solve
from lungmech.mesh import box, from_file, nodes
from lungmech.mesh.nodes import move_nodes
from lungmech.parallel.owned import owned_size
from lungmech.registration.library import shape_modes

A = {"a1": 0.6, "a2": -0.8}
SURROUNDING = ("pleura", "diaphragm", "mediastinum")


def modes_of(mesh, formulas):
    """Vector P1 fields (the mesh's own degree) interpolated from ``formulas`` (x → values)."""
    space = fem.functionspace(mesh, ("Lagrange", 1, (mesh.geometry.dim,)))
    modes = []
    for formula in formulas:
        mode = fem.Function(space)
        mode.interpolate(formula)
        modes.append(mode)
    return modes


def box_modes(scale):
    return [
        lambda x: np.stack([0.2 * x[0] * x[1], 0.1 * x[2] ** 2, -0.15 * x[0]]) * scale,
        lambda x: np.stack([0.05 * x[2], 0.3 * np.sin(x[0]), 0.1 * x[1] * x[2]]) * scale,
    ]


def parameters(count, bound=1.0):
    return [Parameter(f"a{i}", f"shape.mode_{i}", 0.0, (-bound, bound)) for i in range(1, count + 1)]


def moved(make_geometry, formulas, values):
    """The template's mesh with its nodes moved by Σ aᵢ mᵢ."""
    geometry = make_geometry()
    displacement = fem.Function(modes_of(geometry.mesh, formulas)[0].function_space)
    for mode, a in zip(modes_of(geometry.mesh, formulas), values):
        displacement.x.array[:] += a * mode.x.array
    move_nodes(displacement)
    return geometry


def pair(make_geometry, formulas, build):
    """(the model on the template with the shape map at A, the model on the moved mesh)."""
    template = make_geometry()
    on_template = build(template, shape=modes_of(template.mesh, formulas), parameters=parameters(len(formulas)))
    on_template.set_parameters(A)
    on_moved = build(moved(make_geometry, formulas, list(A.values())))
    assert np.array_equal(template.mesh.geometry.dofmaps[0], on_moved.geometry.mesh.geometry.dofmaps[0])
    return on_template, on_moved


def assembled(model, state):
    """(energy, residual, tangent) of ``model`` at ``state`` (this rank's dof values)."""
    model.state.x.array[:] = state
    model.state.x.scatter_forward()
    energy = integral(model.potential, model.geometry.mesh.comm)()
    residual = assemble_vector(fem.form(model.residual))
    residual.ghostUpdate(addv=2, mode=1)  # ADD, REVERSE
    tangent = assemble_matrix(fem.form(model.jacobian))
    tangent.assemble()
    return energy, residual, tangent


def agree(first, second, state):
    e1, r1, k1 = assembled(first, state)
    e2, r2, k2 = assembled(second, state)
    assert e1 == pytest.approx(e2, rel=1e-12)
    assert (r1 - r2).norm() <= 1e-12 * r2.norm()
    k1.axpy(-1.0, k2)
    assert k1.norm() <= 1e-12 * k2.norm()


def rubber(geometry, **keywords):
    return Model(
        geometry,
        NeoHookean.from_young(1e3, 0.3),
        degree=2,
        loads=[FollowerPressure("x1", 40.0), BodyForce([0.0, 0.0, -30.0])],
        constraints=[clamp("x0")],
        **keywords,
    )


def smooth_state(model, amplitude):
    """The model's unloaded state with a smooth displacement (m): the same dof values on any
    copy of the mesh."""
    state = fem.Function(model.space)
    state.x.array[:] = model.state.x.array  # the other fields at their initial values (Φs = Φs0)
    u = state.sub(0) if model.multi_field else state
    u.interpolate(lambda x: amplitude * np.stack([x[1] * x[2], np.sin(x[0]), x[0] * x[1]]))
    return state.x.array.copy()


def cube():
    return box(MPI.COMM_WORLD, cells=(3, 3, 3))


def test_a_rubber_cube_on_its_template_is_the_cube_on_the_moved_mesh():
    on_template, on_moved = pair(cube, box_modes(1.0), rubber)
    agree(on_template, on_moved, smooth_state(on_moved, 0.05))
    solve(on_template), solve(on_moved)
    u1, u2 = on_template.state.x.array, on_moved.state.x.array
    assert np.abs(u1 - u2).max() <= 1e-8 * np.abs(u2).max()
    assert deformed_volume(on_template)() == pytest.approx(deformed_volume(on_moved)(), rel=1e-10)


@pytest.mark.parametrize("image", [Image.motion(), Image.inverse()], ids=["motion", "inverse"])
def test_an_imaged_cube_on_its_template_is_the_imaged_cube_on_the_moved_mesh(image):
    """The template's map composed with an image's inverse motion: the breath from the image
    (with a reference map ξ) and the image's own equilibrium (ξ the unknown)."""
    on_template, on_moved = pair(cube, box_modes(1.0), lambda geometry, **k: rubber(geometry, image=image, **k))
    if image.unknown == "motion":
        xi = smooth_state(on_moved, -0.03)[: owned_size(on_moved.space)]
        on_template.set_reference_map(xi), on_moved.set_reference_map(xi)
    agree(on_template, on_moved, smooth_state(on_moved, 0.04))


@pytest.mark.parametrize("start", ["inverse_motion", "fixed_point"])
def test_an_imaged_cube_s_image_and_reference_on_its_template_are_the_moved_mesh_s(start):
    """The imaged cube's volumes as its start reports them — the image's, and the unloaded
    reference's found at μ, on the fixed image (InverseMotion) or by moving the mesh's nodes
    (Imaged, whose shape modes ride on the nodes) — at the template's shape."""
    from lungmech.fem.inverse_motion import InverseMotion
    from lungmech.fem.parametric import FullOrderModel
    from lungmech.fem.solver import Stepping
    from lungmech.lung.inverse import Imaged, InverseOptions

    motion = start == "inverse_motion"
    build = lambda geometry, **k: rubber(geometry, image=Image.motion(1.0) if motion else None, **k)  # noqa: E731
    on_template, on_moved = pair(cube, box_modes(1.0), build)
    found = []
    for model, mu in ((on_template, A), (on_moved, {})):
        first = InverseMotion(model) if motion else Imaged(model, InverseOptions(tolerance=1e-10))
        stepping = Stepping(start=1.0, end=1.05)  # the image, loaded at t = 1 s, then a little more
        found.append(FullOrderModel(model, stepping, start=first).solve(mu).start.details)
    template, exact = found
    assert template["imaged_volume"] == pytest.approx(exact["imaged_volume"], rel=1e-12)
    assert template["reference_volume"] == pytest.approx(exact["reference_volume"], rel=1e-8)
    assert abs(exact["reference_volume"] - exact["imaged_volume"]) > 1e-3 * exact["imaged_volume"]  # loaded


def test_zones_by_height_move_with_the_shape():
    zone = HalfSpace(normal=(0.0, 0.0, 1.0), position=0.4, width=0.05)

    def zoned(geometry, **keywords):
        stiffer = Parameter("mu_low", "material.mu", 3e3, (1e2, 1e4), region=zone, outside=400.0)
        keywords["parameters"] = [*keywords.get("parameters", []), stiffer]
        return rubber(geometry, **keywords)

    on_template, on_moved = pair(cube, box_modes(1.0), zoned)
    agree(on_template, on_moved, smooth_state(on_moved, 0.05))


def test_changing_the_shape_compiles_nothing():
    template = cube()
    model = rubber(template, shape=modes_of(template.mesh, box_modes(1.0)), parameters=parameters(2))
    signatures = model.residual.signature(), model.jacobian.signature()
    before = fem.assemble_scalar(fem.form(ufl.det(model.F) * model.dx))
    model.set_parameters(A)
    assert (model.residual.signature(), model.jacobian.signature()) == signatures
    assert fem.assemble_scalar(fem.form(ufl.det(model.F) * model.dx)) != before  # it did change the body


def test_a_shape_that_folds_a_cell_is_refused_naming_it():
    """Every corner of the shape box is checked when the model is made (the first that folds
    is named); a box whose corners keep every cell is taken."""
    template = cube()
    with pytest.raises(ParameterError, match=r"the shape at a1 = -?1, a2 = -?1 folds the mesh: det ∇χ = -\d"):
        rubber(template, shape=modes_of(template.mesh, box_modes(10.0)), parameters=parameters(2))
    model = rubber(template, shape=modes_of(template.mesh, box_modes(10.0)), parameters=parameters(2, bound=0.05))
    assert model.shape.values() == pytest.approx([0.0, 0.0])  # back at the defaults after the corners


@pytest.mark.parametrize(
    "target, message",
    [("shape.mode_3", r"target shape.mode_3 is not a shape mode \(its modes are shape.mode_1, shape.mode_2\)")],
)
def test_a_shape_parameter_names_one_of_the_models_modes(target, message):
    template = cube()
    with pytest.raises(ParameterError, match=message):
        rubber(
            template, shape=modes_of(template.mesh, box_modes(1.0)), parameters=[Parameter("a", target, 0.0, (-1, 1))]
        )
    with pytest.raises(ParameterError, match="the model has no shape modes"):
        rubber(template, parameters=[Parameter("a", "shape.mode_1", 0.0, (-1, 1))])


def lung():
    return from_file(MESHES / "lung_phantom_right.msh", MPI.COMM_WORLD)


def population():
    """Shape modes of 6 synthetic lungs (two smooth changes of a few mm, mixed at random)."""
    geometry = lung()
    comm = geometry.mesh.comm
    space, where = nodes.displacement_space(geometry.mesh)
    X = comm.bcast(nodes.positions(space, where))
    weights = comm.bcast(nodes.masses(space, where))
    centred = (X - X.mean(axis=0)) / 0.1
    changes = [
        0.004 * np.column_stack([centred[:, 0] * centred[:, 2], np.zeros(len(X)), centred[:, 2] ** 2]),
        0.003 * np.column_stack([np.sin(3 * centred[:, 1]), centred[:, 0] ** 2, np.zeros(len(X))]),
    ]
    latent = np.random.default_rng(3).normal(size=(6, 2))
    members = [np.einsum("k,knd->nd", z, np.array(changes)) for z in latent]
    return shape_modes(X, members, weights, where.fingerprint)


@pytest.mark.slow
def test_a_poromechanical_lung_with_balanced_gravity_on_its_template_is_the_library_shape():
    """The template of a library of lungs (its mean shape) with 2 modes, at coefficients c (in
    the library's standard deviations), against the lung the library itself makes at c
    (ShapeModes.geometry: the reference's nodes moved)."""
    from lungmech.lung import Poromechanics, skeleton
    from lungmech.lung.gravity import Gravity

    def poromechanical(geometry, **keywords):
        return Model(
            geometry,
            skeleton(160.0, 0.5, 200.0, 400.0),
            formulation=Poromechanics(1e4, 0.3),
            loads=[FollowerPressure(SURROUNDING, -300.0), Gravity(315.0, [0.0, 0.0, -9.81], balanced_on=SURROUNDING)],
            constraints=[clamp("hilum")],
            **keywords,
        )

    modes = population()
    template, fields = modes.template(lung(), 2)
    on_template = poromechanical(template, shape=fields, parameters=parameters(2, bound=2.0))
    c = [1.5, -1.2]
    on_template.set_parameters(a1=c[0], a2=c[1])
    on_moved = poromechanical(modes.geometry(lung(), c))
    agree(on_template, on_moved, smooth_state(on_moved, 0.002))
    on_template.reset(), on_moved.reset()
    solve(on_template), solve(on_moved)
    u1, u2 = on_template.displacement().x.array, on_moved.displacement().x.array
    assert np.abs(u1 - u2).max() <= 1e-7 * np.abs(u2).max()
    assert deformed_volume(on_template)() == pytest.approx(deformed_volume(on_moved)(), rel=1e-9)


def test_a_template_takes_one_to_all_of_the_librarys_modes():
    from lungmech.errors import RegistrationError

    modes = population()
    for count in (0, len(modes.modes) + 1, 1.5):
        with pytest.raises(RegistrationError, match=f"a template takes 1 to {len(modes.modes)} shape modes"):
            modes.template(lung(), count)


@pytest.mark.slow
def test_the_shape_parameters_sensitivities_are_the_finite_differences():
    """d(output)/da by the model's direct sensitivities against central differences of solves:
    a shape coefficient moves the volume explicitly (dx = det G dX₀), the state implicitly."""
    from lungmech.fem.parametric import FullOrderModel
    from lungmech.fem.solver import Stepping

    template = cube()
    stiffness = Parameter("mu", "material.mu", 400.0, (200.0, 800.0))
    model = Model(
        template,
        NeoHookean.from_young(1e3, 0.3),
        loads=[FollowerPressure("x1", 40.0), BodyForce([0.0, 0.0, -30.0])],
        constraints=[clamp("x0")],
        shape=modes_of(template.mesh, box_modes(1.0)),
        parameters=[*parameters(2), stiffness],
    )
    full = FullOrderModel(model, Stepping(), probes=[[1.0, 0.5, 0.5]])
    mu = {"a1": 0.4, "a2": -0.3, "mu": 400.0}
    solution = full.solve(mu, sensitivities=True)
    for i, name in enumerate(solution.parameter_names):
        h = 1e-4 * np.diff(model.parameters.named(name).range)[0]
        up, down = (full.solve(mu | {name: mu[name] + s * h}).outputs for s in (1.0, -1.0))
        for key in ("volume", "strain_energy", "probes"):
            exact, approximate = solution.sensitivities[key][..., i], (up[key] - down[key]) / (2 * h)
            scale = max(np.abs(exact).max(), np.abs(approximate).max())
            assert np.abs(exact - approximate).max() <= 1e-5 * scale, (name, key)


@pytest.mark.slow
def test_a_reduced_and_a_hyper_reduced_model_serve_every_shape():
    """A Galerkin reduced model (its outputs on the full mesh) and a hyper-reduced one (ECSW;
    its volume a cubic in (q, a) together, lungmech.rom.shaped) trained over the shape box are
    the full model's answer to their basis' accuracy at shapes they were not trained on, and the
    hyper-reduced model's derivatives in the shape coefficients are those of its own solves."""
    from lungmech.fem.parametric import FullOrderModel
    from lungmech.fem.solver import Stepping
    from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet

    template = cube()
    model = rubber(template, shape=modes_of(template.mesh, box_modes(1.0)), parameters=parameters(2))
    full = FullOrderModel(model, Stepping())
    corners = [{"a1": a, "a2": b} for a in (-1.0, 1.0) for b in (-1.0, 1.0)] + [{"a1": 0.0, "a2": 0.0}]
    with Reductor(full, POD(12), TrainingSet(corners)) as reductor:
        reduced, hyper = reductor.reduce(), reductor.reduce(ECSW(1e-4))

    def errors(mu):  # of the volume, over the volume change at this shape
        model.set_parameters(mu), model.reset()
        at_rest = deformed_volume(model)()
        exact = full.solve(mu).outputs["volume"][-1]
        return [abs(m.solve(mu).outputs["volume"][-1] - exact) / abs(exact - at_rest) for m in (reduced, hyper)]

    # measured (5 trained shapes: the corners and the centre): 3e-6 at a trained shape, 9.5e-3
    # and 4.6e-3 between them, ECSW (τ = 1e-4) within 6e-5 of Galerkin; a model that kept the
    # template's shape would be off by its 0.04 m³ more volume, 2.3 times the change
    for mu, bound in (
        ({"a1": 1.0, "a2": -1.0}, 1e-4),
        ({"a1": 0.55, "a2": -0.35}, 2e-2),
        ({"a1": -0.8, "a2": 0.3}, 1e-2),
    ):
        galerkin, ecsw = errors(mu)
        assert galerkin < bound and ecsw < bound
        assert abs(ecsw - galerkin) < 2e-4
    mu = {"a1": 0.3, "a2": -0.6}
    solution = hyper.solve(mu, sensitivities=True)
    for i, name in enumerate(solution.parameter_names):
        h = 1e-4
        up, down = (hyper.solve(mu | {name: mu[name] + s * h}).outputs for s in (1.0, -1.0))
        for key in ("volume", "strain_energy"):
            exact, approximate = solution.sensitivities[key][-1, i], (up[key][-1] - down[key][-1]) / (2 * h)
            assert exact == pytest.approx(approximate, rel=1e-5, abs=1e-9), (name, key)
