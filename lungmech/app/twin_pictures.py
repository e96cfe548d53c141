"""The personalised lung's pictures, as a clinician reads them (off-screen; units on every axis).

* :func:`fitted_surface` — the fitted lung at end-inspiration, its surface coloured by what is
  left of the fit: each node's signed distance to the segmented end-inspiration surface, less
  the node's own offset at end-expiration (mm; + outside), from the front and from the side;
* :func:`pressure_volume_band` — the personalised P–V curve from end-expiration to
  end-inspiration, the band of the curves the parameters' intervals allow, and the segmented
  volumes at both ends;
* :func:`ventilation_picture` — regional ventilation, the volume change J − 1 (%) from
  end-expiration to end-inspiration, observed (a registration of the two segmentations) beside
  fitted (the full model at the estimate), on a sagittal cut (:mod:`lungmech.twin.ventilation`);
* :func:`pictures` — these, for each pair of images of an estimate, into a folder (the models
  solved on every rank, the pictures drawn on the first).

Axes as the lung meshes': x towards the patient's right, y anterior, z superior.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mpi4py import MPI

import numpy as np

from lungmech import lung
from lungmech.app.console import CMH2O
from lungmech.app.plot import drawn, pyplot
from lungmech.parallel import on_root
from lungmech.registration.image import Image
from lungmech.twin.fit import Estimate, Fit, View
from lungmech.twin.uncertainty import Interval
from lungmech.twin.ventilation import Ventilation, ventilation

if TYPE_CHECKING:
    from pyvista.plotting._typing import ScalarBarArgs

__all__ = ["fitted_surface", "pictures", "pressure_volume_band", "ventilation_picture"]

STEPS = 12  # points of a P–V curve from end-expiration to end-inspiration


def pictures(
    fit: Fit,
    found: Estimate,
    intervals: dict[str, Interval],
    folder: Path,
    comm: MPI.Comm,
    full: Sequence[View] = (),
    inspirations: Sequence[Image] = (),
) -> list[str]:
    """``fit-<pair>.png`` and ``pressure_volume-<pair>.png`` for each pair of ``fit`` at the
    estimate ``found``, the band from the corners of the ``intervals`` (a parameter without
    one at its value); with each pair's ``full`` model view and ``inspirations`` segmentation,
    ``ventilation-<pair>.png`` too. The names of those drawn. Collective."""
    made = []
    for view, full_view, image in zip(fit.views, full, inspirations):
        lungs = ventilation(full_view.model, dict(view.fixed) | found.values, view.time, image)
        path = folder / f"ventilation-{view.name}.png"
        if drawn(comm, path, partial(ventilation_picture, lungs, path, f"{view.name}: regional ventilation")):
            made.append(path.name)
    for view, prediction in zip(fit.views, fit.predictions(found.unit)):
        surface = folder / f"fit-{view.name}.png"
        draw = partial(
            fitted_surface,
            prediction.positions,
            view.nodes.triangles,
            prediction.residual[: len(view.nodes.points)],
            surface,
            f"{view.name}: the fitted end-inspiration lung",
        )
        if drawn(comm, surface, partial(on_root, comm, draw)):
            made.append(surface.name)
        curves = _curves(view, fit, found, intervals)
        if curves is None:  # no pressure load: no P–V curve
            continue
        label, estimate, band = curves
        base = view.baseline.volume if view.baseline is not None else float("nan")
        path = folder / f"pressure_volume-{view.name}.png"
        title = f"{view.name}: the personalised P–V curve"
        draw = partial(pressure_volume_band, *estimate, band, (base, view.surface.volume), path, label, title)
        if drawn(comm, path, partial(on_root, comm, draw)):
            made.append(path.name)
    return made


Curve = tuple[np.ndarray, np.ndarray]  # (pressure in Pa, volume in m³) along the breath


def _curves(
    view: View, fit: Fit, found: Estimate, intervals: dict[str, Interval]
) -> tuple[str, Curve, list[Curve]] | None:
    """The view's P–V curve at the estimate and at each corner of the intervals, with the
    pressure's label (None without a pressure load). Collective."""
    model = view.model.model
    axis = lung.pressure_axis(model.loads, model.formulation)
    if axis is None:
        return None
    times = np.linspace(view.model.stepping.start, view.time, STEPS).tolist()

    def curve(values: dict[str, float]) -> Curve:
        outputs = view.model.solve(dict(view.fixed) | values, times=times).outputs
        labels = [name.removeprefix("loads/") for name in outputs if name.startswith("loads/")]
        pressure = [axis({label: float(outputs[f"loads/{label}"][i]) for label in labels}) for i in range(len(times))]
        return np.array(pressure), np.asarray(outputs["volume"], dtype=float)

    ends: list[tuple[float, ...]] = []
    for parameter in fit.parameters:
        interval, value = intervals[parameter.name], found.values[parameter.name]
        if interval.low is None or interval.high is None:
            ends.append((value,))
        else:  # (cut at the range's edges)
            ends.append(
                tuple(
                    parameter.from_unit(float(np.clip(parameter.to_unit(v), 0, 1)))
                    for v in (interval.low, interval.high)
                )
            )
    band = [curve(dict(zip(fit.names, corner))) for corner in itertools.product(*ends)]
    return axis.label, curve(dict(found.values)), band


