"""Exact derivatives of a model's outputs with respect to its parameters μ (direct or reduced).

At a converged state x(μ) the residual vanishes, R(x(μ), c(μ)) = 0 on the free dofs, with c the
values the parameters set (the model's ``fem.Constant`` and parameter ``Function`` objects: law and
formulation constants, region fields' inside values, interface positions, load values) and the
imposed (Dirichlet) values x_D(μ) on the others. Differentiating,

    K dx/dμ_i = −∂R/∂μ_i = −Σ_k ∂R/∂c_k · ∂c_k/∂μ_i   on the free dofs,   dx/dμ_i = dx_D/dμ_i  on the imposed ones,

with K = ∂R/∂x the model's exact Jacobian at the converged state (direct sensitivities: one
factorisation of K serves every parameter). A reduced Galerkin model x = x₀ + V q, whose basis V
vanishes on imposed dofs and x₀ holds the imposed values, gives instead

    dq/dμ = −(Vᵀ K V)⁻¹ Vᵀ (∂R/∂μ + K dx₀/dμ),   dx/dμ = V dq/dμ + dx₀/dμ,

the exact derivative of the reduced model's own answer. An output J(x, c) then has
dJ/dμ = ∂J/∂x · dx/dμ + ∂J/∂c · ∂c/∂μ: the deformed volume ∫ det F dX has no explicit part
but through a shape map's coefficients (dX = det G dX₀, :mod:`lungmech.fem.shape`), the
strain energy ∫ ψ dX has ∂ψ/∂c (ψ depends on the law's constants), a probe is the displacement
part of dx/dμ at its point, and a scalar load's value is itself one of the c.

∂R/∂c_k and ∂ψ/∂c_k are exact in the forms. One form per model holds Σ_k w_k · ∂R/∂c_k (and
Σ_j ∂R/∂f_j [δf_j] for the Functions) with weight Constants w_k (dotted with the constant for a
vector one) and direction Functions δf_j: UFL takes it as one directional derivative,
d/dε R(c + ε w, f + ε δf) at ε = 0 (ε a ``Constant`` 0 wrapped in a ``ufl.variable``). Each
parameter costs one assembly with w_k = ∂c_k/∂μ_i and nothing is recompiled
between parameters or μ. The map μ → c is the model's own assignment
(:meth:`lungmech.fem.model.Model.set_parameters`) and may be nonlinear (E, ν → Lamé constants;
posture angles → gravity vector): ∂c/∂μ_i and dx_D/dμ_i are its central differences in the
*values* only (no assembly), exact for targets that enter linearly (most do: up to round-off,
≈ 10⁻¹¹ relative) and second-order accurate otherwise (relative error ≈ h² c'''/(6 c') with
h = 10⁻⁵ of the parameter's range: ≈ 10⁻⁹ for ν in [0.2, 0.4]).

The direct method solves once per parameter and serves every output (volume, energy, each probe
component, loads); an adjoint would pay off only for more parameters than outputs.

Loads whose coefficients θ = Θ(x; c) depend on the state (balanced gravity) add a low-rank
term to the tangent, J = K + U Wᵀ (U = ∂R/∂θ, W = (∂Θ/∂x)ᵀ: :mod:`lungmech.fem.state_dependent`),
and their explicit dependence on the values, ∂Θ/∂c, is one more value the parameters set
(:func:`value_derivatives` sets θ again at each of its points): the direct solves are then
J dx/dμ = −∂R/∂μ, by Woodbury's identity on the one factorisation of K, and a reduced model's
are Vᵀ J V dq/dμ = −Vᵀ(∂R/∂μ + J dx₀/dμ).
"""

from __future__ import annotations

import contextlib
import math
import weakref
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix, create_matrix
from ufl.algorithms import expand_derivatives
from ufl.algorithms.map_integrands import map_integrands

from lungmech import jit
from lungmech.errors import ParameterError
from lungmech.fem.linear import factorised
from lungmech.fem.quantities import assemble_owned
from lungmech.fem.state_dependent import StateDependent
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size

if TYPE_CHECKING:
    from lungmech.fem.model import Model
    from lungmech.fem.parameters import Parameter
    from lungmech.fem.solver_interface import Solver

