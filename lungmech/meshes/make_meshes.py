"""Regenerate the meshes bundled in this folder: ``python -m lungmech.meshes.make_meshes``.

Gmsh runs single-threaded with a fixed seed, so the files come out the same on every run.
"""

from pathlib import Path

from mpi4py import MPI

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)
from lungmech.mesh import lung_phantom, sphere

HERE = Path(__file__).resolve().parent


def main() -> None:
    meshes = {
        "lung_phantom_right.msh": lambda path: lung_phantom(MPI.COMM_SELF, side="right", msh_file=path),
        "lung_phantom_left.msh": lambda path: lung_phantom(MPI.COMM_SELF, side="left", msh_file=path),
        "sphere_octant.msh": lambda path: sphere(MPI.COMM_SELF, 1.0, 2.0, octant=True, msh_file=path),
    }
    for name, make in meshes.items():
        geometry = make(HERE / name)
        cells = geometry.mesh.topology.index_map(3).size_global
        kb = (HERE / name).stat().st_size / 1024
        volume, names = geometry.volume(), ", ".join(geometry.boundaries)
        print(f"{name}: {cells} tetrahedra, {kb:.0f} kB, volume {volume:.6g}, boundaries {names}")


if __name__ == "__main__":
    if MPI.COMM_WORLD.rank == 0:  # the meshes are serial files: one writer
        main()
