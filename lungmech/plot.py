"""Pictures of results (matplotlib, off-screen)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def pressure_volume(pressure: np.ndarray, volume: np.ndarray, path: Path, pressure_label: str) -> None:
    """The P–V curve, inspiration (volume rising) and expiration (falling) drawn apart."""
    pressure, volume = np.asarray(pressure, dtype=float), np.asarray(volume, dtype=float)
    rising = np.diff(volume) >= 0
    fig, ax = plt.subplots(figsize=(5.5, 4))
    branches = ((rising, "tab:blue", "-o", "inspiration"), (~rising, "tab:orange", "--s", "expiration"))
    for branch, colour, style, label in branches:
        for k, i in enumerate(np.flatnonzero(branch)):
            ax.plot(pressure[i : i + 2], volume[i : i + 2], style, color=colour, ms=3, label=label if k == 0 else None)
    ax.set_xlabel(pressure_label)
    ax.set_ylabel("volume")
    ax.set_title("Pressure–volume curve")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def deformed_body(model, path: Path, title: str = "") -> None:
    """A PNG of the deformed body coloured by J (pyvista, off-screen); collective under MPI."""
    import pyvista
    import ufl
    import vtk
    from dolfinx import fem, plot

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server" noise: rendering is off-screen
    mesh = model.geometry.mesh
    u = model.displacement()
    cells_owned = mesh.topology.index_map(mesh.topology.dim).size_local
    topology, types, x = plot.vtk_mesh(u.function_space, np.arange(cells_owned, dtype=np.int32))
    dg0 = fem.functionspace(mesh, ("DG", 0))
    J = fem.Function(dg0)
    J.interpolate(fem.Expression(ufl.det(model.F), dg0.element.interpolation_points))
    J_cells = J.x.array[dg0.dofmap.list[:cells_owned, 0]]
    displacement = u.x.array.reshape(-1, 3)[: len(x)]

    pieces = mesh.comm.gather((topology, types, x, displacement, J_cells), root=0)
    if mesh.comm.rank != 0:
        return
    grids = []
    for topology, types, x, displacement, J_cells in pieces:
        grid = pyvista.UnstructuredGrid(topology, types, x + displacement)
        grid.cell_data["J"] = J_cells
        grids.append(grid)
    body = pyvista.merge(grids) if len(grids) > 1 else grids[0]
    plotter = pyvista.Plotter(off_screen=True, window_size=(900, 700))
    plotter.add_mesh(body, scalars="J", cmap="viridis", show_edges=False, scalar_bar_args={"title": "J = det F"})
    if title:
        plotter.add_text(title, font_size=10)
    plotter.view_vector((-1.0, -0.7, 0.35), viewup=(0.0, 0.0, 1.0))  # medial-anterior: the hilum side of a lung
    plotter.screenshot(str(path))
    plotter.close()
