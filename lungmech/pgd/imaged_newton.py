"""The a priori PGD of an imaged body: its unloaded reference ξ(μ) and its breath from the image,
each by a Newton–PGD over the box, no full solve.

On an imaged body (:mod:`lungmech.fem.inverse_motion`) a full solve at μ first finds the
unloaded reference X = x + ξ(μ) of the image — the inverse problem R_ξ(x_ξ; μ) = 0 at the loads
of t₀, its state x_ξ = (ξ, the other fields) — and then the breath from the image, w = 0 at t₀,
ξ(μ) a coefficient of its forms. The a priori PGD takes the same two steps over the box, each
a Newton–PGD (:func:`lungmech.pgd.newton.newton_pgd`) at the same quadrature points:

1. the inverse problem along its own path, the loads of t₀ raised from zero by a factor
   s ∈ (0, 1] as a full solve raises them:

       x_ξ(μ) ≈ x_ξ,rest + Q_ξ R_ξ q_ξ(μ);

2. the breath from t₀ through the output times, each point's state the image on that ξ(μ_q),
   with the inverse problem's other fields (the lung's Φs) — the hand-over a full solve makes
   (:class:`~lungmech.fem.inverse_motion.Handover`) — plus the breath's own terms:

       x(μ, t) ≈ x₀(μ) + Q R_t q_t(μ),   x₀(μ) = the image (w = 0) on x_ξ(μ)'s fields.

Both take the tangents at the points' states (``benchmarks/pgd_tangent.py``): the image is
prestressed, its tangent at μ far from the material's at rest, which only a new term's space
part takes. The answer is then what a fitted PGD of the imaged body holds
(:mod:`lungmech.pgd.imaged`): its breath from t₀ on — x₀(μ)'s terms on at every time, with the
breath's own at their output time, their space modes W-orthonormal together — and ξ(μ) as its
:class:`~lungmech.pgd.imaged.Reference`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import Handover, InverseMotion, vector_entries
from lungmech.fem.parametric import FullOrderModel, output_times
from lungmech.fem.quantities import Probe
from lungmech.parallel.linalg import apply, gram, gram_schmidt
from lungmech.parallel.owned import owned_size
from lungmech.pgd import imaged
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.fitted import energy_fit
from lungmech.pgd.fitting import FIT
from lungmech.pgd.greedy import Options, Round
from lungmech.pgd.indicator import indicator
from lungmech.pgd.model import ESTIMATE, PGDModel, answerable, load_fractions
from lungmech.pgd.newton import INTERVALS, Newton, Path, axes_of, joined, newton_pgd, quadrature, states
from lungmech.pgd.online import online
from lungmech.pgd.timeline import SampledTimeline
from lungmech.rom.basis import inner_product

__all__ = ["build_imaged"]


def build_imaged(
    full: FullOrderModel,
    probe_points: Sequence[Sequence[float]] = (),
    intervals: int = INTERVALS,
    options: Options | None = None,
    newton: Newton = Newton(),
) -> tuple[PGDModel, list[Round]]:
    """The a priori :class:`PGDModel` of the imaged body ``full`` (started by its inverse motion)
    over its parameters' box (module docstring): splines on ``intervals`` intervals, the
    greedy's ``options`` at every iteration of both Newton–PGDs, ``newton``'s sample and
    stopping; with every round of the breath's greedy. Refused in one line before any work
    where it cannot answer, and where either Newton–PGD does not converge. Collective; the
    full model is reset."""
    model, stepping, start = full.model, full.stepping, full.start
    if not isinstance(start, InverseMotion):
        raise ParameterError("PGD: build_imaged answers an imaged body, a full model started by its inverse motion")
    answerable(model)
    load_fractions(model, stepping)
    options = options or Options()
    axes = axes_of(model, intervals)
    sample = quadrature(model, axes, newton)
    t0, times = float(stepping.start), output_times(model, stepping)
    inverse, comm = start.inverse, model.geometry.mesh.comm
    full.reset()
    W: PETSc.Mat = inner_product(inverse, "energy")
    try:
        inverse.set_time(t0, 0.0)  # (its tangent with the loads 0)
        raised = Path(0.0, np.array([1.0]), lambda s: inverse.set_time(t0, s), _raised(start.body))
        unloaded = newton_pgd(inverse, sample, raised, options, newton, W, at_states=True)
    finally:
        W.destroy()
    reference = Decomposition(tuple(axes), unloaded.found.Q.copy(), *unloaded.blocks[-1])
    image = _Image(full, reference)
    W = inner_product(model, "energy")
    try:
        model.set_time(t0, 0.0)
        breath = newton_pgd(
            model, sample, Path(t0, times, model.set_time), options, newton, W, at_states=True, start=image
        )
        seconds = breath.seconds | {f"reference_{name}": value for name, value in unloaded.seconds.items()}
        tic = time.perf_counter()
        Q, blocks = breath.found.Q, breath.blocks
        decomposition, timeline = _from_image(joined(breath.found, blocks, times, t0), image.fields(), W, t0, comm)
        energies = breath.march.energies(
            [np.zeros((Q.shape[0], len(sample.units))), *states(Q, blocks, sample)], [t0, *times]
        )
        energy, separated_energy = energy_fit(
            comm, energies, sample.units, [tuple(axes)], FIT, newton.seed, t0, timeline.times
        )
        seconds["energy"] = time.perf_counter() - tic
        tic = time.perf_counter()
        model.set_time(stepping.end)
        last = Decomposition(tuple(axes), Q.copy(), *blocks[-1])
        estimates = indicator(model, last, W, model.parameters.sample(ESTIMATE, seed=31), start=image)
        seconds["indicator"] = time.perf_counter() - tic
    finally:
        W.destroy()
        full.reset()
    tic = time.perf_counter()
    probe = Probe(model.geometry.mesh, probe_points) if len(probe_points) else None
    outputs = online(model, None, decomposition.modes, probe)
    xi = imaged.reference(full, reference, probe)
    seconds["outputs"] = time.perf_counter() - tic
    built = breath.record(options, newton) | {
        "method": breath.method + "; the reference ξ(μ) by its own, the loads of t₀ raised from 0",
        "reference_newton_iterations": unloaded.iterations,
        "reference_terms": reference.terms,
        "energy_held_out": energy.held_out,
        "estimate": float(estimates.max()),  # the breath's, from the image on its reference
        "indicator_points": estimates.tolist(),
        "seconds": seconds,
    }
    answer = PGDModel(
        model,
        decomposition,
        outputs,
        stepping,
        probe_points,
        built,
        timeline=timeline,
        energy=separated_energy,
        reference=xi,
    )
    return answer, breath.rounds


def _raised(body: str) -> Callable[[float], str]:
    """Where the reference's path is, for a message: its loads' fraction of t₀'s."""
    return lambda s: f"the {body}'s reference, its loads at {100 * s:.3g} %"