__all__ = [
    "STEP",
    "DerivativeForms",
    "Moved",
    "ValueDerivatives",
    "derivative_forms",
    "output_derivatives",
    "reduced_state_derivatives",
    "residual_derivatives",
    "state_derivatives",
    "value_derivatives",
]

STEP = 1e-5  # the difference step of ∂c/∂μ, as a fraction of the parameter's range


@dataclass(frozen=True)
class ValueDerivatives:
    """∂(the values the parameters set)/∂μ at the current μ and time, the parameters last.

    ``constants[c]`` (the shape of the Constant c + (n,)) and ``functions[f]`` (the local entries of
    the Function f, ghosts included, n) cover every one the model's forms hold; ``imposed`` is
    dx_D/dμ, the derivative of the imposed values as a state vector (local entries, n; zero on
    free dofs); ``loads`` the derivative of each scalar load's value (Pa per unit of μ) by label;
    ``amplitudes`` that of each imposed displacement's factor amplitude · ramp(t) (constraints, n).

    A start found at every μ moves what it sets with them (:class:`Moved`): an imaged body's
    reference map ξ among ``functions`` (dξ/dμ), and ``start``, the derivative of the state its
    path starts from beyond the imposed values (the image's other fields; local entries, n),
    which a reduced path is relative to: dx₀/dμ = ``imposed`` + ``start``.
    """

    names: tuple[str, ...]
    constants: dict[fem.Constant, np.ndarray]
    functions: dict[fem.Function, np.ndarray]
    imposed: np.ndarray
    loads: dict[str, np.ndarray]
    amplitudes: np.ndarray
    start: np.ndarray | None = None

    def start_state(self, owned: int) -> np.ndarray:
        """dx₀/dμ on the ``owned`` rows: the imposed values' and the start's (owned × parameters)."""
        dx0 = self.imposed[:owned]
        return np.ascontiguousarray(dx0 if self.start is None else dx0 + self.start[:owned])


@dataclass(frozen=True)
class Moved:
    """What a start found at μ sets beyond the parameters' values, with its derivatives:
    ``functions`` (Function → d/dμ, local entries × parameters: an imaged body's ξ) and ``start``
    (dx₀/dμ beyond the imposed values: the image's other fields; local entries × parameters)."""

    functions: Mapping[fem.Function, np.ndarray]
    start: np.ndarray


