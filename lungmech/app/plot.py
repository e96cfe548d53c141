"""Pictures of results (matplotlib and pyvista, off-screen), with units on every axis."""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from lungmech.app.console import CMH2O

if TYPE_CHECKING:
    from mpi4py import MPI

    from lungmech.fem.model import Model

__all__ = ["deformed_body", "drawn", "pareto", "pressure_volume", "pyplot", "sweep_volumes"]


def pyplot() -> ModuleType:
    """matplotlib's pyplot, off-screen, imported when a picture is drawn (0.3–0.4 s of every
    process's start-up otherwise, with or without a picture)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def drawn(comm: MPI.Comm, path: Path, draw: Callable[[], object]) -> bool:
    """Collective: ``draw()`` a picture (itself collective). A picture that cannot be drawn (no
    off-screen rendering on this machine, say) is a warning on the console, not a failed run:
    the results are in the other files. Returns whether it was drawn."""
    import logging

    try:
        draw()
        return True
    except Exception as error:  # raised on every rank alike: draw() is collective
        if comm.rank == 0:
            reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
            logging.getLogger("lungmech").warning("lungmech: warning: %s was not drawn (%s)", Path(path).name, reason)
        return False


def pressure_volume(
    pressure: Sequence[float],
    volume: Sequence[float],
    path: Path,
    label: str,
    title: str = "",
    note: Sequence[str] = (),
    planar: bool = False,
) -> None:
    """The P–V curve: volume (m³, drawn in L; a ``planar`` body's in m³ per m of thickness)
    against ``pressure`` (Pa, drawn in kPa, with cmH2O on the top axis), inspiration (volume
    rising) and expiration drawn apart. ``label`` names the pressure; ``note`` lines say what
    it is made of."""
    kpa = np.asarray(pressure, dtype=float) / 1e3
    shown = np.asarray(volume, dtype=float) * (1.0 if planar else 1e3)
    unit = "m³/m" if planar else "L"
    rising = np.diff(shown) >= 0
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.4))
    branches = (
        (rising, dict(color="tab:blue", ls="-", marker="o", ms=4, lw=2.5), "inspiration (volume rising)"),
        (
            ~rising,
            dict(color="tab:orange", ls="--", marker="s", ms=3, mfc="none", lw=1.2),
            "expiration (volume falling)",
        ),
    )
    for branch, style, name in branches:
        for k, i in enumerate(np.flatnonzero(branch)):
            ax.plot(kpa[i : i + 2], shown[i : i + 2], **style, label=name if k == 0 else None)
    ax.set_xlabel(f"{label} [kPa]")
    ax.set_ylabel(f"{'lung volume' if label.startswith('transpulmonary') else 'volume'} [{unit}]")
    top = ax.secondary_xaxis("top", functions=(lambda p: 1e3 * p / CMH2O, lambda c: c * CMH2O / 1e3))
    top.set_xlabel("[cmH$_2$O]")
    ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=9)
    if note:
        ax.text(0.98, 0.02, "\n".join(note), transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.35")
    if rising.any() or (~rising).any():
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def sweep_volumes(
    times: Sequence[float] | np.ndarray,
    volumes: Sequence[Sequence[float] | np.ndarray],
    labels: Sequence[str],
    path: Path,
    title: str = "",
    planar: bool = False,
    against: Sequence[tuple[str, Sequence[float]]] = (),
) -> None:
    """The volume (m³, drawn in L; a ``planar`` body's in m³ per m of thickness) of every point
    of a sweep against time (s), one curve per point (the legend names at most ten; more are
    coloured by their order). A sweep of one output time is drawn against the parameters that
    vary instead, ``against`` = [(label with its unit, the points' values), …]: the first on
    the axis, the second (if any) as the points' colour."""
    scale, unit = (1.0, "m³/m") if planar else (1e3, "L")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    if len(times) == 1 and against:
        final = np.asarray(volumes)[:, 0] * scale
        if len(against) > 1:  # points, not a curve: another parameter varies between them
            shown = ax.scatter(against[0][1], final, c=against[1][1], cmap="viridis", s=30)
            fig.colorbar(shown, ax=ax, label=against[1][0])
        else:
            order = np.argsort(against[0][1])
            ax.plot(np.asarray(against[0][1])[order], final[order], "o-", color="tab:blue")
        ax.set_xlabel(against[0][0])
        ax.set_ylabel(f"volume at t = {times[0]:g} s [{unit}]")
    else:
        colours = plt.cm.viridis(np.linspace(0.0, 0.9, len(volumes)))
        for volume, label, colour in zip(volumes, labels, colours):
            ax.plot(times, np.asarray(volume) * scale, "o-", ms=3, lw=1.2, color=colour, label=label)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"volume [{unit}]")
        if len(volumes) <= 10:
            ax.legend(fontsize=7, loc="best")
        else:
            note = f"{len(volumes)} points, dark → light in file order"
            ax.text(0.02, 0.98, note, transform=ax.transAxes, va="top", fontsize=7, color="0.35")
    ax.grid(alpha=0.3)
    fig.suptitle(title or f"sweep of {len(volumes)} parameter points", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def deformed_body(model: Model, path: Path, title: str = "") -> None:
    """A PNG of the deformed body coloured by J = det F (the local volume ratio), with an
    orientation triad; the camera is set by the reference configuration, so every state of a
    body is seen alike. Collective under MPI; rank 0 draws, and an error
    there is raised on every rank."""
    import ufl
    from dolfinx import fem, plot

    from lungmech import jit
    from lungmech.parallel import on_root

    mesh = model.geometry.mesh
    u = model.motion()  # from the mesh's nodes (on an image: the motion w from it)
    cells_owned = mesh.topology.index_map(mesh.topology.dim).size_local
    topology, types, x = plot.vtk_mesh(u.function_space, np.arange(cells_owned, dtype=np.int32))  # type: ignore[arg-type]  # the FunctionSpace overload (singledispatch) is not in the hints
    dg0 = fem.functionspace(mesh, ("DG", 0))
    J = fem.Function(dg0)
    J.interpolate(jit.expression(ufl.det(model.F), dg0.element.interpolation_points))
    J_cells = J.x.array[dg0.dofmap.list[:cells_owned, 0]]
    gdim = mesh.geometry.dim
    displacement = np.zeros((len(x), 3))  # VTK's points are 3-D; a plane body's z stays 0
    displacement[:, :gdim] = u.x.array.reshape(-1, gdim)[: len(x)]
    pieces = mesh.comm.gather((topology, types, x, displacement, J_cells), root=0)
    on_root(mesh.comm, lambda: _draw(pieces, path, title, planar=gdim == 2))


def _colour_format(low: float, high: float) -> str:
    """Enough significant digits for the colour bar's labels to differ across [low, high] (a
    nearly incompressible body's J spans 1 ± 1e-4)."""
    spread, size = high - low, max(abs(low), abs(high))
    digits = 3 if spread <= 0 or size == 0 else 3 + max(0, int(np.ceil(np.log10(size / spread))) - 1)
    return f"%.{min(digits, 10)}g"


def _draw(pieces: Sequence[Sequence[np.ndarray]], path: Path, title: str, planar: bool = False) -> None:
    import pyvista
    import vtk

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server" noise: rendering is off-screen
    bodies, lowers, uppers = [], [], []
    for topology, types, x, displacement, J_cells in pieces:
        grid = pyvista.UnstructuredGrid(topology, types, x + displacement)
        grid.cell_data["J"] = J_cells
        bodies.append(grid)
        if len(x):
            lowers.append(x.min(axis=0))
            uppers.append(x.max(axis=0))
    body = pyvista.merge(bodies) if len(bodies) > 1 else bodies[0]
    low, high = (float(f(body.cell_data["J"])) for f in (np.min, np.max)) if body.n_cells else (1.0, 1.0)

    plotter = pyvista.Plotter(off_screen=True, window_size=[1000, 760])
    plotter.add_mesh(
        body,
        scalars="J",
        cmap="viridis",
        show_edges=False,
        smooth_shading=False,
        scalar_bar_args={
            "title": "J = det F [-]",
            "vertical": True,
            "position_x": 0.86,
            "position_y": 0.15,
            "width": 0.07,
            "height": 0.7,
            "fmt": _colour_format(low, high),
            "title_font_size": 14,
            "label_font_size": 12,
        },
    )
    if title:
        plotter.add_text(title, font_size=10)
    plotter.add_axes(line_width=3, labels_off=False)  # type: ignore[call-arg]  # pyvista wraps Renderer.add_axes (functools.wraps): its hint keeps the unbound self
    # A fixed camera: medial-anterior view (the hilum side of a lung), or a plane body seen from
    # +z with y up, framed by the reference with room for the body to grow and for the colour
    # bar on the right.
    lower, upper = np.min(lowers, axis=0), np.max(uppers, axis=0)  # of the reference configuration
    centre, size = (lower + upper) / 2, float(np.linalg.norm(upper - lower))
    view, up = (
        (np.array([0.0, 0.0, 1.0]), (0.0, 1.0, 0.0)) if planar else (np.array([-1.0, -0.7, 0.35]), (0.0, 0.0, 1.0))
    )
    view /= np.linalg.norm(view)
    right = np.cross(view, up)
    right /= np.linalg.norm(right)
    focus = centre - 0.12 * size * right  # shifts the body left, clear of the colour bar
    plotter.camera.focal_point = focus
    plotter.camera.position = focus + 2.6 * size * view  # pyvista: the camera sits along +view
    plotter.camera.up = up
    plotter.camera.view_angle = 30.0
    plotter.screenshot(str(path))
    plotter.close()


MARKERS = {"full": "o", "galerkin": "s", "ecsw": "^", "pgd": "D"}  # a marker per model family


def pareto(
    models: Sequence[tuple[str, str, float | None, float | None, int, float]],
    tolerance: float | Sequence[float],
    error_label: str,
    path: Path,
    chosen: str | Sequence[str] | None = None,
    title: str = "",
    accuracy: float | None = None,
) -> None:
    """The speed–accuracy trade: each model's worst error against its warm online time per
    point (ms), log–log, a marker per family; ``models`` are (name, family, online ms, worst
    error, failed points, offline s). Each tolerance is a line, and so is the reference's own
    ``accuracy`` where known; the chosen models are ringed, a model that failed somewhere drawn
    hollow and red. Each marker carries a number, and a key beside the plot names its model
    with its offline cost (names beside markers overlap where models are close)."""
    tolerances = [float(tolerance)] if isinstance(tolerance, int | float) else [float(t) for t in tolerance]
    ringed = [chosen] if isinstance(chosen, str) else list(chosen or ())
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.6, 4.8))
    shown = [
        (m[0], m[1], float(m[2]), float(m[3]), m[4], m[5]) for m in models if m[2] is not None and m[3] is not None
    ]
    floor = min([m[3] for m in shown if m[3] > 0] + tolerances) / 10
    for i, family in enumerate(dict.fromkeys(m[1] for m in shown)):
        mine, colour = [m for m in shown if m[1] == family], f"C{i}"
        ax.scatter(
            [m[2] for m in mine],
            [max(m[3], floor) for m in mine],
            marker=MARKERS.get(family, "P"),
            s=46,
            label=family,
            facecolors=["none" if m[4] else colour for m in mine],
            edgecolors=["tab:red" if m[4] else colour for m in mine],
        )
    key = []
    for number, (name, _, online, error, failed, offline) in enumerate(shown, start=1):
        where = (online, max(error, floor))
        ax.annotate(str(number), where, xytext=(5, 3), textcoords="offset points", fontsize=7)
        if name in ringed:
            ax.scatter(*where, s=260, facecolors="none", edgecolors="k", linewidths=1.4)
        cost = (f", offline {offline:.3g} s" if offline else "") + (f", fails at {failed} points" if failed else "")
        key.append(f"{number}  {name}{cost}")
    ax.text(1.02, 0.0, "\n".join(key), transform=ax.transAxes, ha="left", va="bottom", fontsize=7)
    for k, line in enumerate(tolerances):
        ax.axhline(line, color="0.4", ls=("--", "-.", ":")[k % 3], lw=1, label=f"tolerance {line:.0e}")
    if accuracy is not None:
        ax.axhline(accuracy, color="0.6", ls=":", lw=1, label=f"the reference's own error ≈ {accuracy:.1e}")
    ax.margins(x=0.25, y=0.15)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("online time per point, warm median [ms]")
    ax.set_ylabel(textwrap.fill(error_label, 48))  # a long denominator on two lines, inside the figure
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: the markers keep the plot
    if ringed:
        text = "chosen (ringed): " + ", ".join(ringed)
        ax.text(0.99, 0.01, text, transform=ax.transAxes, ha="right", va="bottom", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")  # with the legend and the key outside the axes
    plt.close(fig)
