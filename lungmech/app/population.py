"""A patient on a population's reduced model: no model of its own to build.

A model file built over a population (a scene whose [geometry] names a library's shape modes,
:mod:`lungmech.app.template`, with its template's surface nodes as probes: ``lungmech rom build
--probes surface``) serves every patient its modes represent. For each pair of the patient's
segmentations, :func:`prepare` does, in seconds:

1. **registration**: the modes' reference mesh mapped onto the end-expiration segmentation;
2. **the shape**: the mapping projected on the model's modes (:meth:`ShapeModes.project
   <lungmech.registration.library.ShapeModes.project>`: coefficients, the pose S the modes
   were taken without, what the modes leave out in mm), then the coefficients a and the pose
   that put the template's surface on the segmentation's (:func:`lungmech.twin.shape.fit_shape`,
   a inside the model's box): the surface is what the image holds, where a registration also
   slides the nodes along it as its regulariser says;
3. **the pair's view**: the template's surface nodes moved to the patient's shape χ_a, the
   segmentations seen from the model's frame through the pose (d(S x)), the shape coefficients
   fixed at a — unless they are estimated with the rest;
4. **the check**: the reduced model against the full one on χ_a(Ω₀) at 3 points, the model's
   error on each datum (no refined mesh: the template's modes live on its own mesh).

The estimate and its uncertainty are then :func:`lungmech.app.personalise.estimated`'s, as for a
patient's own model.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from mpi4py import MPI

import numpy as np
from dolfinx import fem

from lungmech.app.output import write_json
from lungmech.app.personalise import (
    Pair,
    Patient,
    Preparation,
    Setting,
    checked_request,
    estimated,
    position_values,
)
from lungmech.app.run import full_order_model
from lungmech.app.scene import Scene, build_geometry
from lungmech.app.template import build_template, mode_count
from lungmech.errors import ModelFileError
from lungmech.fem.parameters import Parameters
from lungmech.fem.quantities import Probe
from lungmech.mesh import nodes
from lungmech.mesh.geometry import Geometry
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.registration import metrics
from lungmech.registration.library import ShapeModes
from lungmech.registration.sobolev import Options, register
from lungmech.rom.reduced import ReducedModel

if TYPE_CHECKING:
    from lungmech.pgd.model import PGDModel
from lungmech.twin.fit import View
from lungmech.twin.shape import fit_shape
from lungmech.twin.surface import SurfaceNodes, surface_data, surface_nodes

__all__ = ["check_probes", "is_population", "personalise", "prepare", "shape_names"]


def is_population(scene: Scene) -> bool:
    """Whether ``scene`` is a population's (its [geometry] names a library's shape modes)."""
    return "shape_modes" in scene.geometry


def shape_names(scene: Scene) -> list[str]:
    """The scene's shape parameters' names, mode by mode (1, 2, …)."""
    shaped = [p for p in scene.parameters if p.kind == "shape"]
    return [p.name for p in sorted(shaped, key=lambda p: int(p.key.rpartition("_")[2]))]


def personalise(
    path: str | Path,
    scene: Scene,
    pairs: Sequence[Pair],
    out: str | Path,
    setting: Setting,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Estimate a patient's parameters from ``pairs`` with the population's model file ``path``
    (``scene``, its own), no model of the patient's own built; ``report.json`` into the folder
    ``out`` (replaced only on success), as :func:`lungmech.app.personalise.personalise` writes
    it, with each pair's shape coefficients. The shape coefficients are estimated only where
    ``setting.estimate`` names them. Collective."""
    from lungmech.app.reduce import load

    pairs = tuple(pairs)
    names, end = checked_request(scene, pairs, setting)
    if not setting.estimate:  # the shape comes from the registration, the rest is estimated
        names = tuple(n for n in names if n not in shape_names(scene))
    inputs = [image.source for p in pairs for image in (p.expiration, p.inspiration) if image.source is not None]
    with output_folder(out, comm, inputs=[Path(path), *inputs], command="lungmech personalise") as staging:
        reduced = load(path, comm)
        patient = prepare(scene, reduced, pairs, setting, names, end, path, comm)
        report = estimated(patient, setting, staging, comm)
        report["model"]["population"] = str(path)
        hold_signals_until_swap()
        write_json(staging / "report.json", report, comm)
    return report


