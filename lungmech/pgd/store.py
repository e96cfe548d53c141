"""PGD models in model files: the same ``.npz`` files as reduced models (:mod:`lungmech.rom.store`:
plain arrays, a digest, the canonical dof order, the mesh's fingerprint checked on loading).

The space modes Q are the file's basis (kind "pgd", orthonormal in the energy inner product,
checked on loading); beside them the terms' coefficients R, each axis's spline coefficients and
the online outputs (:class:`~lungmech.pgd.online.Online`), and a record under ``extra["pgd"]``:
each axis's parameter and intervals, how the model was built, its probe points. The axes are
made again on loading from the model's own parameters, which must be the record's. An imaged
body's PGD keeps its reference's fit beside (:class:`~lungmech.pgd.imaged.Reference`: its modes
and the inverse problem's rest state in the canonical order, ``record["image"]``), and is
loaded on a model of the image's motion.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from dolfinx import fem

from lungmech.errors import ModelFileError
from lungmech.fem.model import Model
from lungmech.fem.parametric import output_times
from lungmech.fem.solver import Stepping
from lungmech.parallel.layout import layout
from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.imaged import Reference, constant
from lungmech.pgd.model import PGDModel
from lungmech.pgd.online import Online
from lungmech.pgd.timeline import SampledTimeline
from lungmech.rom import store
from lungmech.rom.basis import Basis
from lungmech.rom.exact import Cubic

__all__ = ["is_pgd", "load_pgd", "write_pgd"]

KIND = "pgd"


def is_pgd(metadata: Mapping) -> bool:
    """Whether a model file's metadata (:func:`lungmech.rom.store.read`) is a PGD model's."""
    return metadata.get("kind") == KIND and isinstance(metadata.get("extra", {}).get("pgd"), dict)


def write_pgd(path: str | Path, found: PGDModel, extra: dict | None = None, arrays: dict | None = None) -> None:
    """Collective: ``found`` as a model file at ``path`` (no checks: the caller stages the file,
    :mod:`lungmech.parallel.destination`), with the caller's ``extra`` metadata and canonical
    ``arrays`` beside it."""
    model, d = found.model, found.decomposition
    weights = np.linalg.norm(d.reduced, axis=1)  # each space mode's share of the terms
    method = "a priori PGD" if found.energy is None or found.built.get("newton_iterations") else "a posteriori PGD"
    basis = Basis(d.modes, weights, KIND, "energy", layout(model.space).fingerprint, {"method": method})
    record = {
        "axes": [{"parameter": axis.parameter.name, "intervals": axis.intervals} for axis in d.axes],
        "probes": [list(p) for p in found.probe_points],
        "built": found.built,
    }
    content: dict[str, np.ndarray | None] = {"pgd/reduced": d.reduced}  # (rank 0's: the others may hold None)
    content |= {f"pgd/axis/{j}": X for j, X in enumerate(d.coefficients)}
    content |= {f"pgd/online/{name}": a for name, a in found.online.arrays().items()}
    if found.energy is not None:  # fitted to full solves: the terms' timeline, the strain energy's fit
        assert isinstance(found.timeline, SampledTimeline)  # (a fitted PGD's)
        energy, its_timeline = found.energy
        content |= {"pgd/timeline/times": found.timeline.times, "pgd/timeline/values": found.timeline.values}
        content |= {"pgd/energy/reduced": energy.reduced, "pgd/energy/timeline": its_timeline.values}
        content |= {f"pgd/energy/axis/{j}": X for j, X in enumerate(energy.coefficients)}
        record["energy_axes"] = [axis.intervals for axis in energy.axes]
    if found.reference is not None:  # an imaged body's: its reference's fit, modes and rest in canonical order
        reference, where = found.reference, layout(model.space)
        content |= {f"pgd/reference/{name}": a for name, a in reference.arrays().items()}
        content |= {f"pgd/reference/axis/{j}": X for j, X in enumerate(reference.decomposition.coefficients)}
        content |= {
            "pgd/reference/modes": where.gather(reference.decomposition.modes),
            "pgd/reference/rest": where.gather(reference.rest[: reference.decomposition.modes.shape[0]]),
        }
        record["image"] = {"axes": [axis.intervals for axis in reference.decomposition.axes], "body": reference.body}
    store.write(path, model, basis, extra=(extra or {}) | {"pgd": record}, arrays=content | (arrays or {}))


def load_pgd(path: str | Path, model: Model, stepping: Stepping, content: tuple[dict, dict]) -> PGDModel:
    """Collective: the PGD model of the file at ``path`` (``content``, as
    :func:`lungmech.rom.store.read_on_root` gave it) on ``model``, the scene's, with the load
    path ``stepping``. Refused in one line where the file is not one, was built on another mesh,
    over other parameters, or its modes are not orthonormal."""
    metadata, _ = content
    if not is_pgd(metadata):
        raise ModelFileError(f"'{path}' is not a PGD model file (its basis is {metadata.get('kind')!r})")
    record = metadata["extra"]["pgd"]
    basis, _, arrays = store.load(path, model, content=content)
    store.check_orthonormal(path, model, basis)
    comm = model.geometry.mesh.comm
    canonical = ("pgd/reference/modes", "pgd/reference/rest")  # scattered, not broadcast
    held = comm.bcast(
        {name: a for name, a in arrays.items() if name.startswith("pgd/") and name not in canonical}
        if comm.rank == 0
        else None
    )
    names = [axis["parameter"] for axis in record["axes"]]
    if names != list(model.parameters.names):
        raise ModelFileError(
            f"'{path}' was built over the parameters {', '.join(names) or 'none'}; this scene's are "
            f"{', '.join(model.parameters.names) or 'none'}"
        )
    try:
        axes = tuple(Axis(p, int(a["intervals"])) for p, a in zip(model.parameters, record["axes"]))
        coefficients = [held[f"pgd/axis/{j}"] for j in range(len(axes))]
        decomposition = Decomposition(axes, basis.vectors, held["pgd/reduced"], coefficients)
        online = Online.of(
            {name[len("pgd/online/") :]: a for name, a in held.items() if name.startswith("pgd/online/")}
        )
        _check_shapes(decomposition, online)
        if online.shape != (0 if model.shape is None else len(model.shape.modes)):
            raise ValueError(f"{online.shape} shape coefficients in the volume, the model's {model.shape}")
        timeline, energy = _fitted(held, record, model, stepping, decomposition.terms)
        reference = _reference(held, arrays, record, model)
    except (KeyError, ValueError) as error:
        raise ModelFileError(f"'{path}' is damaged: its PGD arrays are incomplete ({error}); rebuild it") from None
    fitted_at = None if timeline is None else timeline.times[timeline.times > stepping.start]
    if fitted_at is not None and not np.allclose(fitted_at, output_times(model, stepping), rtol=1e-12, atol=0.0):
        raise ModelFileError(
            f"'{path}' was fitted at the output times {', '.join(f'{t:g}' for t in fitted_at)} s; this scene's are "
            f"{', '.join(f'{t:g}' for t in output_times(model, stepping))} s: build it again for them"
        )
    return PGDModel(
        model, decomposition, online, stepping, record["probes"], record["built"], timeline, energy, reference
    )


def _fitted(
    held: Mapping[str, np.ndarray], record: Mapping, model: Model, stepping: Stepping, terms: int
) -> tuple[SampledTimeline | None, tuple[Decomposition, SampledTimeline] | None]:
    """A fitted PGD's timeline and strain energy's fit from its arrays and ``record`` (None,
    None: an a priori one's), their sizes checked (else ValueError)."""
    if "pgd/timeline/values" not in held:
        return None, None
    axes = tuple(Axis(p, int(k)) for p, k in zip(model.parameters, record["energy_axes"], strict=True))
    times = held["pgd/timeline/times"]
    timeline = SampledTimeline(stepping.start, times, held["pgd/timeline/values"])
    reduced = held["pgd/energy/reduced"]
    energy = Decomposition(axes, np.ones((1, 1)), reduced, [held[f"pgd/energy/axis/{j}"] for j in range(len(axes))])
    its_timeline = SampledTimeline(stepping.start, times, held["pgd/energy/timeline"])
    if timeline.values.shape != (terms, len(times)) or its_timeline.values.shape != (reduced.shape[1], len(times)):
        raise ValueError(f"timelines {timeline.values.shape} and {its_timeline.values.shape} for {len(times)} times")
    for axis, X in zip(axes, energy.coefficients):
        if X.shape != (reduced.shape[1], axis.size):
            raise ValueError(f"energy axis {axis.parameter.name}: {X.shape}")
    return timeline, (energy, its_timeline)


def _reference(
    held: Mapping[str, np.ndarray], arrays: Mapping[str, np.ndarray | None], record: Mapping, model: Model
) -> Reference | None:
    """An imaged body's fitted reference from its arrays (``held`` on every rank, ``arrays``
    rank 0's canonical ones) and ``record`` (None: not an imaged body's), on ``model``, a model
    of the image's motion (its space the inverse problem's, numbered alike). Collective."""
    image = record.get("image")
    if image is None:
        return None
    if model.reference_map is None:
        raise ValueError("an imaged body's PGD on a model that is not of the image's motion")
    where, space = layout(model.space), model.space
    modes = where.scatter(arrays.get("pgd/reference/modes"))
    rest = fem.Function(space)
    rest.x.array[: modes.shape[0]] = where.scatter(arrays.get("pgd/reference/rest"))
    rest.x.scatter_forward()
    axes = tuple(Axis(p, int(k)) for p, k in zip(model.parameters, image["axes"], strict=True))
    reduced = held["pgd/reference/reduced"]
    coefficients = [held[f"pgd/reference/axis/{j}"] for j in range(len(axes))]
    for axis, X in zip(axes, coefficients):
        if X.shape != (reduced.shape[1], axis.size) or reduced.shape[0] != modes.shape[1]:
            raise ValueError(f"reference axis {axis.parameter.name}: {X.shape}")
    names = ("c0", "c1", "c2", "c3")
    volume = Cubic.of(tuple(held[f"pgd/reference/volume/{name}"] for name in names))
    if "imaged_volume" in image:  # written before the shape was followed: no shape map, the image's volume
        imaged, shape = constant(image["imaged_volume"]), 0
    else:
        imaged = Cubic.of(tuple(held[f"pgd/reference/imaged/{name}"] for name in names))
        shape = int(held["pgd/reference/shape"][0])
    if volume.c1.shape != (modes.shape[1] + shape,) or imaged.c1.shape != (shape,):
        raise ValueError(f"reference volumes {volume.c1.shape} and {imaged.c1.shape}, {shape} shape coefficients")
    probes = (held["pgd/reference/probes0"], held["pgd/reference/probes"])
    decomposition = Decomposition(axes, modes, reduced, coefficients)
    return Reference(decomposition, rest.x.array.copy(), probes, volume, imaged, image["body"], shape)


def _check_shapes(d: Decomposition, online: Online) -> None:
    """The arrays agree in their sizes (m modes, n terms, each axis's splines), else ValueError."""
    m, n = d.modes.shape[1], d.reduced.shape[1]
    if d.reduced.shape[0] != m or online.energy.shape[2:] != (m, m) or online.probes.shape[1:] != (m,):
        raise ValueError(f"{m} modes, R {d.reduced.shape}, energy {online.energy.shape}, probes {online.probes.shape}")
    for axis, X in zip(d.axes, d.coefficients):
        if X.shape != (n, axis.size):
            raise ValueError(f"axis {axis.parameter.name}: {X.shape}, expected {(n, axis.size)}")
    if online.volume.c1.shape != (m + online.shape,):
        raise ValueError(f"volume in {online.volume.c1.shape} coordinates, {m} modes and {online.shape} shape")
    operated = online.energy.shape[0]  # (0: a fitted PGD's, its strain energy fitted)
    if len(online.curves) != len(online.degrees) or (operated and math.prod(online.degrees) != operated):
        raise ValueError(f"curves {online.curves} of degrees {online.degrees}, energy {online.energy.shape}")
    if any(not 0 <= j < len(d.axes) for j in online.curves):
        raise ValueError(f"curves on axes {online.curves}, {len(d.axes)} axes")
    columns = online.energy.shape[0] * online.energy.shape[1] * (m + 1)
    if online.residual.size and online.residual.shape != (columns, columns):
        raise ValueError(f"residual's Gram matrix {online.residual.shape}, expected {columns} columns")