def fitted_surface(
    points: np.ndarray, triangles: np.ndarray, residual: np.ndarray, path: Path, title: str = ""
) -> None:
    """The surface of ``triangles`` on the fitted nodes ``points`` (m), coloured by
    ``residual`` (m, drawn in mm, a diverging scale centred at 0), seen from the front (the
    patient's anterior) and from the patient's side of the lung."""
    import pyvista
    import vtk

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server" noise: rendering is off-screen
    faces = np.hstack([np.full((len(triangles), 1), 3), triangles]).astype(np.int64).ravel()
    surface = pyvista.PolyData(np.asarray(points, dtype=float), faces)
    surface.point_data["residual [mm]"] = 1e3 * np.asarray(residual, dtype=float)
    limit = float(np.max(np.abs(surface.point_data["residual [mm]"]))) or 1.0
    centre = surface.center
    size = float(np.linalg.norm(np.ptp(np.asarray(points), axis=0)))
    side = 1.0 if centre[0] >= 0 else -1.0  # a right lung is seen from the right
    plotter = pyvista.Plotter(off_screen=True, shape=(1, 2), window_size=[1400, 720], border=False)
    for column, (view, name) in enumerate(
        ((np.array([0.0, 1.0, 0.0]), "anterior"), (np.array([side, 0.0, 0.0]), "lateral"))
    ):
        plotter.subplot(0, column)
        plotter.add_mesh(
            surface.copy(),
            scalars="residual [mm]",
            cmap="coolwarm",
            clim=(-limit, limit),
            smooth_shading=True,
            show_scalar_bar=column == 1,
            scalar_bar_args=_scalar_bar("distance left [mm]", "%.2f"),
        )
        said = f"{title}\n{name} view" if column == 0 else f"{name} view (+: outside the segmented surface)"
        plotter.add_text(said, font_size=10)
        _look(plotter, centre, size, view)
    plotter.screenshot(str(path))
    plotter.close()


