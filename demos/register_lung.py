# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # From segmented images to shape parameters
#
# A patient's lung model starts from a CT segmentation. This demo registers the bundled
# reference lung onto a synthetic patient, then builds the shape modes of a small synthetic
# cohort and makes a new lung from two shape coefficients, ready to be a scene's geometry.
#
# 1. A synthetic patient, a taller and narrower right lung with a higher dome, placed off
#    centre, is voxelised at 2 mm and written as NIfTI, as a segmentation would come.
# 2. The bundled reference mesh is registered onto it: a similarity fit of the image's
#    moments, then a Sobolev-gradient descent of the mismatch $\int_\omega I \, dx$ in
#    stages ([shape registration](../guide/registration.md)).
# 3. Ten synthetic patients driven by 2 latent shape parameters (elongation and dome), with
#    random sizes and positions, are registered; their mappings, similarity removed, are
#    reduced by a mass-weighted POD into shape modes.
#
# Run it as `python demos/register_lung.py [-o FOLDER]`.

# %%
import shutil
import time

from mpi4py import MPI

import numpy as np

from lungmech import mesh as geometry
from lungmech import meshes
from lungmech.app import registration as workflow
from lungmech.app.demo import Demo
from lungmech.mesh.lung_shape import LungShape
from lungmech.registration import image, metrics, phantom, pictures
from lungmech.registration.library import ShapeModes

REFERENCE = meshes.reference("lung_phantom_right")
demo = Demo("register_lung", inputs=[REFERENCE])
comm = MPI.COMM_WORLD
out = demo.folder

# %% [markdown]
# ## A synthetic patient
#
# Saved and read back as a real segmentation is: a binary image with its spacing and origin.

# %%
patient = LungShape(height=0.26, width=0.10, depth=0.16, dome=0.22, apex=0.27)
target = out / "patient.nii.gz"
if comm.rank == 0:
    image.write(phantom.voxelise(patient, 0.002, offset=(0.012, 0.02, -0.03)), target)
comm.Barrier()
segmentation = image.read(target)

# %% [markdown]
# ## Registration
#
# `register_image` writes the mapped mesh (`registered.vtu`), the mapping, a report and a
# picture of the fitted surface over slices of the image.

# %%
report = workflow.register_image(REFERENCE, segmentation, out / "registration", comm=comm)
demo.report("iterations", report["iterations"])
demo.report("seconds", report["seconds"])
demo.report("dice", report["dice"])
demo.report("distance", 1e3 * report["mean_surface_distance"])
demo.report("distance_voxels", report["mean_surface_distance_voxels"])
demo.report("hd95", 1e3 * report["hd95"])
demo.report(
    "min_det_F",
    report["min_det_F"],
    f"registered in {report['iterations']} iterations, {report['seconds']:.1f} s: Dice {report['dice']:.4f}, "
    f"mean surface distance {1e3 * report['mean_surface_distance']:.2f} mm "
    f"({report['mean_surface_distance_voxels']:.2f} voxels), hd95 {1e3 * report['hd95']:.2f} mm, "
    f"min det F {report['min_det_F']:.3f}",
)
# A converged descent: the surface within a voxel on average, no element near inversion.
assert report["dice"] > 0.98 and report["mean_surface_distance_voxels"] < 1.0 and report["min_det_F"] > 0.25
if comm.rank == 0:
    shutil.copy(out / "registration" / "registration.png", out / "registration.png")
demo.show("registration.png")

# %% [markdown]
# The descent took {glue:text}`iterations:.0f` iterations in {glue:text}`seconds:.1f` s:
# Dice {glue:text}`dice:.3f`, mean surface distance {glue:text}`distance:.2f` mm
# ({glue:text}`distance_voxels:.2f` voxel), hd95 {glue:text}`hd95:.1f` mm, smallest
# $\det F$ {glue:text}`min_det_F:.2f`.
#
# ## Shape modes of a cohort

