"""A full model's load path at one parameter point, as a reduction trains on it — solved here, or
elsewhere and brought here in the canonical dof order.

A :class:`LoadPath` holds what a greedy training takes from one full solve: the snapshots (every
accepted state of the approach to μ and of the load path, minus the start state), the solution
(its states at the output times, for the true error of the reduced model there) and, when a
hyper-reduction is trained on them, every Newton iterate ``(state, time, parameters)``. An
imaged body's path (:class:`~lungmech.fem.inverse_motion.InverseMotion` start) holds its two
unknowns' (:mod:`lungmech.rom.imaged`): the breath's accepted states minus its own start at μ,
and the inverse problem's solution at μ. All arrays are a rank's owned rows.

:func:`solve_path` solves one on the model at hand. A training that runs its full solves
elsewhere — other processes, other groups of ranks, other machines
(:mod:`lungmech.app.training_paths`) — moves them as :func:`canonical` arrays (one rank holds
them, in the partition-independent order of :mod:`lungmech.parallel.layout`) and places them
back with :func:`placed`: the numbers are copied, never recomputed, so a path solved on the same
number of ranks is the same to the last bit wherever it was solved.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from lungmech.errors import ParameterError
from lungmech.fem.inverse_motion import InverseMotion
from lungmech.fem.parametric import FullOrderModel, Solution, Step
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.start import one_state
from lungmech.parallel.layout import Layout
from lungmech.parallel.owned import owned_size, owned_values
from lungmech.rom import ecsw
from lungmech.rom.basis import snapshot

__all__ = ["LoadPath", "Paths", "Run", "canonical", "collected", "placed", "relative_to", "serial", "solve_path"]

Iterate = tuple[np.ndarray, float, dict[str, float]]  # a Newton iterate: (owned rows, time, μ)
Run = tuple[Mapping[str, float], float | Sequence[float]]  # a parameter point and the load scale(s)


@dataclass(frozen=True)
class LoadPath:
    """One full solve at ``solution.parameters``: ``snapshots`` (owned rows × accepted states),
    its ``solution`` (states: owned rows at the output times; outputs: volume, strain energy),
    its Newton ``iterates`` (empty unless asked for) and, for an imaged body, ``inverse``: the
    inverse problem's solution x_ξ(μ) (owned rows of its state; None otherwise)."""

    snapshots: np.ndarray
    solution: Solution
    iterates: tuple[Iterate, ...] = ()
    inverse: np.ndarray | None = None


Paths = Callable[[Sequence[Run], bool], list[LoadPath]]
"""Full load paths at (parameter point, load scale) runs, in order (``iterates``: with their
Newton iterates)."""


def solve_path(
    full: FullOrderModel,
    point: Mapping[str, float],
    start: np.ndarray,
    iterates: bool = False,
    scale: float | Sequence[float] = 1.0,
) -> LoadPath:
    """``full``'s load path at ``point``, the loads' change scaled by ``scale``; snapshots
    relative to ``start`` (a full local array, the start state at the defaults). An imaged
    body's (an :class:`InverseMotion` start; ``start`` is not read): the load path's snapshots
    relative to its own start at μ, and the inverse problem's solution there; its iterates are
    refused (its hyper-reduction trains on both problems' in the build's process). Collective."""
    model, columns, kept = full.model, [], []
    owned = owned_size(model.space)
    imaged = full.start if isinstance(full.start, InverseMotion) else None
    if imaged is not None and iterates:
        raise ParameterError("an imaged body's Newton iterates are taken in the build's own process")
    inverse: list[np.ndarray] = []
    relative_to = [start]  # the start at the defaults, or an imaged body's own at μ

    def keep(step: Step) -> None:
        if imaged is not None and step.phase == "start":
            relative_to[0] = model.state.x.array.copy()  # the image: w = 0, and x_ξ(μ)'s other fields
            inverse.append(owned_values(imaged.inverse.state))
        elif step.phase == "path" or (step.phase == "approach" and imaged is None):
            columns.append(snapshot(model, relative_to[0]))

    def seen(iteration: int) -> None:
        kept.append((model.state.x.array[:owned].copy(), float(model.time), dict(model.parameter_values)))

    watching = ecsw.iterates(cast(NewtonSolver, full.solver), seen) if iterates else contextlib.nullcontext()
    with watching:
        solution = full.solve(dict(point), on_step=keep, scale=scale)
    return LoadPath(np.column_stack(columns), solution, tuple(kept), inverse[0] if inverse else None)


def relative_to(full: FullOrderModel) -> np.ndarray:
    """What :func:`solve_path`'s snapshots of ``full`` are relative to: its start state at the
    defaults (a full local array), or nothing for an imaged body (its own start at each μ)."""
    return np.zeros(0) if isinstance(full.start, InverseMotion) else one_state(full.start, full.model)


def collected(full: FullOrderModel, runs: Sequence[Run]) -> np.ndarray:
    """The snapshots of ``full``'s solves at each (parameter point, load scale) of ``runs``,
    side by side (owned rows); the model is left at its start, at the default parameters.
    Collective."""
    start = one_state(full.start, full.model)
    columns = [solve_path(full, point, start, scale=scale).snapshots for point, scale in runs]
    full.reset()
    full.model.set_time(full.stepping.start)
    return np.hstack(columns)