def pressure_volume_band(
    pressure: np.ndarray,
    volume: np.ndarray,
    band: Sequence[tuple[np.ndarray, np.ndarray]],
    segmented: tuple[float, float],
    path: Path,
    label: str,
    title: str = "",
) -> None:
    """The personalised P–V curve (``pressure`` in Pa, drawn in kPa and cmH2O; ``volume`` in
    m³, drawn in L), the envelope of the ``band``'s curves (each its own (pressure, volume): a
    parameter changes the pressure as well as the volume), and the ``segmented`` volumes of
    end-expiration and end-inspiration (m³): the curve rises by their difference (what was
    fitted), from the registered mesh's own volume, which the note compares with the first."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.2, 4.4))
    kpa = np.asarray(pressure) / 1e3
    if band:
        low = max(float(np.min(p)) for p, _ in band)
        high = min(float(np.max(p)) for p, _ in band)
        if high > low:  # the pressures every curve of the band reaches
            grid = np.linspace(low, high, 60)
            curves = np.array([np.interp(grid, *_rising(p, v)) for p, v in band])
            ax.fill_between(
                grid / 1e3, 1e3 * curves.min(axis=0), 1e3 * curves.max(axis=0), color="tab:blue", alpha=0.2,
                label="band: the parameters' intervals",
            )  # fmt: skip
    ax.plot(kpa, 1e3 * np.asarray(volume), "o-", color="tab:blue", ms=3, lw=2, label="personalised (the estimate)")
    for value, name, style in zip(segmented, ("end-expiration", "end-inspiration"), (":", "--")):
        ax.axhline(1e3 * value, color="0.3", ls=style, lw=1, label=f"segmented volume, {name}")
    offset = 1e3 * (float(volume[0]) - segmented[0])
    note = f"the registered mesh holds {offset:+.3f} L against the segmentation at end-expiration (chords)"
    ax.text(0.98, 0.02, note, transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.35")
    ax.set_xlabel(f"{label} [kPa]")
    ax.set_ylabel("lung volume [L]")
    top = ax.secondary_xaxis("top", functions=(lambda p: 1e3 * p / CMH2O, lambda c: c * CMH2O / 1e3))
    top.set_xlabel("[cmH$_2$O]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def ventilation_picture(lungs: Ventilation, path: Path, title: str = "") -> None:
    """J − 1 (%) on a sagittal cut through the lung imaged at end-expiration (where the
    weight's front-to-back gradient shows, lying down), observed beside fitted, on one colour
    scale, seen from the lung's side. Collective; the first rank draws."""
    from dolfinx import plot

    mesh = lungs.mesh
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    topology, types, x = plot.vtk_mesh(mesh, mesh.topology.dim, np.arange(owned, dtype=np.int32))
    pieces = mesh.comm.gather((topology, types, x, lungs.fitted, lungs.observed), root=0)
    on_root(mesh.comm, lambda: _cut(pieces, path, title))


def _cut(pieces: Sequence[tuple[np.ndarray, ...]], path: Path, title: str) -> None:
    import pyvista
    import vtk

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server" noise: rendering is off-screen
    grids = []
    for topology, types, x, fitted, observed in pieces:
        grid = pyvista.UnstructuredGrid(topology, types, x)
        grid.cell_data["fitted"], grid.cell_data["observed"] = 100 * fitted, 100 * observed
        grids.append(grid)
    lung = pyvista.merge(grids) if len(grids) > 1 else grids[0]
    centre = np.asarray(lung.center)
    side = 1.0 if centre[0] >= 0 else -1.0  # a right lung (x > 0) is seen from the right
    # a sagittal cut: the weight's gradient, front to back when lying down, lies in it
    cut = lung.clip(normal=(side, 0.0, 0.0), origin=centre)  # the medial half, its cut face to the viewer
    where = f"sagittal cut, seen from the lung's side: anterior to the {'right' if side > 0 else 'left'}"
    values = np.concatenate([lung.cell_data["fitted"], lung.cell_data["observed"]])
    limits = (float(np.percentile(values, 1)), float(np.percentile(values, 99)))
    size = float(np.linalg.norm(np.ptp(np.asarray(lung.points), axis=0)))
    plotter = pyvista.Plotter(off_screen=True, shape=(1, 2), window_size=[1400, 720], border=False)
    for column, (name, said) in enumerate(
        (
            ("observed", "observed: a registration of the two segmentations (inside: its regulariser's)"),
            ("fitted", "fitted: the model at the estimate"),
        )
    ):
        plotter.subplot(0, column)
        plotter.add_mesh(
            cut.copy(),
            scalars=name,
            cmap="viridis",
            clim=limits,
            show_scalar_bar=column == 1,
            scalar_bar_args=_scalar_bar("J - 1 [%]", "%.0f"),
        )
        plotter.add_text((f"{title}\n" if column == 0 and title else "") + f"{said}\n{where}", font_size=9)
        _look(plotter, centre, size, np.array([side, 0.0, 0.0]))
    plotter.screenshot(str(path))
    plotter.close()


def _scalar_bar(title: str, fmt: str) -> ScalarBarArgs:
    """A vertical colour bar at the right of the second panel."""
    return {
        "title": title,
        "vertical": True,
        "fmt": fmt,
        "position_x": 0.8,
        "position_y": 0.15,
        "width": 0.08,
        "height": 0.7,
    }


def _look(plotter: Any, centre: Sequence[float] | np.ndarray, size: float, direction: np.ndarray) -> None:
    """The current panel's camera: at ``direction`` from ``centre``, far enough for a body of
    ``size`` (m), the patient's head up."""
    plotter.camera.focal_point = centre
    plotter.camera.position = np.asarray(centre) + 2.6 * size * direction
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.camera.view_angle = 30.0


def _rising(pressure: np.ndarray, volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A curve's points in increasing pressure (np.interp's order)."""
    order = np.argsort(pressure)
    return np.asarray(pressure)[order], np.asarray(volume)[order]
