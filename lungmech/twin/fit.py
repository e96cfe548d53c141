"""A lung's parameters from its images: bounded nonlinear least squares on a model's answers.

Each image pair is a :class:`View`: a model of the lung imaged at end-expiration (its start, t₀)
whose probes are the surface nodes x_i, the end-inspiration segmentation's data
(:mod:`lungmech.twin.surface`), the time of end-inspiration T, and the values of the
parameters this pair fixes (its posture). The residual of a view at μ is, in metres,

    r_i(μ) = d(x_i + w_i(T; μ)) − d₀(x_i)                  for each surface node,
    r_V(μ) = ((V(T; μ) − V(t₀)) − (V_seg − V₀_seg)) / Σ a_i   for the volume (a mean normal offset),

d₀ and V₀_seg the end-expiration segmentation's (its ``baseline``; zero without one): a
registered mesh does not lie on the segmented surface — its facets are chords, and the
registration, which matches volumes, leaves its nodes about half a millimetre outside (on a
coarse lung at 4 mm voxels) —, and what a breath must reproduce is each node's change of
distance and the volume's change, not the offset the mesh had from the start (left in, it
biased a breath's depth by 15 %). w = u(T) − u(t₀) is the motion from the image (the probes' displacement from the reference,
u = w − ξ, at both times). Its Jacobian comes from the model's own exact sensitivities
(``solve(μ, sensitivities=True)``): ∂r_i/∂μ = ∇d · ∂w_i/∂μ and ∂r_V/∂μ = (∂V/∂μ)/Σ a_i —
never from differences of solves. The views' residuals are stacked; the estimated parameters
are shared, in the unit box of the model's ranges (log parameters in log μ), which is what
SciPy's ``least_squares`` (method 'trf', the box as its bounds) iterates on: θ ∈ [0, 1]^p,
∂μ/∂θ = (high − low), or μ ln(high/low) on a log scale.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from time import perf_counter

import numpy as np
from scipy.optimize import least_squares

from lungmech.errors import ParameterError
from lungmech.fem.parameters import Parameter
from lungmech.fem.parametric import ParametricModel
from lungmech.twin.surface import Surface, SurfaceNodes

__all__ = ["Estimate", "Fit", "Interior", "View", "estimate", "predict"]


@dataclass(frozen=True)
class Interior:
    """Interior motion as data (:mod:`lungmech.twin.displacement`): at ``points`` (m, 3; the
    model probes them after the surface nodes), the ``observed`` displacement from
    end-expiration to end-inspiration (m, 3; m), its rows weighed by ``weight``."""

    points: np.ndarray
    observed: np.ndarray
    weight: float = 1.0
    smoothing: float | None = None  # m: the field's, for the record


@dataclass(frozen=True)
class View:
    """One image pair's data and the model that predicts it (see the module's doc); with
    ``interior`` data, three rows more a point, after the volume's."""

    model: ParametricModel
    nodes: SurfaceNodes
    surface: Surface
    time: float
    fixed: Mapping[str, float] = field(default_factory=dict)
    name: str = "view"
    baseline: Surface | None = None
    interior: Interior | None = None

    @property
    def rows(self) -> int:
        """Its residual's length: one per surface node, the volume, three per interior point."""
        return len(self.nodes.points) + 1 + 3 * self.interior_count

    @property
    def interior_count(self) -> int:
        return 0 if self.interior is None else len(self.interior.points)


@dataclass(frozen=True)
class Prediction:
    """A view's residual r (rows), its Jacobian by the parameters (rows, all the model's), and
    the predicted node positions at T (nodes, 3; m) and volume (m³)."""

    residual: np.ndarray
    jacobian: np.ndarray
    positions: np.ndarray
    volume: float


