"""Registration jobs with files: what ``lungmech register`` and ``lungmech shape-modes`` do.

:func:`register_image` maps a reference mesh onto one segmented image and writes the mapped mesh
(with the reference's boundary names, ready for a scene), the mapping, a JSON report and a
picture. :func:`build_shape_modes` does that for every image of a set, then writes the shape
modes, their spectrum and leave-one-out error. Outputs replace a folder only on success.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from mpi4py import MPI

from lungmech import geometry as geometries
from lungmech.errors import ImageError
from lungmech.output import atomic_folder, write_json
from lungmech.registration import image as images
from lungmech.registration import metrics, nodes, pictures
from lungmech.registration.image import Image
from lungmech.registration.library import mapping_library
from lungmech.registration.sobolev import Options, register

__all__ = ["build_shape_modes", "read_images", "register_image"]


def register_image(
    reference: str | Path,
    image: Image,
    out: str | Path,
    options: Options = Options(),
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Register the mesh file ``reference`` onto ``image``; write into the folder ``out``:
    ``registered.xdmf`` (the mapped mesh), ``mapping.npz`` (reference nodes and displacement in
    canonical order), ``report.json`` (metrics and the descent) and ``registration.png``."""
    geometry = geometries.from_file(reference, comm)
    start = time.perf_counter()
    result = register(geometry.mesh, image, options)
    space, where = nodes.displacement_space(geometry.mesh)
    reference_nodes = nodes.positions(space, where)
    initial = result.similarity(metrics.boundary_triangles(geometry.mesh).reshape(-1, 3)).reshape(-1, 3, 3)
    with atomic_folder(Path(out), comm) as staging:
        with nodes.deformed(result.displacement) as mesh:
            report = {"reference": str(reference)} | metrics.report(mesh, image) | result.summary()
            geometries.write(geometry, staging / "registered.xdmf")
            pictures.registration_slices(mesh, image, staging / "registration.png", reference=initial,
                                         reference_label="start (similarity fit)",
                                         title=f"Dice {report['dice']:.3f}, mean distance "
                                               f"{1e3 * report['mean_surface_distance']:.2f} mm")
        report["total_seconds"] = time.perf_counter() - start
        displacement = nodes.gather(result.displacement, where)
        if comm.rank == 0:
            np.savez(staging / "mapping.npz", reference=reference_nodes, displacement=displacement,
                     fingerprint=where.fingerprint)
        write_json(staging / "report.json", report, comm)
    return report


def build_shape_modes(
    reference: str | Path,
    sources: Mapping[str, Image],
    out: str | Path,
    options: Options = Options(),
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> dict:
    """Register the mesh file ``reference`` onto every image and reduce the mappings to shape
    modes; write ``shape_modes.npz``, ``report.json`` (per-image metrics, singular values,
    compactness, leave-one-out error) and ``singular_values.png`` into the folder ``out``."""
    geometry = geometries.from_file(reference, comm)
    start = time.perf_counter()
    library = mapping_library(geometry.mesh, sources, options)
    modes = library.modes()
    loo = library.leave_one_out() if len(sources) >= 3 else None
    report = {
        "reference": str(reference),
        "images": len(sources),
        "singular_values": modes.singular_values,
        "deviations": modes.deviations,
        "compactness": modes.compactness(),
        "leave_one_out_rms": loo,
        "members": list(library.reports),
        "worst": {
            "dice": min(r["dice"] for r in library.reports),
            "mean_surface_distance_voxels": max(r["mean_surface_distance_voxels"] for r in library.reports),
            "min_det_F": min(r["min_det_F"] for r in library.reports),
        },
        "seconds": time.perf_counter() - start,
    }
    with atomic_folder(Path(out), comm) as staging:
        if comm.rank == 0:
            modes.save(staging / "shape_modes.npz")
            pictures.shape_spectrum(modes.singular_values, staging / "singular_values.png", leave_one_out=loo,
                                    title=f"Shape modes of {len(sources)} mappings")
        write_json(staging / "report.json", report, comm)
    return report


def read_images(paths: list[str | Path], label: int | None = None, unit: str | None = None) -> dict[str, Image]:
    """Images by name from files and folders (every image file in a folder, sorted)."""
    files: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if images.stem(p) is not None)
            if not found:
                raise ImageError(f"folder '{path}' holds no image ({', '.join(images.SUFFIXES)})")
            files += found
        else:
            files.append(path)
    names = [images.stem(p) or p.name for p in files]
    if len(set(names)) != len(names):
        raise ImageError("two images share a name: " + ", ".join(sorted({n for n in names if names.count(n) > 1})))
    return {name: images.read(p, label=label, unit=unit) for name, p in zip(names, files)}