# %%
start = time.perf_counter()
cohort = phantom.cohort(10, latent=2, seed=3, size_spread=0.05, shift=0.01)
sources = {f"patient_{j:02d}": im for j, im in enumerate(cohort.images(spacing=0.0025))}
summary = workflow.build_shape_modes(REFERENCE, sources, out / "shape_modes", comm=comm)
sigma = np.asarray(summary["singular_values"])
loo = 1e3 * np.asarray(summary["leave_one_out_rms"])
demo.report("worst_dice", summary["worst"]["dice"])
demo.report("compactness", 100 * summary["compactness"][1])
for i, ratio in enumerate(sigma[:4] / sigma[0]):
    demo.report(f"sigma_{i}", ratio)
for i, error in enumerate(loo[:4]):
    demo.report(f"loo_{i}", error)
demo.report(
    "cohort_seconds",
    time.perf_counter() - start,
    f"{len(sources)} mappings in {time.perf_counter() - start:.0f} s (worst Dice {summary['worst']['dice']:.4f}); "
    f"σ/σ1 = {np.array2string(sigma / sigma[0], precision=3)}; the first 2 modes capture "
    f"{100 * summary['compactness'][1]:.1f} % of the variance; leave-one-out RMS error "
    f"{' → '.join(f'{e:.2f}' for e in loo[:4])} mm with 0 → {min(len(loo), 4) - 1} modes",
)
# Two latent parameters: two modes carry nearly all the variance, and they predict unseen shapes.
assert summary["compactness"][1] > 0.9 and loo[2] < 0.5 * loo[0]
if comm.rank == 0:
    shutil.copy(out / "shape_modes" / "singular_values.png", out / "shape_modes.png")
demo.show("shape_modes.png")

# %% [markdown]
# The ten registrations' worst Dice is {glue:text}`worst_dice:.3f`. The first 2 modes capture
# {glue:text}`compactness:.1f` % of the variance ($\sigma/\sigma_1$ = 1,
# {glue:text}`sigma_1:.3f`, {glue:text}`sigma_2:.3f`, {glue:text}`sigma_3:.3f`, …), and the
# leave-one-out error falls {glue:text}`loo_0:.2f` → {glue:text}`loo_1:.2f` →
# {glue:text}`loo_2:.2f` → {glue:text}`loo_3:.2f` mm with 0 → 3 modes. The first mode is the
# elongation. The remaining variance comes from two sources: the shape parameters act
# non-linearly, and registration leaves noise of about a third of a voxel. These last digits
# follow the CPU's floating point.
#
# ## The modes, and a new lung
#
# The mean shape and ±2 standard deviations along each of the first two modes, in three
# sections; then a new lung at +1σ along mode 1 and −1σ along mode 2, written as a mesh file
# that meshio, pyvista and ParaView open and a scene reads as `[geometry] file`.

# %%
modes = ShapeModes.load(out / "shape_modes" / "shape_modes.npz")
coefficients = {"mean": [], "mode 1 +2σ": [2.0], "mode 1 −2σ": [-2.0], "mode 2 +2σ": [0, 2.0], "mode 2 −2σ": [0, -2.0]}
surfaces = {
    label: metrics.boundary_triangles(modes.geometry(geometry.from_file(REFERENCE, comm), c).mesh)
    for label, c in coefficients.items()
}
if comm.rank == 0:
    title = "Shape modes of 10 synthetic patients (2 latent parameters)"
    pictures.surface_sections(surfaces, out / "shape_mode_sections.png", title=title)
demo.show("shape_mode_sections.png")
new = modes.geometry(geometry.from_file(REFERENCE, comm), [1.0, -1.0])
geometry.write(new, out / "new_lung.vtu")
demo.report(
    "new_volume",
    1e3 * new.volume(),
    f"new lung (+1σ mode 1, −1σ mode 2): volume {1e3 * new.volume():.3f} L -> new_lung.vtu",
)
demo.close()

# %% [markdown]
# The new lung's volume is {glue:text}`new_volume:.2f` L.