class DerivativeForms:
    """The derivative forms of one model, compiled once (collective).

    ``constants`` and ``functions`` are every ``Constant`` and (non-state) ``Function`` of the
    residual and of the strain energy: whatever a parameter may set. ``weights`` are their
    directions (w_k, δf_j); ``residual`` = Σ_k w_k · ∂R/∂c_k + Σ_j ∂R/∂f_j [δf_j], ``energy`` the
    same of ∫ ψ dX, ``volume`` the same of ∫ det F dX (a shape map's model only: None otherwise),
    ``volume_gradient`` = ∂(∫ det F dX)/∂x, ``energy_gradient`` = ∂(∫ ψ dX)/∂x.

    A hyper-reduced model gives its own ``residual`` and ``energy`` (weighted, over sampled
    cells), ``compile`` (onto its reduced mesh) and ``like``, the full model's forms, whose
    constants and functions are the ones the parameters set; it has no ``volume_gradient``.
    ``with_energy=False``: the residual's alone (a problem whose answer is its state, an imaged
    body's inverse motion): ``energy`` and ``energy_gradient`` are None.
    """

    def __init__(
        self,
        model: Model,
        residual: ufl.Form | None = None,
        energy: ufl.Form | None = None,
        compile: Callable[[ufl.Form], fem.Form] = fem.form,
        like: DerivativeForms | None = None,
        with_energy: bool = True,
    ) -> None:
        residual = expand_derivatives(model.residual if residual is None else residual)
        energy = model.energy_density * model.dx if energy is None else energy
        forms = (residual, energy) if with_energy else (residual,)
        if like is None:
            found_constants = {c: None for form in forms for c in form.constants()}
            found_functions = {f: None for form in forms for f in form.coefficients() if f is not model.state}
            self.constants, self.functions = tuple(found_constants), tuple(found_functions)
        else:
            self.constants, self.functions = like.constants, like.functions
        mesh = model.geometry.mesh
        self.weights = tuple(fem.Constant(mesh, np.zeros(c.ufl_shape)) for c in self.constants)
        self.directions = tuple(fem.Function(f.function_space) for f in self.functions)
        self._epsilon = fem.Constant(mesh, 0.0)  # the directions' step: 0, where the derivative is taken
        self._compile = compile
        self.residual = self._explicit(residual)  # None: no parameter acts
        self.energy = self._explicit(energy) if with_energy else None
        volume = ufl.det(model.F) * model.dx
        self.volume_gradient = None if like else jit.form(ufl.derivative(volume, model.state))
        # ∫ det F dX depends on the values at fixed state only through a shape map (dX = det G dX₀):
        # on an image, det F dX = det(I + ∇w) dx holds no ξ
        self.volume = self._explicit(volume) if like is None and model.shape is not None else None
        self.energy_gradient = compile(ufl.derivative(energy, model.state)) if with_energy else None
        self.comm = mesh.comm

    def _explicit(self, form: ufl.Form) -> fem.Form | None:
        """Σ_k w_k · ∂form/∂c_k + Σ_j ∂form/∂f_j [δf_j] at fixed state, compiled (None if it
        vanishes): one directional derivative d/dε form(c + ε w, f + ε δf) at ε = 0, ε a Constant
        0. (A derivative per constant cost UFL a pass each: 10 s on a shape-parametrised lung.)"""
        epsilon = ufl.variable(self._epsilon)
        moved = {c: c + epsilon * w for c, w in zip(self.constants, self.weights)}
        moved |= {f: f + epsilon * direction for f, direction in zip(self.functions, self.directions)}
        along = map_integrands(lambda integrand: ufl.diff(integrand, epsilon), ufl.replace(form, moved))
        derivative = expand_derivatives(along)
        return None if derivative.empty() else self._compile(derivative)

    def set_weights(self, derivatives: ValueDerivatives, i: int) -> None:
        """The directions of parameter i: w_k = ∂c_k/∂μ_i, δf_j = ∂f_j/∂μ_i."""
        for c, w in zip(self.constants, self.weights):
            w.value = derivatives.constants[c][..., i]
        for f, direction in zip(self.functions, self.directions):
            direction.x.array[:] = derivatives.functions[f][:, i]


_compiled: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def derivative_forms(model: Model) -> DerivativeForms:
    """The model's derivative forms, compiled on first use (collective) and kept with the model."""
    if model not in _compiled:
        _compiled[model] = DerivativeForms(model)
    return _compiled[model]


def _stencil(parameter: Parameter, value: float) -> tuple[np.ndarray, np.ndarray]:
    """Points and weights of a second-order first derivative that stay inside the range: central
    (c(μ+h) − c(μ−h))/2h, or one-sided (±(−3c(μ) + 4c(μ±h) − c(μ±2h))/2h) at an end of the range.
    h = STEP × (high − low); for a log-scale parameter, STEP × μ ln(high/low) (its range in its own
    sampling coordinate, at μ)."""
    low, high = parameter.range
    h = STEP * (value * math.log(high / low) if parameter.log else high - low)
    if value - h >= low and value + h <= high:
        return value + h * np.array([-1.0, 1.0]), np.array([-1.0, 1.0]) / (2 * h)
    side = 1.0 if value - h < low else -1.0
    return value + side * h * np.array([0.0, 1.0, 2.0]), side * np.array([-3.0, 4.0, -1.0]) / (2 * h)


@contextlib.contextmanager
def _restored(model: Model, forms: DerivativeForms) -> Iterator[None]:
    """Whatever the block does to the parameters, constants, imposed values and state, they are
    restored afterwards (also on an error)."""
    values, state = dict(model.parameter_values), model.state.x.array.copy()
    constants = {c: np.array(c.value, copy=True) for c in (*forms.constants, *model._load_values)}
    functions = {f: f.x.array.copy() for f in forms.functions}
    imposed = [(i.amplitude, i.target.x.array.copy()) for i in model._imposed]
    try:
        yield
    finally:
        model.set_parameters(values)
        for c, value in constants.items():
            c.value = value
        for f, array in functions.items():
            f.x.array[:] = array
        for i, (amplitude, target) in zip(model._imposed, imposed):
            i.amplitude, i.target.x.array[:] = amplitude, target
        model.state.x.array[:] = state
        model.state.x.scatter_forward()