def predict(view: View, values: Mapping[str, float], sensitivities: bool = True) -> Prediction:
    """The view's residual and Jacobian at the parameter ``values`` (one solve with
    sensitivities from t₀ to T; without ``sensitivities``, the Jacobian has no columns)."""
    solution = view.model.solve(values, sensitivities=sensitivities, times=[view.model.stepping.start, view.time])
    outputs = solution.outputs
    probes = np.asarray(outputs["probes"])
    n, m = len(view.nodes.points), view.interior_count
    if probes.shape[1] != n + m:
        raise ParameterError(
            f"view {view.name}: the model probes {probes.shape[1]} points, not the {len(view.nodes.points)} surface "
            f"nodes of its image" + (f" and its {m} interior points" if m else "")
        )
    moved = probes[1] - probes[0]  # w(T) = u(T) − u(t₀)
    motion = moved[:n]
    positions = view.nodes.points + motion
    distance, gradient = view.surface.distance(positions)
    scale = view.nodes.area
    volumes = np.asarray(outputs["volume"])
    volume = float(volumes[1])
    if view.baseline is None:
        residual = np.append(distance, (volume - view.surface.volume) / scale)
    else:  # the changes from end-expiration (see the module's doc)
        offset, _ = view.baseline.distance(view.nodes.points)
        change = (volume - float(volumes[0])) - (view.surface.volume - view.baseline.volume)
        residual = np.append(distance - offset, change / scale)
    weight = 1.0 if view.interior is None else view.interior.weight
    if view.interior is not None:  # ω (w_j − u_obs,j), three rows a point
        residual = np.append(residual, weight * (moved[n:] - view.interior.observed).ravel())
    if not sensitivities:
        return Prediction(residual, np.zeros((len(residual), 0)), positions, volume)
    derivatives = solution.sensitivities or {}
    moved_derivative = np.asarray(derivatives["probes"])[1] - np.asarray(derivatives["probes"])[0]
    jacobian = np.vstack(
        [
            np.einsum("nc,ncp->np", gradient, moved_derivative[:n]),
            np.asarray(derivatives["volume"])[1][None, :] / scale,
        ]
    )
    if view.interior is not None:
        jacobian = np.vstack([jacobian, weight * moved_derivative[n:].reshape(3 * m, -1)])
    return Prediction(residual, jacobian, positions, volume)


class Fit:
    """The least-squares problem of ``views`` in the ``estimated`` parameters (shared by every
    view; the others at each view's ``fixed`` values, else the defaults). ``offset``: added to
    the residual (a resampled noise; see :func:`lungmech.twin.uncertainty.resampled`)."""

    def __init__(self, views: Sequence[View], estimated: Sequence[str]) -> None:
        if not views:
            raise ParameterError("personalisation needs at least one pair of images")
        if not estimated:
            raise ParameterError("personalisation needs at least one parameter to estimate")
        self.views = tuple(views)
        box = self.views[0].model.parameters
        self.parameters: tuple[Parameter, ...] = tuple(box.named(name) for name in estimated)
        for view in self.views:
            for name in estimated:
                view.model.parameters.named(name)
                if name in view.fixed:
                    raise ParameterError(f"view {view.name}: parameter '{name}' is both estimated and fixed")
            view.model.parameters.values(view.fixed)  # known names, inside their ranges
        self.names = tuple(p.name for p in self.parameters)
        self.rows = sum(view.rows for view in self.views)
        self.evaluations = 0
        self._last: tuple[np.ndarray, list[Prediction]] | None = None

    def values(self, theta: np.ndarray) -> dict[str, float]:
        """The estimated parameters' values at unit coordinates θ."""
        return {p.name: p.from_unit(float(t)) for p, t in zip(self.parameters, theta)}

    def unit(self, values: Mapping[str, float]) -> np.ndarray:
        """Unit coordinates θ of the estimated parameters' ``values``."""
        return np.array([p.to_unit(float(values[p.name])) for p in self.parameters])

    def predictions(self, theta: np.ndarray) -> list[Prediction]:
        """Each view's prediction at θ (solved once per θ)."""
        theta = np.asarray(theta, dtype=float)
        if self._last is None or not np.array_equal(self._last[0], theta):
            values = self.values(theta)
            self._last = (theta.copy(), [predict(view, dict(view.fixed) | values) for view in self.views])
            self.evaluations += 1
        return self._last[1]

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """r(θ), every view's rows stacked (m)."""
        return np.concatenate([p.residual for p in self.predictions(theta)])

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """∂r/∂θ (rows, estimated parameters), from the models' exact sensitivities."""
        values = self.values(theta)
        columns = []
        for view, prediction in zip(self.views, self.predictions(theta)):
            index = [list(view.model.parameters.names).index(name) for name in self.names]
            columns.append(prediction.jacobian[:, index])
        chain = np.array([p.unit_derivative(values[p.name]) for p in self.parameters])
        return np.vstack(columns) * chain[None, :]

    def surface_rows(self) -> list[np.ndarray]:
        """The row indices of each view's surface distances (its volume row follows them)."""
        rows, start = [], 0
        for view in self.views:
            rows.append(np.arange(start, start + len(view.nodes.points)))
            start += view.rows
        return rows

    def interior_rows(self) -> list[np.ndarray]:
        """The row indices of each view's interior data (none without), after its volume row."""
        rows, start = [], 0
        for view in self.views:
            first = start + len(view.nodes.points) + 1
            rows.append(np.arange(first, first + 3 * view.interior_count))
            start += view.rows
        return rows


