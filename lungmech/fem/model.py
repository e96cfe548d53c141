"""A finite-strain boundary-value problem: a law, loads and imposed displacements on a geometry.

The model is the sum of the terms it is given and nothing more: its total potential is
Π = ∫ ψ dx + Σ (load potentials), its residual is δΠ minus the virtual work of follower loads,
and its Jacobian is the exact derivative of the residual. Every load value, imposed
displacement and material parameter lives in a ``Constant`` or ``Function``, so changing the time
or a parameter recompiles nothing.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem

from lungmech.errors import ParameterError
from lungmech.fem import binding, limits
from lungmech.fem import constraints as _constraints
from lungmech.fem.constraints import Displacement
from lungmech.fem.formulations import Formulation, PlaneStress, PureDisplacement, TaylorHood
from lungmech.fem.kinematics import PLANES
from lungmech.fem.loads import Load, StateDependentWork, is_pressure
from lungmech.fem.materials import Material
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.fem.placement import Image, kinematics
from lungmech.fem.shape import KIND as SHAPE
from lungmech.fem.shape import ShapeMap
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    import dolfinx.mesh

    from lungmech.mesh.geometry import Geometry


class Model:
    """Unknowns, forms and boundary data of one problem.

    Args:
        geometry: mesh with named boundaries (:mod:`lungmech.mesh`).
        material: a strain-energy law (:mod:`lungmech.fem.materials`), or a function of the
            parameter values that returns one (``lambda mu: NeoHookean.from_young(mu["E"], 0.3)``).
        degree: Lagrange degree of the displacement.
        mixed: shorthand for ``formulation=TaylorHood()``: displacement–pressure
            (P``degree``–P``degree-1``), for nearly or exactly incompressible laws with a
            volumetric split.
        formulation: how the unknowns are discretised (:mod:`lungmech.fem.formulations`).
        loads: body forces, tractions, follower pressures (:mod:`lungmech.fem.loads`).
        constraints: imposed displacements (:mod:`lungmech.fem.constraints`).
        quadrature_degree: overrides the law's own choice.
        plane: on a 2-D mesh, ``"strain"`` (a long body, λ₃ = 1) or ``"stress"`` (a thin plate,
            λ₃ solved for; the displacement formulation only), see
            :mod:`lungmech.fem.kinematics`. Required in 2-D, refused in 3-D.
        parameters: named parameters μ (:mod:`lungmech.fem.parameters`), set with
            :meth:`set_parameters` without recompiling anything.
        image: the mesh is the body imaged under load, not its reference
            (:mod:`lungmech.fem.placement`): the state's vector field is the motion w from the
            image (``Image.motion(t₀)``, the reference map ξ in :attr:`reference_map`) or ξ
            itself (``Image.inverse(t₀)``, the image's equilibrium). None: the mesh is the
            reference and the state's vector field the displacement u.
    """

    def __init__(
        self,
        geometry: Geometry,
        material: Material | binding.LawAt,
        *,
        degree: int = 1,
        mixed: bool = False,
        formulation: Formulation | None = None,
        loads: Sequence[Load] = (),
        constraints: Sequence[Displacement] = (),
        quadrature_degree: int | None = None,
        parameters: Sequence[Parameter] = (),
        plane: str | None = None,
        image: Image | None = None,
        shape: Sequence[fem.Function] = (),
    ) -> None:
        self._arguments = dict(
            geometry=geometry, material=material, degree=degree, mixed=mixed, formulation=formulation, loads=loads,
            constraints=constraints, quadrature_degree=quadrature_degree, parameters=parameters, plane=plane,
            shape=shape,
        )  # fmt: skip
        mesh = geometry.mesh
        self.plane = _plane(mesh, plane)
        self.geometry = geometry
        self.parameters = Parameters(parameters)
        self.shape = ShapeMap.of(shape) if len(shape) else None  # the template's map χ_a, or None
        self._shape_jacobian: Callable[[], float] | None = None  # min det G, compiled when first asked
        _check_shape_parameters(self.parameters, self.shape)
        shape_displacement = self.shape.displacement if self.shape else None
        self._interfaces: dict[str, fem.Constant] = {
            p.name: fem.Constant(mesh, p.default) for p in self.parameters if p.kind == "interface"
        }
        law_at = binding.law_function(material, self.parameters)
        material = law_at(binding.outside_keys(self.parameters, self.parameters.defaults))
        self.material, assign_material = binding.material(
            law_at, self.parameters, geometry, self._interfaces, shape_displacement
        )
        unbound = formulation or (TaylorHood() if mixed else PureDisplacement())
        if self.plane == "stress":
            if not isinstance(unbound, PureDisplacement):
                raise ParameterError(
                    f"plane stress works with the displacement formulation only (got {type(unbound).__name__}); "
                    "use plane = 'strain'"
                )
            unbound = PlaneStress()
            if image is not None:
                raise ParameterError(
                    "plane stress on an imaged mesh is not supported (the reference thickness would be an unknown "
                    "too); use plane = 'strain'"
                )
        self.image = image
        self.formulation = unbound.bind(mesh)
        self.degree = degree
        self.loads, self.constraints = tuple(loads), tuple(constraints)
        for load in self.loads:
            if np.ndim(load.value) == 1 and np.size(load.value) != mesh.geometry.dim:
                raise ParameterError(
                    f"load '{getattr(load, 'label', type(load).__name__)}': its value has {np.size(load.value)} "
                    f"components, the mesh is {mesh.geometry.dim}-D"
                )
        if not isinstance(degree, int) or isinstance(degree, bool) or degree < 1:
            raise ParameterError(f"the displacement degree must be an integer >= 1 (got {degree!r})")
        if degree < mesh.geometry.cmaps[0].degree:
            raise ParameterError(
                f"degree {degree} displacements on a mesh of order {mesh.geometry.cmaps[0].degree} (curved cells) "
                "cannot move the body rigidly: rotations would strain it. Use degree >= the mesh order, or a "
                "straight (order 1) mesh"
            )
        self.formulation.check(material, degree)

        q = quadrature_degree if quadrature_degree is not None else self._default_quadrature_degree()
        self.dx = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": q})
        cell, gdim = mesh.basix_cell(), mesh.geometry.dim
        element_u = basix.ufl.element("Lagrange", cell, degree, shape=(gdim,))
        extra = self.formulation.elements(cell, degree, q)
        if extra:
            self.space = fem.functionspace(mesh, basix.ufl.mixed_element([element_u, *extra]))
            self.displacement_space = self.space.sub(0)
        else:
            self.space = fem.functionspace(mesh, element_u)
            self.displacement_space = self.space
        self.state: fem.Function = fem.Function(self.space, name="state")
        unknowns = ufl.split(self.state) if extra else (self.state,)
        self.fields = dict(zip(("u", *self.formulation.fields), unknowns))
        # on an image: ξ, a coefficient of the motion's forms; w = 0, the inverse problem's direction
        vectors = self.space.sub(0).collapse()[0] if extra else self.space  # the state's own numbering of u
        self.reference_map = (
            fem.Function(vectors, name="reference_map") if image and image.unknown == "motion" else None
        )
        self._motion = fem.Function(vectors, name="motion") if image and image.unknown == "inverse" else None
        self.kinematics = kinematics(
            mesh,
            self.fields["u"],
            image,
            self.reference_map,
            self._motion,
            self.fields.get("thickness_stretch"),
            shape_displacement,
        )
        self.reset()
        self.fields["u"] = self.u = self.kinematics.u  # the displacement from the reference
        self.position = self.kinematics.position  # X, where laws and loads are given as formulas
        self.area_normal = self.kinematics.area_normal  # N dA per mesh area, for Nanson's formula
        self.F = self.kinematics.F
        self.dx = self.kinematics.reference_volume(self.dx)
        self.energy_density = self.formulation.energy_density(self.material, self.F, self.fields)

        v = ufl.TestFunction(self.space)
        v_u = ufl.split(v)[0] if self.multi_field else v
        self._load_values = [fem.Constant(mesh, np.zeros(np.shape(load.magnitude))) for load in self.loads]
        self.time_constant: fem.Constant = fem.Constant(mesh, 0.0)  # t in loads given as formulas (s)
        self.potential = self.energy_density * self.dx
        virtual_work, self._state_dependent = [], []
        load_potentials = []
        for load, value in zip(self.loads, self._load_values):
            if hasattr(load, "potential"):
                load_potentials.append(load.potential(self, value))
                self.potential += load_potentials[-1]
            work = load.virtual_work(self, v_u, value) if hasattr(load, "virtual_work") else None
            if isinstance(work, StateDependentWork):
                self._state_dependent.append(work)
                work = work.form
            if work is not None:
                virtual_work.append(work)
        self.residual = self._variation(self.potential, v)
        for work in virtual_work:
            self.residual -= work
        # the same residual in its two parts, R = R_int + R_load: the internal forces (of the
        # energy density) and the loads' (hyper-reduction samples them apart)
        self.internal_residual = self._variation(self.energy_density * self.dx, v)
        self.load_residual = sum((self._variation(potential, v) for potential in load_potentials), ufl.Form([]))
        for work in virtual_work:
            self.load_residual -= work
        self.jacobian = ufl.derivative(self.residual, self.state, ufl.TrialFunction(self.space))

        self._imposed = [_constraints.build(c, self.displacement_space, geometry, image) for c in self.constraints]
        self.bcs = [imposed.bc for imposed in self._imposed]
        self._amplitudes = np.ones(len(self.loads))
        self._assign_material = assign_material
        self._assign_formulation = binding.formulation(unbound, self.formulation, self.parameters)
        self._loads_at = binding.loads(self.loads, self.parameters)
        self._constraint_amplitudes = binding.constraints(self.constraints, self.parameters)
        self.parameter_values = self.parameters.defaults
        self.time = 0.0
        self.loading = 0  # changes whenever the loads are set (what was assembled at one holds)
        self._scaling: tuple = (1.0, None)  # set_time's load factor and ``about``, kept for set_parameters
        self.set_parameters()
        self._check_shape_box()

    def set_parameters(self, values: Mapping[str, float] | None = None, **named: float) -> None:
        """Set parameters by name (``model.set_parameters(stiffness=2e3)`` or a mapping); the others
        keep their current values. Each value is checked against its range. Only constants change:
        nothing is recompiled. The loads are re-evaluated at the current time, with the load factor
        of the last :meth:`set_time`; the state is kept."""
        given = {**(values or {}), **named}
        current = self.parameters.values(given, start=self.parameter_values)
        self._assign_material(current)
        self._assign_formulation(current)
        self.loads, self._amplitudes = self._loads_at(current)
        for imposed, amplitude in zip(self._imposed, self._constraint_amplitudes(current)):
            imposed.amplitude = amplitude
        for name, constant in self._interfaces.items():
            constant.value = np.asarray(current[name])
        if self.shape is not None:
            self._set_shape(current)
        self.parameter_values = current
        self.set_time(self.time, *self._scaling)

    def _set_shape(self, values: Mapping[str, float]) -> None:
        """The shape coefficients a from the parameter ``values``, refused where the map folds a
        cell (det G ≤ 0 at a quadrature point; checked when a changes)."""
        assert self.shape is not None
        before = self.shape.values()
        acting = [p for p in self.parameters if p.kind == SHAPE]
        self.shape.assign({p.key: values[p.name] for p in acting})
        if np.array_equal(before, self.shape.values()) and self._shape_jacobian is not None:
            return
        if self._shape_jacobian is None:  # compiled when first needed
            mesh = self.geometry.mesh
            degree = limits.quadrature_degree(self)
            self._shape_jacobian = limits.smallest(
                limits.at_quadrature_points(ufl.det(self.shape.gradient), mesh, degree), mesh.comm
            )
        try:
            self.shape.check(self._shape_jacobian, {p.name: values[p.name] for p in acting})
        except ParameterError:
            self.shape.set(before)  # the model keeps the shape it had
            raise

    def _check_shape_box(self) -> None:
        """Every corner of the shape parameters' box keeps every cell unfolded (det G > 0 at
        every quadrature point), or the model is refused, naming the corner."""
        acting = [p for p in self.parameters if p.kind == SHAPE]
        if not acting:
            return
        for corner in itertools.product(*(p.range for p in acting)):
            self._set_shape(self.parameter_values | {p.name: value for p, value in zip(acting, corner)})
        self._set_shape(self.parameter_values)

    def _variation(self, form: ufl.Form, v: ufl.Argument) -> ufl.Form:
        """δ``form`` along the test function ``v``: its derivative in the state — on an image's
        inverse problem, in the motion w (at w = 0) and in the other fields, not in ξ (see
        :mod:`lungmech.fem.placement`)."""
        if self._motion is None:
            return ufl.derivative(form, self.state, v)
        v_u = ufl.split(v)[0] if self.multi_field else v
        variation = ufl.derivative(form, self._motion, v_u)
        if self.multi_field:  # the other fields' equations: along v with its vector part zero
            d = len(v_u)
            others = ufl.as_vector([0.0] * d + [v[i] for i in range(d, v.ufl_shape[0])])
            variation += ufl.derivative(form, self.state, others)
        return variation

    def variant(self, image: Image | None) -> Model:
        """The same problem with the mesh placed as ``image`` says (another unknown, the same
        loads, law and parameters): e.g. the inverse problem of an imaged model's breath."""
        return Model(**self._arguments, image=image)  # type: ignore[arg-type]  # the constructor's own arguments

    def set_reference_map(self, values: np.ndarray) -> None:
        """ξ = X − x of an imaged model's breath (``Image.motion``): ``values``, this rank's owned
        entries of ξ (its ghosts follow; collective)."""
        if self.reference_map is None:
            raise ParameterError("only a model of an image's motion (Image.motion) has a reference map")
        self.reference_map.x.array[: values.size] = values
        self.reference_map.x.scatter_forward()

    def reset(self) -> None:
        """Back to the unloaded state: u = 0 and every other field at its initial value (on an
        image's motion, w = ξ: the state is its reference)."""
        self.state.x.array[:] = 0.0
        if self.reference_map is not None:
            if self.multi_field:
                self.state.x.array[self.space.sub(0).collapse()[1]] = self.reference_map.x.array
            else:
                self.state.x.array[:] = self.reference_map.x.array
        initial = self.formulation.initial_values()
        for index, name in enumerate(self.formulation.fields, start=1):
            if name in initial:  # e.g. the solid fraction starts at its reference value, not 0
                subspace, dofs = self.space.sub(index).collapse()
                start: fem.Function = fem.Function(subspace)
                value = initial[name]
                if isinstance(value, fem.Function):
                    start.interpolate(value)
                else:
                    start.x.array[:] = value
                self.state.x.array[dofs] = start.x.array

    def set_time(self, t: float, load_factor: float | Sequence[float] = 1.0, about: float | None = None) -> None:
        """Set every load and imposed displacement to its ramped value at time t.

        ``load_factor`` scales the loads (not the imposed displacements), all alike or one
        factor per load: a path to the loads of time t from zero, as the inverse problem needs.
        With ``about`` = t₀ it scales only their change since t₀ (ramp(t₀) + f (ramp(t) −
        ramp(t₀))): a deeper or shallower breath from the same end-expiration, say.
        """
        self.time, self._scaling = t, (load_factor, about)
        self.loading += 1
        self.time_constant.value = np.asarray(t)
        factors = np.broadcast_to(np.asarray(load_factor, dtype=float), (len(self.loads),))
        for load, value, factor, amplitude in zip(self.loads, self._load_values, factors, self._amplitudes):
            base = 0.0 if about is None else load.ramp(about)
            current = (base + factor * (load.ramp(t) - base)) * amplitude * load.magnitude
            if not np.all(np.isfinite(current)):
                label = getattr(load, "label", type(load).__name__)
                raise ParameterError(
                    f"load '{label}' is not a finite number at t = {t:g} (value {current}, factor {factor})"
                )
            value.value = current
        for imposed in self._imposed:
            imposed.set_time(t)

    @property
    def scaling(self) -> tuple:
        """The ``(load_factor, about)`` of the last :meth:`set_time`."""
        return self._scaling

    def scalar_loads(self) -> dict[str, float]:
        """The current value of every scalar load (a pressure, Pa) by label, as :meth:`set_time` set it."""
        return {
            load.label: float(value.value) for load, value in zip(self.loads, self._load_values) if is_pressure(load)
        }

    @contextlib.contextmanager
    def kept_state(self) -> Iterator[None]:
        """Whatever the block does to the state, it is restored afterwards (also on an error)."""
        saved = self.state.x.array.copy()
        try:
            yield
        finally:
            self.state.x.array[:] = saved
            self.state.x.scatter_forward()

    @property
    def imposed(self) -> list[_constraints.ImposedValue]:
        """The imposed displacements as built (their conditions are :attr:`bcs`, in order)."""
        return self._imposed

    def imposed_amplitudes(self) -> np.ndarray:
        """Each imposed displacement's factor on its base value now: amplitude · ramp(t) (on an
        image, see :meth:`lungmech.fem.constraints.ImposedValue.factor`)."""
        return np.array([imposed.factor(self.time) for imposed in self._imposed])

    @property
    def state_dependent(self) -> list[StateDependentWork]:
        """Load terms whose coefficients are global functionals of the state (solver-managed)."""
        return self._state_dependent

    @property
    def multi_field(self) -> bool:
        """Whether the state holds fields besides the displacement: a mixed function space.

        Taylor–Hood's pressure or the lung's porosity. Not the constructor's ``mixed``, which
        chooses the Taylor–Hood formulation.
        """
        return bool(self.formulation.fields)

    @property
    def breakpoints(self) -> list[float]:
        """Times where some ramp has a kink: the solver lands on them exactly."""
        ramps = [load.ramp for load in self.loads] + [c.ramp for c in self.constraints]
        return sorted({t for ramp in ramps for t in ramp.times})

    def first_piola(self) -> ufl.core.expr.Expr:
        """P = ∂(energy density)/∂F, including the pressure of the mixed formulation."""
        return ufl.diff(self.energy_density, self.F)

    def cauchy(self) -> ufl.core.expr.Expr:
        """σ = P Fᵀ / J (σ = P for a small-strain law)."""
        if getattr(self.material, "small_strain", False):
            return self.first_piola()
        return self.first_piola() * self.F.T / ufl.det(self.F)

    def mesh_volume(self) -> ufl.Form:
        """∫ dx over the body the mesh holds, as it stands (m³; m³/m in 2-D): the mesh's own
        volume, or on a template χ_a(Ω₀)'s, ∫ det G dx̂ (the image, on an imaged template)."""
        dx = ufl.dx(domain=self.geometry.mesh)
        one = fem.Constant(self.geometry.mesh, 1.0)
        return (one * dx) if self.shape is None else one * ufl.det(self.shape.gradient) * dx

    def displacement(self) -> fem.Function:
        """The displacement u from the reference as a Function of its own (collapsed) space: a
        copy (on an image, w − ξ)."""
        u = self.state.sub(0).collapse() if self.multi_field else self.state.copy()
        if self.reference_map is not None:
            u.x.array[:] -= self.reference_map.x.array
        elif self._motion is not None:
            u.x.array[:] *= -1.0
        return u

    def motion(self) -> fem.Function:
        """The displacement from the mesh as a Function of its own (collapsed) space, a copy:
        u on a reference mesh, w on an image's motion, 0 on its inverse problem."""
        w = self.state.sub(0).collapse() if self.multi_field else self.state.copy()
        if self._motion is not None:
            w.x.array[:] = 0.0
        return w

    def field_dofs(self) -> dict[str, np.ndarray]:
        """This rank's owned entries of the state vector, by field ("u", then the formulation's)."""
        owned = owned_size(self.space)
        if not self.multi_field:
            return {"u": np.arange(owned)}
        names = ("u", *self.formulation.fields)
        parts = [np.asarray(self.space.sub(i).collapse()[1]).ravel() for i in range(len(names))]
        return {name: rows[rows < owned] for name, rows in zip(names, parts)}

    def constrained_dofs(self) -> np.ndarray:
        """This rank's owned entries of the state vector that an imposed displacement sets."""
        owned = owned_size(self.space)
        dofs = [bc.dof_indices()[0] for bc in self.bcs]
        everything = np.unique(np.concatenate(dofs)) if dofs else np.zeros(0, dtype=np.int32)
        return everything[everything < owned]

    def _default_quadrature_degree(self) -> int:
        mesh = self.geometry.mesh
        affine = mesh.topology.cell_name() in ("interval", "triangle", "tetrahedron")
        gradient_degree = self.degree - 1 if affine else self.degree
        gradient_degree += mesh.geometry.cmaps[0].degree - 1  # curved cells: non-constant Jacobian
        return self.material.quadrature_degree(gradient_degree)