def value_derivatives(
    model: Model, moved: Moved | None = None, update: Callable[[], None] | None = None
) -> ValueDerivatives:
    """∂c/∂μ of every value the parameters set, dx_D/dμ and ∂(scalar load)/∂μ, at the current μ
    and time: differences of the model's own assignment (:meth:`Model.set_parameters` at a few μ
    around the current one, reading the constants, functions, imposed values and loads; no
    assembly). Exact for values that depend linearly on μ, second-order accurate otherwise (see
    :func:`_stencil`). The model is left as it was: parameters, constants, time, load values, state.

    ``moved``: what a start sets at μ, moved along (f + (μ_i' − μ_i) ∂f/∂μ_i at each difference
    point). The coefficients θ of state-dependent loads (balanced gravity's centre of mass and
    pressure) are values too: at the fixed state θ = Θ(x; c, ξ) is set again at each point
    (``update``: default, on the whole mesh; a hyper-reduced model's on its sample), so their
    explicit dependence on μ — the weight's direction, an imaged reference's dX — enters ∂R/∂μ.

    The loads are differentiated as :meth:`Model.set_time` last set them (its time, load factor
    and reference time); a model whose loads were set otherwise is refused. Collective (the
    first call compiles the model's derivative forms).
    """
    forms = derivative_forms(model)
    along = dict(moved.functions) if moved is not None else {}
    if unknown := [f.name for f in along if f not in forms.functions]:
        raise ParameterError(f"sensitivities: the start sets {', '.join(unknown)}, which no form of the model holds")
    terms = model.state_dependent

    def on_the_whole_mesh() -> None:
        for term in terms:
            term.update()

    refresh = update or on_the_whole_mesh
    parameters = model.parameters
    size = len(model.state.x.array)
    constants = {c: np.zeros((*np.shape(c.value), len(parameters))) for c in forms.constants}
    functions = {f: np.zeros((len(f.x.array), len(parameters))) for f in forms.functions}
    imposed = np.zeros((size, len(parameters)))
    loads = {label: np.zeros(len(parameters)) for label in model.scalar_loads()}
    amplitudes = np.zeros((len(model.imposed), len(parameters)))
    with _restored(model, forms):
        kept = {f: f.x.array.copy() for f in along}
        current = dict(model.parameter_values)
        given = [np.array(v.value, copy=True) for v in model._load_values]
        model.set_parameters(current)
        if not all(np.array_equal(v.value, g) for v, g in zip(model._load_values, given)):
            raise ParameterError(
                "sensitivities: the loads were not set by Model.set_time; derivatives follow what it sets"
            )
        for i, parameter in enumerate(parameters):
            points, weights = _stencil(parameter, current[parameter.name])
            for point, weight in zip(points, weights):
                model.set_parameters({parameter.name: float(point)})
                for f, derivative in along.items():
                    f.x.array[:] = kept[f] + (point - current[parameter.name]) * derivative[:, i]
                if terms:
                    refresh()  # θ = Θ(x; values here), at the fixed state
                for c, d in constants.items():
                    d[..., i] += weight * np.asarray(c.value, dtype=float)
                for f, d in functions.items():
                    d[:, i] += weight * f.x.array
                x_D = np.zeros(size)
                for bc in model.bcs:
                    bc.set(x_D)
                imposed[:, i] += weight * x_D
                for label, value in model.scalar_loads().items():
                    loads[label][i] += weight * value
                amplitudes[:, i] += weight * model.imposed_amplitudes()
            model.set_parameters(current)
    if terms:  # the terms' own record (their last Θ's linearisation) back at the values restored
        refresh()
    start = None if moved is None else moved.start
    return ValueDerivatives(parameters.names, constants, functions, imposed, loads, amplitudes, start)


