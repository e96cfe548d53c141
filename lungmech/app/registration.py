"""Registration jobs with files: what ``lungmech register`` and ``lungmech shape-modes`` do.

:func:`register_image` maps a reference mesh onto one segmented image and writes the mapped mesh
(with the reference's boundary names, ready for a scene), the mapping, a JSON report and a
picture. :func:`build_shape_modes` does that for every image of a set, then writes the shape
modes, their spectrum and leave-one-out error. Outputs replace a folder only on success.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import cast

from mpi4py import MPI

import numpy as np

from lungmech import mesh as geometries
from lungmech.app.output import write_json
from lungmech.app.plot import drawn
from lungmech.errors import ImageError, RegistrationError
from lungmech.mesh import nodes
from lungmech.parallel import on_root
from lungmech.parallel.destination import hold_signals_until_swap, output_folder
from lungmech.registration import image as images
from lungmech.registration import metrics, pictures
from lungmech.registration.image import Image
from lungmech.registration.library import Library, mapping_library
from lungmech.registration.sobolev import Options, register

__all__ = ["build_shape_modes", "choose_reference", "read_images", "register_image"]


def choose_reference(
    image: Image,
    reference: str | Path | None = None,
    side: str | None = None,
    accept_other_side: bool = False,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> tuple[Path, dict]:
    """Collective: the reference mesh for the lung in ``image``, and what decided it.

    The lung's side comes from the image (:func:`lungmech.registration.side.of_image`), or from
    ``side`` where the image cannot tell (no orientation in its header, unclear or disagreeing
    cues). Without ``reference``, the bundled phantom of that side is used. A given reference
    is checked to be of that side too (by its own shape). Refused in one line, unless
    ``accept_other_side``: a side the image cannot tell and ``side`` does not give; a ``side``
    the image contradicts; a reference of the other side, whose medial face and hilum would
    land on the lung's outer wall.
    """
    from lungmech import meshes
    from lungmech.registration import side as sides

    name = f"image '{image.source}'" if image.source is not None else "the image"
    if side not in (None, "left", "right"):
        raise RegistrationError(f"--side must be left or right (got {side!r})")
    given = None if reference is None else geometries.from_file(meshes.locate(reference), comm, dimension=3)
    check_voxels(image)
    found = comm.bcast(on_root(comm, lambda: sides.of_image(image)))
    if found.side is None and side is None:
        raise RegistrationError(f"{name}: cannot tell which lung it holds: {found.reason}; give --side left or right")
    if side is not None and found.side not in (None, side) and not accept_other_side:
        raise RegistrationError(
            f"{name} holds a {found.side} lung by its shape (convexity {found.convexity:+.3f}), not the {side} one "
            "--side names: check the header's orientation, or --accept-other-side registers it as given"
        )
    lung = side or found.side
    path = meshes.reference(f"lung_phantom_{lung}") if reference is None else meshes.locate(reference)
    decided = {"image": found.describe(), "lung": lung, "reference": str(path)}
    if given is not None:
        held = sides.of_mesh(given.mesh)
        decided["reference_side"] = held.side
        if held.side not in (None, lung) and not accept_other_side:
            raise RegistrationError(
                f"the reference '{path}' is a {held.side} lung and {name} holds a {lung} one: its medial face and "
                f"hilum would land on the lung's outer wall; use --reference lung_phantom_{lung} (the default), or "
                "--accept-other-side"
            )
    return path, decided


def register_image(
    reference: str | Path,
    image: Image,
    out: str | Path,
    options: Options = Options(),
    comm: MPI.Comm = MPI.COMM_WORLD,
    accept: Sequence[str] = (),
    side: dict | None = None,
) -> dict:
    """Register the mesh file ``reference`` onto ``image``; write into the folder ``out``:
    ``registered.vtu`` (the mapped mesh, :mod:`lungmech.mesh.vtu`), ``mapping.npz`` (reference nodes and displacement in
    canonical order), ``report.json`` (metrics and the descent) and ``registration.png``.

    Refused with a :class:`RegistrationError` (nothing written): a target of a handful of
    voxels; unless ``accept`` names the doubt, a target whose size points at a wrong length unit
    ("implausible") and a descent that did not converge ("unconverged"). ``side``: how the
    reference was chosen (:func:`choose_reference`), for the report.
    """
    inputs = [reference, *([image.source] if image.source is not None else [])]
    with output_folder(out, comm, inputs=inputs, command="lungmech register") as staging:
        geometry = geometries.from_file(reference, comm, dimension=3)
        check_target(geometry, image, "implausible" in accept)
        start = time.perf_counter()
        result = register(geometry.mesh, image, options)
        hold_signals_until_swap()  # the outputs are collective writes
        space, where = nodes.displacement_space(geometry.mesh)
        reference_nodes = nodes.positions(space, where)  # canonical, on rank 0 (it writes mapping.npz)
        initial = result.similarity(metrics.boundary_triangles(geometry.mesh).reshape(-1, 3)).reshape(-1, 3, 3)
        with nodes.deformed(result.displacement) as mesh:
            report = {"reference": str(reference), "side": side} | metrics.report(mesh, image) | result.summary()
            geometries.write(geometry, staging / "registered.vtu")
            title = f"Dice {report['dice']:.3f}, mean distance {1e3 * report['mean_surface_distance']:.2f} mm"
            drawn(
                comm,
                staging / "registration.png",
                lambda: pictures.registration_slices(
                    mesh,
                    image,
                    staging / "registration.png",
                    reference=initial,
                    reference_label="start (similarity fit)",
                    title=title,
                ),
            )
        report["total_seconds"] = time.perf_counter() - start
        report["units"] = REPORT_UNITS
        check_converged(report, "unconverged" in accept)
        displacement = nodes.gather(result.displacement, where)
        on_root(
            comm,
            lambda: np.savez(
                staging / "mapping.npz",
                reference=cast(np.ndarray, reference_nodes),  # on rank 0, where both are gathered
                displacement=cast(np.ndarray, displacement),
                fingerprint=where.fingerprint,
            ),
        )
        write_json(staging / "report.json", report, comm)
    return report


# Units of the numbers in report.json (registration) and of the shape-modes report.
REPORT_UNITS = {
    "dice": "1",
    "mean_surface_distance": "m",
    "mean_surface_distance_voxels": "voxel",
    "hd95": "m",
    "hausdorff": "m",
    "volume_mesh": "m^3",
    "volume_image": "m^3",
    "spacing": "m",
    "psi": "m^4 (signed distance) or m^3 (binary)",
    "min_det_F": "1",
    "iterations": "1",
    "seconds": "s",
    "total_seconds": "s",
    "initial_similarity": "scale 1, rotation 1, translation m",
}
MODES_UNITS = {
    "singular_values": "m (RMS displacement, mass-weighted)",
    "deviations": "m (RMS)",
    "compactness": "1",
    "leave_one_out_rms": "m (RMS)",
    "members": "as in a registration report",
    "seconds": "s",
    "pose": "1 (what each mapping was taken without: similarity, or rigid with the size kept)",
}

# A target must span this many voxels along each axis, and be within this factor of the
# reference's size (a millimetre image read as metres is 1000 times too large).
MIN_VOXELS_ACROSS = 4
SIZE_FACTOR = 10.0


def check_target(reference: geometries.Geometry, image: Image, accept: bool = False) -> None:
    """Refuse a segmentation that cannot be a fair target: a handful of voxels, or a size so
    far from the reference mesh's that the image's length unit is likely wrong."""
    name = f"image '{image.source}'" if image.source is not None else "the image"
    index = check_voxels(image)
    extent = float(np.linalg.norm(image.points(index.max(axis=0)) - image.points(index.min(axis=0))))
    ratio = extent / reference.size
    if not 1 / SIZE_FACTOR <= ratio <= SIZE_FACTOR and not accept:
        raise RegistrationError(
            f"{name}: the segmentation is {extent:.3g} m across and the reference mesh {reference.size:.3g} m, a "
            f"ratio of {ratio:.3g}; is the image's length unit right (--unit mm or m)? --accept-implausible "
            "registers it anyway"
        )


def check_voxels(image: Image) -> np.ndarray:
    """The indices of the segmented voxels, if they span enough voxels to register a mesh onto
    (and to tell which lung they hold); else one error."""
    name = f"image '{image.source}'" if image.source is not None else "the image"
    index = np.argwhere(image.mask)
    across = index.max(axis=0) - index.min(axis=0) + 1
    if across.min() < MIN_VOXELS_ACROSS:
        raise RegistrationError(
            f"{name}: the segmentation spans only {across.tolist()} voxels along its axes "
            f"({len(index)} voxels in all), too few to register a mesh onto"
        )
    return index


def check_converged(report: dict, accept: bool = False) -> None:
    """Refuse a registration whose descent did not converge (unless accepted)."""
    if report["converged"] or accept:
        return
    reasons = ", ".join(s["reason"] for s in report["stages"])
    held = any(s["reason"].startswith("held by the det F limit") for s in report["stages"])
    remedy = (
        "the mesh would have to squeeze cells further to fit: a lower --min-jacobian allows it (a closer fit, "
        "a poorer mesh)"
        if held
        else "raise --max-iterations"
    )
    raise RegistrationError(
        f"the registration did not converge (stages ended by: {reasons}; Dice {report['dice']:.4f}, mean surface "
        f"distance {1e3 * report['mean_surface_distance']:.2f} mm); {remedy}, or --accept-unconverged keeps the result"
    )


def build_shape_modes(
    reference: str | Path,
    sources: Mapping[str, Image],
    out: str | Path,
    options: Options = Options(),
    comm: MPI.Comm = MPI.COMM_WORLD,
    accept: Sequence[str] = (),
    pose: str = "similarity",
) -> dict:
    """Register the mesh file ``reference`` onto every image and reduce the mappings, each
    without its ``pose`` ("similarity", or "rigid": the size kept, for a population's model), to shape
    modes; write ``shape_modes.npz``, ``report.json`` (per-image metrics, singular values,
    compactness, leave-one-out error) and ``singular_values.png`` into the folder ``out``.
    Every image is checked as in :func:`register_image` (``accept`` as there, and
    "other side": an image whose lung is clearly of the other side than the reference's is
    refused without it)."""
    from lungmech.registration import side as sides

    inputs = [reference, *(image.source for image in sources.values() if image.source is not None)]
    with output_folder(out, comm, inputs=inputs, command="lungmech shape-modes") as staging:
        geometry = geometries.from_file(reference, comm, dimension=3)
        held = sides.of_mesh(geometry.mesh).side
        for name, image in sources.items():
            check_target(geometry, image, "implausible" in accept)
            found = comm.bcast(on_root(comm, functools.partial(sides.of_image, image)))
            if held and found.side not in (None, held) and "other side" not in accept:
                raise RegistrationError(
                    f"{name}: it holds a {found.side} lung and the reference '{reference}' is a {held} one: give "
                    f"--reference lung_phantom_{found.side} for a cohort of {found.side} lungs, or --accept-other-side"
                )
        start = time.perf_counter()
        library = mapping_library(geometry.mesh, sources, options)
        for member in library.reports:
            try:
                check_converged(member, "unconverged" in accept)
            except RegistrationError as e:
                raise RegistrationError(f"{member['name']}: {e}") from None
        return _shape_modes(library, reference, len(sources), start, staging, comm, pose)


def _shape_modes(
    library: Library, reference: str | Path, count: int, start: float, staging: Path, comm: MPI.Comm, pose: str
) -> dict:
    modes = library.modes(pose)
    loo = library.leave_one_out(pose) if count >= 3 else None
    report = {
        "reference": str(reference),
        "images": count,
        "pose": pose,
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
        "units": MODES_UNITS | {f"members[].{k}": v for k, v in REPORT_UNITS.items()},
    }

    on_root(comm, lambda: modes.save(staging / "shape_modes.npz"))
    drawn(
        comm,
        staging / "singular_values.png",
        lambda: on_root(
            comm,
            lambda: pictures.shape_spectrum(
                modes.singular_values,
                staging / "singular_values.png",
                leave_one_out=loo,
                title=f"Shape modes of {count} mappings",
            ),
        ),
    )
    write_json(staging / "report.json", report, comm)
    return report


def read_images(
    paths: list[str | Path], label: int | Sequence[int] | None = None, unit: str | None = None
) -> dict[str, Image]:
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