@dataclass(frozen=True)
class Estimate:
    """A least-squares estimate: the ``values`` (physical units) and ``unit`` coordinates θ̂ of
    the estimated parameters, the ``residual`` (m) and ``jacobian`` (∂r/∂θ) there, which bound
    each is at (``active``: "lower", "upper" or None), the optimiser's ``history`` (each
    evaluation's values and cost ½‖r‖² in m²), its ``message``, its time (s), and the
    ``offset`` that was added to the residual (m)."""

    names: tuple[str, ...]
    values: dict[str, float]
    unit: np.ndarray
    residual: np.ndarray
    jacobian: np.ndarray
    active: dict[str, str | None]
    history: list[dict[str, object]]
    evaluations: int
    message: str
    seconds: float
    offset: np.ndarray

    @property
    def cost(self) -> float:
        """½‖r‖² at the estimate (m²)."""
        return 0.5 * float(self.residual @ self.residual)


def estimate(
    fit: Fit,
    start: Mapping[str, float] | None = None,
    offset: np.ndarray | None = None,
    tolerance: float = 1e-10,
    most: int = 60,
) -> Estimate:
    """The bounded least-squares estimate of ``fit``'s parameters from ``start`` (default: the
    defaults), by trust-region reflective steps in the unit box (SciPy's ``least_squares``,
    method 'trf', the exact Jacobian); ``offset`` is added to the residual; ``tolerance`` on
    the relative change of the cost and of θ; at most ``most`` evaluations."""
    first = {p.name: p.default for p in fit.parameters} | {n: v for n, v in (start or {}).items() if n in fit.names}
    theta0 = fit.unit({p.name: p.check(first[p.name]) for p in fit.parameters})
    shift = np.zeros(fit.rows) if offset is None else np.asarray(offset, dtype=float)
    if shift.shape != (fit.rows,):
        raise ParameterError(f"the offset needs {fit.rows} rows (got shape {shift.shape})")
    history: list[dict[str, object]] = []

    def residual(theta: np.ndarray) -> np.ndarray:
        r = fit.residual(theta) + shift
        history.append({"evaluation": len(history) + 1, "values": fit.values(theta), "cost": 0.5 * float(r @ r)})
        return r

    tic = perf_counter()
    result = least_squares(
        residual,
        theta0,
        jac=fit.jacobian,
        bounds=(0.0, 1.0),
        method="trf",
        x_scale=1.0,
        ftol=tolerance,
        xtol=tolerance,
        gtol=tolerance,
        max_nfev=most,
    )
    theta = np.clip(result.x, 0.0, 1.0)
    # at a bound: within the optimiser's reach of it (its own active mask misses a bound it
    # approaches from inside, as trust-region reflective steps do)
    reach = max(1e3 * tolerance, 1e-6)
    side = np.where(theta <= reach, -1, np.where(theta >= 1.0 - reach, 1, result.active_mask))
    sides: dict[int, str | None] = {-1: "lower", 0: None, 1: "upper"}
    return Estimate(
        fit.names,
        fit.values(theta),
        theta,
        fit.residual(theta) + shift,
        fit.jacobian(theta),
        {name: sides[int(at)] for name, at in zip(fit.names, side)},
        history,
        int(result.nfev),
        str(result.message),
        perf_counter() - tic,
        shift,
    )