def serial(full: FullOrderModel, start: np.ndarray) -> Paths:
    """The paths solved one after another on ``full`` itself (the default of a training)."""
    return lambda runs, iterates: [solve_path(full, point, start, iterates, scale) for point, scale in runs]


def canonical(path: LoadPath, where: Layout) -> dict[str, np.ndarray] | None:
    """``path`` as plain arrays in canonical dof order on rank 0 (None on the others), for a file
    or a message. Collective."""
    solution = path.solution
    states = where.gather(np.asarray(solution.states).T)
    snapshots = where.gather(path.snapshots)
    iterated = where.gather(np.column_stack([state for state, _, _ in path.iterates])) if path.iterates else None
    inverse = None if path.inverse is None else where.gather(path.inverse)
    if where.comm.rank != 0:
        return None
    assert states is not None and snapshots is not None  # (gathered on rank 0)
    names = sorted(solution.parameters)
    arrays: dict[str, np.ndarray] = {
        "fingerprint": np.array(where.fingerprint),
        "parameter_names": np.array(names, dtype=str),
        "parameter_values": np.array([solution.parameters[n] for n in names], dtype=float),
        "times": np.asarray(solution.times, dtype=float),
        "volume": np.asarray(solution.outputs["volume"], dtype=float),
        "strain_energy": np.asarray(solution.outputs["strain_energy"], dtype=float),
        "states": states,
        "snapshots": snapshots,
        "newton_iterations": np.array(solution.newton_iterations),
        "seconds": np.array(solution.seconds),
        "ranks": np.array(where.comm.size),  # where it was solved (round-off differs with it)
    }
    if inverse is not None:
        arrays["inverse"] = inverse
    if iterated is not None:
        arrays["iterates"] = iterated
        arrays["iterate_times"] = np.array([t for _, t, _ in path.iterates], dtype=float)
        which = sorted(path.iterates[0][2])  # the model's parameters, as the solver saw them
        arrays["iterate_names"] = np.array(which, dtype=str)
        arrays["iterate_parameters"] = np.array([[mu[n] for n in which] for _, _, mu in path.iterates], dtype=float)
    return arrays


def placed(arrays: Mapping[str, np.ndarray] | None, where: Layout, iterates: bool = False) -> LoadPath:
    """The :class:`LoadPath` of :func:`canonical` ``arrays`` (given on rank 0) on this rank's
    owned rows of ``where``; refused when they were solved on another mesh or element, or
    without the iterates asked for. Collective."""
    header = None
    if where.comm.rank == 0:
        assert arrays is not None  # (given on rank 0)
        header = {
            "fingerprint": str(arrays["fingerprint"]),
            "names": [str(n) for n in arrays["parameter_names"]],
            "values": np.asarray(arrays["parameter_values"], dtype=float),
            "times": np.asarray(arrays["times"]),
            "volume": np.asarray(arrays["volume"]),
            "strain_energy": np.asarray(arrays["strain_energy"]),
            "newton": int(arrays["newton_iterations"]),
            "seconds": float(arrays["seconds"]),
            "iterates": "iterates" in arrays,
            "inverse": "inverse" in arrays,
            "iterate_times": np.asarray(arrays.get("iterate_times", [])),
            "iterate_names": [str(n) for n in arrays.get("iterate_names", [])],
            "iterate_parameters": np.asarray(arrays.get("iterate_parameters", [])),
        }
    header = where.comm.bcast(header, root=0)
    if header["fingerprint"] != where.fingerprint:
        raise ParameterError(
            f"a full load path was solved on another mesh or element (its fingerprint {header['fingerprint']}, "
            f"this model's {where.fingerprint})"
        )
    if iterates and not header["iterates"]:
        raise ParameterError(
            "a full load path without its Newton iterates was given where a hyper-reduction needs them"
        )
    get = (lambda name: arrays[name]) if where.comm.rank == 0 else (lambda name: None)  # type: ignore[index]
    names = header["names"]
    parameters = dict(zip(names, map(float, header["values"]), strict=True))
    solution = Solution(
        parameters=parameters,
        times=header["times"],
        outputs={"volume": header["volume"], "strain_energy": header["strain_energy"]},
        states=where.scatter(get("states")).T.copy(),
        newton_iterations=header["newton"],
        seconds=header["seconds"],
    )
    kept: tuple[Iterate, ...] = ()
    if iterates:
        columns = where.scatter(get("iterates"))
        kept = tuple(
            (
                np.ascontiguousarray(columns[:, i]),
                float(t),
                dict(zip(header["iterate_names"], map(float, mu), strict=True)),
            )
            for i, (t, mu) in enumerate(zip(header["iterate_times"], header["iterate_parameters"], strict=True))
        )
    inverse = where.scatter(get("inverse")) if header["inverse"] else None
    return LoadPath(where.scatter(get("snapshots")), solution, kept, inverse)
