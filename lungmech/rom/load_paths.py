"""A full model's load path at one parameter point, as a reduction trains on it — solved here, or
elsewhere and brought here in the canonical dof order.

A :class:`LoadPath` holds what a greedy training takes from one full solve: the snapshots (every
accepted state of the approach to μ and of the load path, minus the start state), the solution
(its states at the output times, for the true error of the reduced model there) and, when a
hyper-reduction is trained on them, every Newton iterate ``(state, time, parameters)``. All
arrays are a rank's owned rows.

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
from lungmech.fem.parametric import FullOrderModel, Solution, Step
from lungmech.fem.solver import NewtonSolver
from lungmech.fem.start import one_state
from lungmech.parallel.layout import Layout
from lungmech.rom import ecsw
from lungmech.rom.basis import snapshot

__all__ = ["LoadPath", "Paths", "Run", "canonical", "collected", "placed", "serial", "solve_path"]

Iterate = tuple[np.ndarray, float, dict[str, float]]  # a Newton iterate: (owned rows, time, μ)
Run = tuple[Mapping[str, float], float | Sequence[float]]  # a parameter point and the load scale(s)


@dataclass(frozen=True)
class LoadPath:
    """One full solve at ``solution.parameters``: ``snapshots`` (owned rows × accepted states),
    its ``solution`` (states: owned rows at the output times; outputs: volume, strain energy) and
    its Newton ``iterates`` (empty unless asked for)."""

    snapshots: np.ndarray
    solution: Solution
    iterates: tuple[Iterate, ...] = ()


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
    relative to ``start`` (a full local array, the start state at the defaults). Collective."""
    model, columns, kept = full.model, [], []
    owned = model.space.dofmap.index_map.size_local * model.space.dofmap.index_map_bs

    def keep(step: Step) -> None:
        if step.phase in ("approach", "path"):
            columns.append(snapshot(model, start))

    def seen(iteration: int) -> None:
        kept.append((model.state.x.array[:owned].copy(), float(model.time), dict(model.parameter_values)))

    watching = ecsw.iterates(cast(NewtonSolver, full.solver), seen) if iterates else contextlib.nullcontext()
    with watching:
        solution = full.solve(dict(point), on_step=keep, scale=scale)
    return LoadPath(np.column_stack(columns), solution, tuple(kept))


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
    return LoadPath(where.scatter(get("snapshots")), solution, kept)