def prepare(
    scene: Scene,
    reduced: ReducedModel | PGDModel,
    pairs: Sequence[Pair],
    setting: Setting,
    estimated: Sequence[str],
    end: float,
    source: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> Patient:
    """Each pair's registration, projection, view and check on the population's ``reduced``
    model (of ``scene``, the file's own, from ``source``); see the module's doc. Collective."""
    modes = ShapeModes.load(scene.geometry["shape_modes"])
    names, count = shape_names(scene), mode_count(scene)
    box = Parameters(scene.parameters)
    template, fields = build_template(scene, comm)
    surface = surface_nodes(template.mesh)
    check_probes(reduced, surface, source)
    full = full_order_model(scene, comm, start="inverse_motion", probes=surface.points.tolist())
    at_nodes = np.array([_at(template, field, surface.points) for field in fields])  # each mode at the nodes
    gathered = Preparation(box, tuple(estimated))
    checks = [
        {name: point[name] for name in estimated if name not in names} for point in box.sample(3, setting.seed + 1)
    ]
    for pair in pairs:
        name = pair.name(pairs)
        tic = time.perf_counter()
        reference = build_geometry(scene.geometry, comm)  # the modes' own mesh, unmoved
        registration = register(reference.mesh, pair.expiration, Options())
        _, where = nodes.displacement_space(reference.mesh)
        mapping = comm.bcast(nodes.gather(registration.displacement, where))
        projection = modes.project(mapping, count)
        expiration = surface_data(pair.expiration)
        S = projection.pose
        low, high = np.array([box.named(n).range for n in names]).T
        fit = fit_shape(
            surface.points,
            surface.areas,
            at_nodes,
            expiration,
            projection.coefficients,
            (low, high),
            S.rotation,
            S.translation,
        )
        with nodes.deformed(registration.displacement) as mapped:
            quality = metrics.report(mapped, pair.expiration)
        shape = {n: float(v) for n, v in zip(names, fit.coefficients) if n not in estimated}
        gathered.registered.append(
            {"pair": name}
            | quality
            | registration.summary()
            | {
                "shape_coefficients": fit.coefficients.tolist(),
                "shape_at_a_bound": bool(
                    np.any(np.minimum(fit.coefficients - low, high - fit.coefficients) <= 1e-6 * (high - low))
                ),
                "shape_surface_rms": fit.rms,
                "shape_surface_largest": fit.largest,
                "shape_projected": projection.coefficients.tolist(),
                "shape_left_out_rms": projection.rms,
                "shape_left_out_largest": projection.largest,
            }
        )
        gathered.seconds["registration"] += time.perf_counter() - tic

        fixed = position_values(scene, pair.position) | shape
        patient = surface.moved(np.einsum("k,knd->nd", fit.coefficients, at_nodes))
        data = surface_data(pair.inspiration).seen_from(fit.rotation, fit.translation)
        baseline = expiration.seen_from(fit.rotation, fit.translation)
        tic = time.perf_counter()
        chain = [View(model, patient, data, end, fixed, name, baseline) for model in (reduced, full)]
        gathered.check(name, chain, [point | fixed for point in checks], tic)
    return gathered.patient([reduced.size] * len(pairs), [pair.inspiration for pair in pairs])


def _at(template: Geometry, field: fem.Function, points: np.ndarray) -> np.ndarray:
    """A mode's values at the template's ``points`` (n, 3; m per unit coefficient)."""
    return Probe(template.mesh, points.tolist())(field)


def check_probes(reduced: ReducedModel | PGDModel, surface: SurfaceNodes, source: str | Path) -> None:
    """The model's probes must be its template's surface nodes, in their order."""
    probes = np.asarray(reduced.probe_points, dtype=float).reshape(-1, 3)
    if probes.shape != surface.points.shape or not np.allclose(probes, surface.points, rtol=0, atol=1e-9):
        raise ModelFileError(
            f"'{source}' is a population's model, but its probes are not its lung's surface nodes: build it with "
            "lungmech rom build SCENE --probes surface"
        )