def residual_derivatives(model: Model, derivatives: ValueDerivatives | None = None) -> np.ndarray:
    """∂R/∂μ_i = Σ_k ∂R/∂c_k ∂c_k/∂μ_i at the current state (fixed x, imposed rows included):
    owned rows, one column per parameter. One assembly of the compiled form per parameter.
    Collective."""
    forms = derivative_forms(model)
    derivatives = derivatives or value_derivatives(model)
    vector = fem.Function(model.space).x
    owned = owned_size(model.space)
    columns = np.zeros((owned, len(derivatives.names)))
    for i in range(len(derivatives.names)):
        forms.set_weights(derivatives, i)
        if forms.residual is None:
            break
        columns[:, i] = assemble_owned(forms.residual, vector, owned)
    return columns


def _jacobian(jacobian_form: fem.Form) -> PETSc.Mat:
    """K assembled without imposed values (their rows and columns kept): destroy it after."""
    K = create_matrix(jacobian_form)
    assemble_matrix(K, jacobian_form)  # type: ignore[arg-type]  # the into-a-matrix overload (singledispatch) is not in the hints
    K.assemble()
    return K


def state_derivatives(model: Model, jacobian_form: fem.Form, derivatives: ValueDerivatives | None = None) -> np.ndarray:
    """Direct sensitivities dx/dμ at the current (converged) state: owned rows, one column per parameter.

    dx = dx_D + y with y = 0 on the imposed dofs and K_ff y_f = −(∂R/∂μ + K dx_D)_f: K is
    assembled once without the imposed values (``jacobian_form``: the exact Jacobian of
    ``model.residual``, e.g. the solver's compiled one), K dx_D formed, then the imposed rows
    and columns of K replaced by the identity and K factorised once (MUMPS LU) for every
    parameter. Collective.
    """
    derivatives = derivatives or value_derivatives(model)
    comm, owned = model.geometry.mesh.comm, owned_size(model.space)
    n = len(derivatives.names)
    if n == 0:
        return np.zeros((owned, 0))
    low_rank = _low_rank(model)
    dR = residual_derivatives(model, derivatives)
    dx_D = np.ascontiguousarray(derivatives.imposed[:owned])
    K = _jacobian(jacobian_form)
    rhs = -dR - apply(K, dx_D, comm)
    imposed = model.constrained_dofs()
    rhs[imposed] = dx_D[imposed]
    index_map = model.space.dofmap.index_map
    K.zeroRowsColumns((index_map.local_range[0] * model.space.dofmap.index_map_bs + imposed).astype(PETSc.IntType))
    ksp = factorised(K)
    b, x = K.createVecLeft(), K.createVecRight()

    def solve(column: np.ndarray) -> np.ndarray:
        b.array[:] = column
        ksp.solve(b, x)
        if ksp.getConvergedReason() < 0:  # type: ignore[operator]  # an int at run time; the stubs say a class
            raise ParameterError(
                f"sensitivities: the linear solve with the Jacobian failed (reason {ksp.getConvergedReason()})"
            )
        return x.array.copy()

    try:
        result = np.column_stack([solve(rhs[:, i]) for i in range(n)])
        if low_rank is not None:  # (K + U Wᵀ)⁻¹ from K⁻¹: U vanishes on the imposed rows, which stay dx_D
            terms, U, W = low_rank
            result = terms.woodbury(result, U, W, solve)
    finally:
        for obj in (b, x, ksp, K):
            obj.destroy()
    return result


def reduced_state_derivatives(
    model: Model, V: np.ndarray, jacobian_form: fem.Form, derivatives: ValueDerivatives | None = None
) -> np.ndarray:
    """Reduced sensitivities dq/dμ = −(Vᵀ K V)⁻¹ Vᵀ (∂R/∂μ + K dx₀/dμ) of x = x₀ + V q at the
    current (converged) reduced state, shape (k, parameters). ``V``: the basis's owned rows
    (vanishing on imposed dofs); dx₀/dμ = ``derivatives.start_state``. The state's derivative
    is V dq/dμ + dx₀/dμ (pass it to :func:`output_derivatives`). Collective."""
    derivatives = derivatives or value_derivatives(model)
    comm, owned = model.geometry.mesh.comm, owned_size(model.space)
    V = np.ascontiguousarray(V)
    dR = residual_derivatives(model, derivatives)
    dx0 = derivatives.start_state(owned)
    K = _jacobian(jacobian_form)
    try:
        KV, Kdx0 = apply(K, V, comm), apply(K, dx0, comm)
    finally:
        K.destroy()
    low_rank = _low_rank(model)
    if low_rank is not None:  # J = K + U Wᵀ
        _, U, W = low_rank
        KV, Kdx0 = KV + U @ gram(W, V, comm), Kdx0 + U @ gram(W, dx0, comm)
    return -np.linalg.solve(gram(V, KV, comm), gram(V, dR + Kdx0, comm))