class _Image:
    """The image on the ``reference`` fit's ξ(μ) (a decomposition of the inverse problem's
    state from its rest): called at μ, sets the breath's reference map to ξ(μ) and gives its
    start, the image (w = 0) with the inverse problem's other fields — as a full solve hands
    them over (:class:`~lungmech.fem.inverse_motion.Handover`). Collective."""

    def __init__(self, full: FullOrderModel, reference: Decomposition) -> None:
        assert isinstance(full.start, InverseMotion)  # (build_imaged's)
        self.model, self.inverse, self.reference = full.model, full.start.inverse, reference
        self.handover = Handover(self.model, self.inverse)
        self.owned, self.owned_inverse = owned_size(self.model.space), owned_size(self.inverse.space)
        with self.inverse.kept_state():
            self.inverse.reset()
            self.rest = self.inverse.state.x.array[: self.owned_inverse].copy()
        self._known: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, point: Mapping[str, float]) -> np.ndarray:
        key = tuple(float(point[name]) for name in self.model.parameters.names)
        if key not in self._known:
            state = self.inverse.state
            state.x.array[: self.owned_inverse] = self.rest + self.reference.state(point)
            state.x.scatter_forward()
            self.handover.hand_over(self.inverse, self.model)
            assert self.model.reference_map is not None  # (a model of an image's motion)
            xi = self.model.reference_map.x.array[: self.handover.owned_vector].copy()
            self._known[key] = (self.model.state.x.array[: self.owned].copy(), xi)
        start, xi = self._known[key]
        self.model.set_reference_map(xi)
        return start

    def fields(self) -> Decomposition:
        """x₀(μ) − the breath's rest as a decomposition: ξ's terms, their modes' vector rows zero
        (w = 0: the image), the other fields' rows the inverse problem's. Refused where the two
        rests differ outside ξ (a lungmech error: the hand-over would not be affine in the fit)."""
        vector = vector_entries(self.model)
        vector = vector[vector < self.owned]
        self.model.set_reference_map(np.zeros(self.handover.owned_vector))  # the rest: w = ξ = 0
        with self.model.kept_state():
            self.model.reset()
            rest = self.model.state.x.array[: self.owned].copy()
        image = self.rest.copy()
        image[vector] = 0.0
        comm = self.model.geometry.mesh.comm
        if comm.allreduce(float(np.abs(image - rest).max(initial=0.0)), op=MPI.MAX) > 1e-12 * max(
            1.0, comm.allreduce(float(np.abs(rest).max(initial=0.0)), op=MPI.MAX)
        ):
            raise ParameterError("PGD: the imaged body's rest differs from its inverse problem's (a lungmech error)")
        modes = self.reference.modes.copy()
        modes[vector] = 0.0
        return Decomposition(self.reference.axes, modes, self.reference.reduced, self.reference.coefficients)


def _from_image(
    breath: tuple[Decomposition, SampledTimeline], fields: Decomposition, W: PETSc.Mat, t0: float, comm: MPI.Comm
) -> tuple[Decomposition, SampledTimeline]:
    """The breath from t₀ on (module docstring): the image's fields' terms on at t₀ and at every
    output time, the breath's own at theirs, all on one W-orthonormal set of space modes (the
    columns of [Q_breath, Q_fields], Q T = [Q_breath, Q_fields])."""
    terms, timeline = breath
    raw = np.hstack([terms.modes, fields.modes])
    Q, kept = gram_schmidt(raw, W, comm)
    if all(k < terms.size for k in kept):  # the fields do not move with μ (a displacement alone, say)
        fields = Decomposition(
            fields.axes, fields.modes[:, :0], fields.reduced[:0, :0], [X[:0] for X in fields.coefficients]
        )
        raw = raw[:, : terms.size]
    T = gram(apply(W, Q, comm), raw, comm)
    m, n = terms.modes.shape[1], fields.modes.shape[1]
    reduced = T @ np.block(
        [
            [terms.reduced, np.zeros((m, fields.terms))],
            [np.zeros((n, terms.terms)), fields.reduced],
        ]
    )
    coefficients = [np.vstack([a, b]) for a, b in zip(terms.coefficients, fields.coefficients)]
    values = np.block(
        [
            [np.zeros((terms.terms, 1)), timeline.values],
            [np.ones((fields.terms, 1 + len(timeline.times)))],
        ]
    )
    times = np.concatenate([[t0], timeline.times])
    return Decomposition(terms.axes, Q, reduced, coefficients), SampledTimeline(t0, times, values)