def _check_shape_parameters(parameters: Parameters, shape: ShapeMap | None) -> None:
    """Each shape parameter names one of the model's modes (``shape.mode_<i>``), each once."""
    acting = [p for p in parameters if p.kind == SHAPE]
    targets = shape.targets if shape is not None else ()
    for p in acting:
        if p.target not in targets:
            has = f"its modes are {', '.join(targets)}" if targets else "the model has no shape modes"
            raise ParameterError(f"parameter '{p.name}': target {p.target} is not a shape mode ({has})")
    named = [p.target for p in acting]
    if len(set(named)) != len(named):
        raise ParameterError(f"shape parameters: each mode takes one parameter (got {', '.join(sorted(named))})")


def _plane(mesh: dolfinx.mesh.Mesh, plane: str | None) -> str | None:
    """The plane hypothesis of a 2-D mesh (required), None for a 3-D one (where it is refused)."""
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    if tdim == 2:
        if gdim != 2:
            raise ParameterError(
                f"a 2-D mesh needs 2-D coordinates (its nodes have {gdim}); read or build it with 2 coordinates"
            )
        if plane not in PLANES:
            raise ParameterError(
                f"a 2-D mesh needs plane = 'strain' (a long body) or 'stress' (a thin plate) (got {plane!r}; "
                "in a scene: [formulation] plane)"
            )
        return plane
    if tdim != 3:
        raise ParameterError(f"meshes of dimension 2 or 3 are supported (got {tdim})")
    if plane is not None:
        raise ParameterError(f"plane = {plane!r} is for 2-D meshes; this mesh is 3-D")
    return None
