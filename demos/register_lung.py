"""From segmented images to shape parameters: register the bundled reference lung onto a
synthetic patient, then build shape modes from a small synthetic cohort.

1. A synthetic patient (a taller, narrower right lung with a higher dome, placed off-centre) is
   voxelised at 2 mm and written as NIfTI, as a CT segmentation would come.
2. The bundled reference mesh is registered onto it (Sobolev-gradient descent of ∫_ω I dx
   from a moments-based similarity fit); the report, the mapped mesh and a picture are written.
3. A cohort of 10 synthetic patients driven by 2 latent shape parameters (elongation, dome),
   with random sizes and positions, is registered; similarity-free mappings are reduced by a
   mass-weighted POD into shape modes; a new lung is made from two shape coefficients, ready to
   be a scene's geometry.

Writes registration.png (fitted surface over image slices), shape_modes.png (singular values,
compactness, leave-one-out error) and shape_mode_sections.png (mean shape ± 2 standard
deviations along each mode), with the image, the registration and shape-mode folders and the
new lung, into the output folder (default demos/output/register_lung).

    python demos/register_lung.py [-o FOLDER]
"""

import argparse
import shutil
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.app import registration as workflow
from lungmech.mesh.lung_shape import LungShape
from lungmech.parallel.destination import output_folder
from lungmech.registration import image, metrics, phantom, pictures
from lungmech.registration.library import ShapeModes

REFERENCE = meshes.reference("lung_phantom_right")


def main(out: Path) -> None:
    """Registration and shape modes; everything goes into the (empty) folder ``out``."""
    comm = MPI.COMM_WORLD

    # 1. A synthetic patient, saved and read back like a real segmentation.
    patient = LungShape(height=0.26, width=0.10, depth=0.16, dome=0.22, apex=0.27)
    target = out / "patient.nii.gz"
    if comm.rank == 0:
        image.write(phantom.voxelise(patient, 0.002, offset=(0.012, 0.02, -0.03)), target)
    comm.Barrier()
    segmentation = image.read(target)

    # 2. Registration.
    report = workflow.register_image(REFERENCE, segmentation, out / "registration", comm=comm)
    say(
        comm,
        f"registered in {report['iterations']} iterations, {report['seconds']:.1f} s: Dice {report['dice']:.4f}, "
        f"mean surface distance {1e3 * report['mean_surface_distance']:.2f} mm "
        f"({report['mean_surface_distance_voxels']:.2f} voxels), hd95 {1e3 * report['hd95']:.2f} mm, "
        f"min det F {report['min_det_F']:.3f}",
    )

    # 3. Shape modes of a cohort.
    start = time.perf_counter()
    cohort = phantom.cohort(10, latent=2, seed=3, size_spread=0.05, shift=0.01)
    sources = {f"patient_{j:02d}": im for j, im in enumerate(cohort.images(spacing=0.0025))}
    summary = workflow.build_shape_modes(REFERENCE, sources, out / "shape_modes", comm=comm)
    sigma = np.asarray(summary["singular_values"])
    loo = 1e3 * np.asarray(summary["leave_one_out_rms"])
    say(
        comm,
        f"{len(sources)} mappings in {time.perf_counter() - start:.0f} s (worst Dice {summary['worst']['dice']:.4f}); "
        f"σ/σ1 = {np.array2string(sigma / sigma[0], precision=3)}; the first 2 modes capture "
        f"{100 * summary['compactness'][1]:.1f} % of the variance; leave-one-out RMS error "
        f"{' → '.join(f'{e:.2f}' for e in loo[:4])} mm with 0 → {min(len(loo), 4) - 1} modes",
    )

    modes = ShapeModes.load(out / "shape_modes" / "shape_modes.npz")
    surfaces = {}
    for label, c in {
        "mean": [],
        "mode 1 +2σ": [2.0],
        "mode 1 −2σ": [-2.0],
        "mode 2 +2σ": [0, 2.0],
        "mode 2 −2σ": [0, -2.0],
    }.items():
        surfaces[label] = metrics.boundary_triangles(modes.geometry(geometry.from_file(REFERENCE, comm), c).mesh)
    if comm.rank == 0:
        pictures.surface_sections(
            surfaces,
            out / "shape_mode_sections.png",
            title="Shape modes of 10 synthetic patients (2 latent parameters)",
        )
    new = modes.geometry(geometry.from_file(REFERENCE, comm), [1.0, -1.0])
    geometry.write(new, out / "new_lung.vtu")
    say(comm, f"new lung (+1σ mode 1, −1σ mode 2): volume {1e3 * new.volume():.3f} L -> new_lung.vtu")

    if comm.rank == 0:
        shutil.copy(out / "registration" / "registration.png", out / "registration.png")
        shutil.copy(out / "shape_modes" / "singular_values.png", out / "shape_modes.png")


def say(comm, text: str) -> None:
    if comm.rank == 0:
        print(text, flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).resolve().parent / "output" / "register_lung"
    )
    target = parser.parse_args().output
    # Staged, and moved into place only when the demo succeeds; a folder that is not empty and
    # not lungmech's own is refused, so no file of the user's is ever overwritten.
    with output_folder(target, MPI.COMM_WORLD, inputs=[REFERENCE], command="python demos/register_lung.py") as staging:
        main(staging)
    say(MPI.COMM_WORLD, f"wrote {target}")