def _low_rank(model: Model) -> tuple[StateDependent, np.ndarray, np.ndarray] | None:
    """The state-dependent loads' low-rank tangent U Wᵀ at the current state (θ set again from
    it), or None without such loads (collective)."""
    terms = StateDependent(model)
    if not terms:
        return None
    terms.update()
    U, W = terms.low_rank()
    return terms, U, W


def output_derivatives(
    model: Model,
    outputs: object,
    solver: Solver | None,
    state_derivative: np.ndarray | None = None,
    derivatives: ValueDerivatives | None = None,
) -> dict[str, object]:
    """d(outputs)/dμ at the current converged state, in the structure of
    :class:`lungmech.fem.parametric.Outputs` with the parameters on a last axis: volume and
    strain_energy (n,), probes (points, 3, n), loads {label: (n,)}.

    dV/dμ = ∂V/∂x · dx/dμ (+ Σ_k ∂V/∂c_k ∂c_k/∂μ on a shape map: dX = det G dX₀);
    dE/dμ = ∂E/∂x · dx/dμ + Σ_k ∂E/∂c_k ∂c_k/∂μ; probes: the displacement
    part of dx/dμ at the points (on an image, u = w − ξ: less dξ/dμ there); loads: ∂(load value)/∂μ. ``state_derivative`` (owned rows,
    parameters) is dx/dμ if known (a reduced model's V dq/dμ + dx₀/dμ); otherwise the direct
    sensitivities with ``solver.jacobian_form``, which must be the exact Jacobian of
    ``model.residual``. Collective.
    """
    forms = derivative_forms(model)
    derivatives = derivatives or value_derivatives(model)
    comm, owned, n = forms.comm, owned_size(model.space), len(derivatives.names)
    dx = (
        state_derivative
        if state_derivative is not None
        else state_derivatives(model, cast("Solver", solver).jacobian_form, derivatives)  # given for this
    )
    dx = np.asarray(dx, dtype=float).reshape(owned, n)
    vector = fem.Function(model.space).x

    def gradient(form: fem.Form) -> np.ndarray:
        return assemble_owned(form, vector, owned)[:, None]

    volume = gram(gradient(cast(fem.Form, forms.volume_gradient)), dx, comm)[0]  # the full model's forms have it
    energy = gram(gradient(cast(fem.Form, forms.energy_gradient)), dx, comm)[0]  # the full model's forms have it
    for total, explicit in ((volume, forms.volume), (energy, forms.energy)):
        for i in range(n if explicit is not None else 0):
            forms.set_weights(derivatives, i)
            total[i] += comm.allreduce(fem.assemble_scalar(cast(fem.Form, explicit)), op=MPI.SUM)
    result: dict[str, object] = {"volume": volume, "strain_energy": energy}
    probe = getattr(outputs, "probe", None)
    if probe is not None:
        direction = fem.Function(model.space)
        reference = derivatives.functions.get(model.reference_map) if model.reference_map is not None else None
        columns = []
        for i in range(n):
            direction.x.array[:owned] = dx[:, i]
            direction.x.scatter_forward()
            moved = direction.sub(0).collapse() if model.multi_field else direction.copy()
            if reference is not None:  # on an image u = w − ξ: du/dμ = dw/dμ − dξ/dμ
                moved.x.array[:] -= reference[:, i]
            columns.append(probe(moved))
        result["probes"] = np.stack(columns, axis=-1) if columns else np.zeros((len(probe.points), 3, 0))
    result["loads"] = {label: d.copy() for label, d in derivatives.loads.items()}
    return result
