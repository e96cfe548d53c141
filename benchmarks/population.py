"""One reduced model for a population: the lung's shape as a parameter, against per-patient models.

    python benchmarks/population.py            # 26 synthetic patients (20 in the library, 6 held out), 3 modes
    python benchmarks/population.py --quick    # 4 patients (3 + 1), 2 modes, h = 40 mm: the suite's smoke run

Synthetic patients of three kinds, each a segmentation at CT spacing: lungmech's phantoms of
varied height, width, depth, dome and apex and size (``phantom.cohort``), phantoms warped by a
random smooth displacement (a few mm over a few cm), and lungs of another generator (a
superellipsoid with a domed base and a flat medial face, not made by the phantom builder). The
bundled right lung mesh is registered onto every one (``mapping_library``); the library's
members give shape modes taken without position and orientation (``pose = "rigid"``: the size
is kept), and the held-out patients are never part of it:

* **representation**: a held-out patient's mapping projected on the first k modes
  (``ShapeModes.project``): what the modes leave out, RMS and at the worst node, mm, against k,
  beside the library's own leave-one-out error;
* **one offline build**: the bundled breathing lung (imaged at end-expiration; stiffness c1,
  breath depth, posture) over its three parameters and the first ``--modes`` shape coefficients
  (±2 standard deviations), on the library's mean shape: POD of the inverse map and the breath
  and ECSW (``Reductor``), from ``--train`` Sobol' points;
* **at each held-out patient** (its coefficients from its projection, kept inside the box) and
  ``--points`` physical points (Sobol', another seed): the population model's answer against
  the full model on χ_a(Ω₀) — state in the energy norm (relative to the breath's largest
  change), breath volume (relative to its volume change), reference volume (relative to the
  inflation the inverse problem undoes) — and, apart, the full model on χ_a(Ω₀) against the full
  model on the patient's own registered mesh (the shape-representation error: the same measures);
  the static point's warm time as ``lungmech rom solve`` loads the model (its body of sampled
  cells);
* **offline**: the population build once, against one patient's own build (the same recipe
  without shape parameters, on its registered mesh) times the patients.

Writes results/population.{md,csv,png} (--quick: population_quick.*). One rank.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

from mpi4py import MPI

import machine
import numpy as np
from dolfinx import fem
from machine import provenance, say, write_results
from resumable import cached, code_version
from rom_imaged import inflation, on_body
from rom_parameters import lung_scene
from rom_real_time import _digest, static_seconds
from scipy import ndimage

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app import scene as scenes
from lungmech.app.run import build_model, full_order_model
from lungmech.fem.parameters import Parameters
from lungmech.fem.parametric import Solution
from lungmech.fem.placement import Image as Placement
from lungmech.mesh import nodes
from lungmech.registration import phantom
from lungmech.registration.image import Image, from_array
from lungmech.registration.library import mapping_library, without_similarity
from lungmech.rom.accuracy import errors
from lungmech.rom.body import cells_of
from lungmech.rom.reductor import ECSW, POD, Reductor, TrainingSet

RESULTS = machine.RESULTS
VERSION = code_version()
KINDS = ("phantom", "warped", "other")
BOX = 2.0  # the shape box: ± this many standard deviations of the library


# --- The patients ------------------------------------------------------------------------------


def warped(image: Image, amplitude: float, length: float, seed: int) -> Image:
    """``image``'s mask moved by a random smooth displacement: three components, each a sum of
    four cosines of wavelength ~``length`` (m), scaled to ``amplitude`` (m) at its largest."""
    rng = np.random.default_rng(seed)
    shape = image.mask.shape
    spacing = image.spacing
    grid = np.meshgrid(*[np.arange(n) * s for n, s in zip(shape, spacing)], indexing="ij")
    moved = []
    for axis in range(3):
        field = np.zeros(shape)
        for _ in range(4):
            k = rng.normal(size=3) * 2 * np.pi / length
            field += np.cos(sum(ki * g for ki, g in zip(k, grid)) + rng.uniform(0, 2 * np.pi))
        field *= amplitude / np.abs(field).max()
        moved.append(
            np.arange(shape[axis])[tuple(None if a != axis else slice(None) for a in range(3))] + field / spacing[axis]
        )
    mask = ndimage.map_coordinates(image.mask.astype(float), moved, order=1, mode="constant") > 0.5
    return image.with_mask(mask)


def other(seed: int, spacing: float) -> Image:
    """A lung of another generator than the phantom builder's: a superellipsoid (exponent 2.5)
    of random semi-axes, its base domed upward, its medial face flat (x > 0, a right lung)."""
    rng = np.random.default_rng(seed)
    a, b, c = rng.uniform(0.05, 0.06), rng.uniform(0.075, 0.09), rng.uniform(0.11, 0.13)  # x, y, z semi-axes
    dome = rng.uniform(0.03, 0.05)
    margin = 0.015
    axes = [
        np.arange(lo, hi, spacing)
        for lo, hi in ((-margin, 2 * a + margin), (-b - margin, b + margin), (-c - margin, c + margin))
    ]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    inside = np.abs((x - a * 0.8) / a) ** 2.5 + np.abs(y / b) ** 2.5 + np.abs(z / c) ** 2.5 <= 1.0
    inside &= x >= 0.0  # the mediastinal face
    inside &= z >= -c + dome * (1.0 - ((x - a) / a) ** 2 - (y / b) ** 2)  # the diaphragm's dome
    return from_array(inside, (spacing,) * 3, (axes[0][0], axes[1][0], axes[2][0]))


def patients(library: int, held: int, spacing: float, seed: int = 0) -> tuple[dict[str, Image], dict[str, str]]:
    """``library + held`` segmentations (name → image) and each one's kind: the kinds in turn,
    so the held-out ones (the last ``held``) mix them too."""
    count = library + held
    kinds = [KINDS[j % len(KINDS)] for j in range(count)]
    cohort = phantom.cohort(count, latent=4, seed=seed, size_spread=0.05)
    images = {}
    for j, kind in enumerate(kinds):
        if kind == "phantom":
            image = phantom.voxelise(cohort.shapes[j], spacing)
        elif kind == "warped":
            image = warped(phantom.voxelise(cohort.shapes[j], spacing), 0.004, 0.08, seed + j)
        else:
            image = other(seed + j, spacing)
        images[f"{kind}_{j:02d}"] = image
    return images, {name: name.rpartition("_")[0] for name in images}


# --- The population's scene ----------------------------------------------------------------------


def population_scene(base: scenes.Scene, modes_file: Path, count: int) -> scenes.Scene:
    """The bundled breathing lung's scene over its parameters and ``count`` shape coefficients
    (±BOX standard deviations), on the library's mean shape."""
    table = copy.deepcopy(base.table)
    table["geometry"]["shape_modes"] = str(modes_file)
    for k in range(1, count + 1):
        table["parameters"][f"shape_{k}"] = {"target": f"shape.mode_{k}", "range": [-BOX, BOX]}
    return scenes.parse(table, folder=modes_file.parent)


def own_model(base: scenes.Scene, reference, displacement: np.ndarray):
    """The full model of the scene on the reference moved by ``displacement`` (canonical nodes)."""
    geometry = scenes.build_geometry(base.geometry, MPI.COMM_WORLD)
    space, where = nodes.displacement_space(geometry.mesh)
    u = fem.Function(space)
    nodes.scatter(displacement, u, where)
    nodes.move_nodes(u)
    model = build_model(base, MPI.COMM_WORLD, geometry=geometry, image=Placement.motion(base.stepping.start))
    return full_order_model(base, start="inverse_motion", model=model)


# --- The run -------------------------------------------------------------------------------------


def case(args) -> tuple[list[dict], dict]:
    base = lung_scene(args.size, [round(0.1 * i, 1) for i in range(1, 21)])  # 20 outputs over the breath
    if args.quick:  # the smoke run: the breath in, in 4 steps (its outputs at each)
        table = copy.deepcopy(base.table)
        table["stepping"] |= {"end": 1.0, "max_step": 0.25, "times": [0.25, 0.5, 0.75, 1.0]}
        base = scenes.parse(table)
    physical = Parameters(base.parameters)
    images, kinds = patients(args.library, args.held, 1e-3 * args.spacing)
    names = list(images)
    say(f"{len(images)} patients: " + ", ".join(f"{sum(k == kind for k in kinds.values())} {kind}" for kind in KINDS))
    reference = scenes.build_geometry(base.geometry, MPI.COMM_WORLD)
    tic = time.perf_counter()
    everyone = cached(
        f"population-library-{args.size}-{args.spacing}-{len(names)}",
        VERSION,
        lambda: mapping_library(reference.mesh, images),
    )
    registration_s = (time.perf_counter() - tic) / len(names)
    members = names[: args.library]
    held = names[args.library :]
    library = replace(
        everyone,
        names=tuple(members),
        displacements=everyone.displacements[: args.library],
        reports=everyone.reports[: args.library],
    )
    modes = library.modes("rigid")
    say(f"modes: σ = {', '.join(f'{1e3 * s:.1f}' for s in modes.deviations[:6])} mm (RMS)")
    loo = library.leave_one_out("rigid")
    representation = {
        name: [modes.project(everyone.displacements[names.index(name)], k) for k in range(min(len(modes.modes), 8) + 1)]
        for name in held
    }
    with tempfile.TemporaryDirectory() as folder:
        modes_file = Path(folder) / "population_modes.npz"
        modes.save(modes_file)
        scene = population_scene(base, modes_file, args.modes)
        box = Parameters(scene.parameters)
        full = full_order_model(scene, start="inverse_motion")
        mesh = full.model.geometry.mesh
        dofs = full.model.space.dofmap.index_map.size_global * full.model.space.dofmap.index_map_bs
        tic = time.perf_counter()
        with Reductor(full, POD(args.size_k), TrainingSet(box.sample(args.train, seed=0))) as reductor:
            reduced = reductor.reduce(ECSW(args.tau))
            timings = dict(reductor.timings)
        population_s = time.perf_counter() - tic
        say(f"population model: {reduced.basis.size} vectors, built in {population_s:.0f} s")
        shipped = on_body(reduced, scene)
        rows = []
        points = physical.sample(args.points, seed=4321)
        for name in held:
            projection = representation[name][args.modes]
            raw = projection.coefficients
            a = np.clip(raw, -BOX, BOX)
            shape = {f"shape_{k + 1}": float(v) for k, v in enumerate(a)}
            own = own_model(
                base,
                reference,
                without_similarity(modes.reference, everyone.displacements[names.index(name)], modes.weights, "rigid"),
            )
            for j, mu in enumerate(points):
                at = mu | shape
                tag = f"population-{_digest(scene)}-{name}-{j}"
                exact = cached(f"{tag}-template", VERSION, partial(full.solve, at))
                mine = cached(f"{tag}-own", VERSION, partial(own.solve, mu))
                answer = reduced.solve(at)
                found = errors(reduced, exact, answer)
                rows.append(
                    {
                        "patient": name,
                        "kind": kinds[name],
                        "point": j,
                        "coefficients": " ".join(f"{v:+.2f}" for v in raw),
                        "clipped": bool(np.any(raw != a)),
                        "left_out_rms_mm": 1e3 * projection.rms,
                        "left_out_max_mm": 1e3 * projection.largest,
                        "energy": found.energy,
                        "volume_change": found.volume_change,
                        "reference_inflation": abs(
                            answer.start.details["reference_volume"] - exact.start.details["reference_volume"]
                        )
                        / inflation(exact),
                        "shape_volume_change": _volume_change(exact, mine),
                        "shape_reference_inflation": abs(
                            exact.start.details["reference_volume"] - mine.start.details["reference_volume"]
                        )
                        / inflation(mine),
                        "shape_energy": _shape_energy(reduced, exact, mine),
                        "static_ms": 1e3 * statistics.median(static_seconds(shipped, [at] * 3)),
                        "static_newton": shipped.solve(at, times=[shipped.stepping.start]).start.details[
                            "newton_iterations"
                        ],
                        "full_s": exact.seconds,
                    }
                )
                r = rows[-1]
                say(
                    f"  {name} μ{j}: energy {r['energy']:.1e}, volume {r['volume_change']:.1e}, static "
                    f"{r['static_ms']:.1f} ms; shape: volume {r['shape_volume_change']:.1e}, energy {r['shape_energy']:.1e}"
                )
        per_patient_s = None
        if not args.quick:  # one patient's own build, the same recipe without the shape coefficients
            own = own_model(
                base,
                reference,
                without_similarity(
                    modes.reference, everyone.displacements[names.index(held[0])], modes.weights, "rigid"
                ),
            )
            tic = time.perf_counter()
            with Reductor(own, POD(args.size_k), TrainingSet(physical.sample(args.train, seed=0))) as per_patient:
                per_patient.reduce(ECSW(args.tau))
            per_patient_s = time.perf_counter() - tic
    summary = {
        "patients": len(names),
        "library": args.library,
        "held": args.held,
        "modes": args.modes,
        "deviations_mm": [1e3 * s for s in modes.deviations],
        "compactness": modes.compactness().tolist(),
        "leave_one_out_mm": (1e3 * loo).tolist(),
        "held_out_rms_mm": [
            float(np.sqrt(np.mean([representation[n][k].rms ** 2 for n in held]))) * 1e3
            for k in range(len(representation[held[0]]))
        ],
        "held_out_max_mm": [
            max(representation[n][k].largest for n in held) * 1e3 for k in range(len(representation[held[0]]))
        ],
        "registration_s": registration_s,
        "population_s": population_s,
        "per_patient_s": per_patient_s,
        "timings": timings,
        "dofs": dofs,
        "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
        "vectors": reduced.basis.size,
        "sampled_cells": reduced.sample.cells_per_type(mesh.comm)["cell"],
        # the static point's own work: the inverse motion's Newton on its sample, then the
        # breath's indicator on the breath's (each solver on its own cells of the shared body)
        "breath_cells": int(len(cells_of(reduced.sample))),
        "inverse_cells": int(len(cells_of(reduced.image.solver.sample))),
    }
    return rows, summary


def _volume_change(solution: Solution, reference: Solution) -> float:
    """The largest difference of two breaths' volume changes from their images, relative to
    the reference's largest change."""
    a = solution.outputs["volume"] - solution.start.details["imaged_volume"]
    b = reference.outputs["volume"] - reference.start.details["imaged_volume"]
    return float(np.abs(a - b).max() / np.abs(b).max())


def _shape_energy(reduced, template: Solution, own: Solution) -> float:
    """The two full models' states (one mesh topology, the same dof numbering) in the energy
    norm of the model at rest on the template, relative to the breath's largest change."""
    from lungmech.parallel.linalg import norms

    W, comm = reduced.energy_product, reduced.model.geometry.mesh.comm
    worst, change = 0.0, 0.0
    for x, y in zip(template.states, own.states):
        difference = np.column_stack([x - y, y - own.states[0]])
        found = norms(difference, W, comm)
        worst, change = max(worst, found[0]), max(change, found[1])
    return float(worst / change)


# --- The report ----------------------------------------------------------------------------------


def markdown(rows: list[dict], summary: dict, command: str, args) -> str:
    worst = {
        key: max(r[key] for r in rows)
        for key in (
            "energy",
            "volume_change",
            "reference_inflation",
            "shape_volume_change",
            "shape_energy",
            "shape_reference_inflation",
        )
    }
    static = statistics.median(r["static_ms"] for r in rows)
    full = statistics.median(r["full_s"] for r in rows)
    k = summary["modes"]

    def verdict(value: float, limit: float) -> str:
        return f"met ({value / limit:.2g} of it)" if value <= limit else f"**missed** ({value / limit:.2g}× over)"

    lines = [
        "# One reduced model for a population: the lung's shape as a parameter",
        "",
        f"{provenance(command)} {summary['patients']} synthetic patients ({', '.join(KINDS)}, in turn), "
        f"segmented at {args.spacing:g} mm; the bundled right lung mesh ({summary['cells']} cells, {summary['dofs']} "
        f"dofs) registered onto each ({summary['registration_s']:.1f} s a patient). Shape modes of the first "
        f"{summary['library']} (position and orientation removed, size kept); the last {summary['held']} held out. "
        f"The population model: the bundled breathing lung (imaged at end-expiration; c1, breath depth, posture) "
        f"over its 3 parameters and {k} shape coefficients (±{BOX:g} σ), on the library's mean shape, POD "
        f"({summary['vectors']} vectors) and ECSW (τ = {args.tau:g}, {summary['sampled_cells']} sampled cells) from "
        f"{args.train} Sobol' points. At each held-out patient, {args.points} physical points (Sobol', another seed) "
        "with the patient's coefficients (its projection, clipped to the box).",
        "",
        "## Targets",
        "",
        "| target | measured (worst over patients and points) | verdict |",
        "|---|---|---|",
        f"| energy norm ≤ 1 % (population model against the full model on χ_a(Ω₀); relative to the breath's largest change) | {worst['energy']:.1e} | {verdict(worst['energy'], 1e-2)} |",
        f"| volume ≤ 1e-3 of the breath's volume change | {worst['volume_change']:.1e} | {verdict(worst['volume_change'], 1e-3)} |",
        f"| static point ≤ 10 ms (median, on its body of sampled cells) | {static:.1f} ms | {verdict(static, 10.0)} |",
        "",
        f"A static point is the inverse motion's reduced Newton on its sample ({summary['inverse_cells']} cells, "
        f"{statistics.median(r['static_newton'] for r in rows):.0f} iterations median) and the breath's error "
        f"indicator on the breath's ({summary['breath_cells']} cells; cells with an exterior facet included).",
        "",
        f"The reference volume (the unloaded lung at μ) is within {worst['reference_inflation']:.1e} of the inflation "
        f"the inverse problem undoes. The full model takes {full:.1f} s a breath (median).",
        "",
        "## Shape representation (reported apart)",
        "",
        f"The full model on χ_a(Ω₀), a the patient's {k} coefficients, against the full model on the patient's own "
        f"registered mesh: breath volume change within {worst['shape_volume_change']:.1e} of the patient's, the state "
        f"within {worst['shape_energy']:.1e} in the energy norm, the reference within "
        f"{worst['shape_reference_inflation']:.1e} of the inflation. What the modes leave out of the held-out patients' "
        "shapes, against the number of modes (mm; RMS over the body, mass-weighted; the largest at a node), beside the "
        "library's leave-one-out error:",
        "",
        "| modes | held out: RMS [mm] | held out: largest [mm] | library leave-one-out RMS [mm] | σ of the mode [mm] |",
        "|---|---|---|---|---|",
    ]
    for m in range(len(summary["held_out_rms_mm"])):
        loo = summary["leave_one_out_mm"][m] if m < len(summary["leave_one_out_mm"]) else None
        sigma = summary["deviations_mm"][m - 1] if 0 < m <= len(summary["deviations_mm"]) else None
        lines.append(
            f"| {m} | {summary['held_out_rms_mm'][m]:.2f} | {summary['held_out_max_mm'][m]:.2f} | "
            f"{'—' if loo is None else f'{loo:.2f}'} | {'—' if sigma is None else f'{sigma:.2f}'} |"
        )
    lines += [
        "",
        "## Per patient",
        "",
        "| patient | kind | point | coefficients [σ] | left out: RMS, largest [mm] | energy | volume / change | "
        "reference / inflation | static [ms] | shape: volume change | shape: energy |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        clipped = " (clipped)" if r["clipped"] else ""
        lines.append(
            f"| {r['patient']} | {r['kind']} | {r['point']} | {r['coefficients']}{clipped} | "
            f"{r['left_out_rms_mm']:.2f}, {r['left_out_max_mm']:.2f} | {r['energy']:.1e} | {r['volume_change']:.1e} | "
            f"{r['reference_inflation']:.1e} | {r['static_ms']:.1f} | {r['shape_volume_change']:.1e} | {r['shape_energy']:.1e} |"
        )
    lines += ["", "## Offline", ""]
    parts = ", ".join(f"{part} {seconds:.0f} s" for part, seconds in summary["timings"].items())
    lines.append(f"- The population model, once: {summary['population_s']:.0f} s ({parts}).")
    if summary["per_patient_s"] is not None:
        n = summary["patients"]
        lines.append(
            f"- One patient's own model (the same recipe without the shape coefficients, on its registered mesh): "
            f"{summary['per_patient_s']:.0f} s; for the {n} patients, {n * summary['per_patient_s'] / 60:.0f} min, "
            f"{n * summary['per_patient_s'] / summary['population_s']:.1f}× the population's one build. Each new patient "
            f"then costs a registration ({summary['registration_s']:.1f} s) and no build."
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    m = np.arange(len(summary["held_out_rms_mm"]))
    left.plot(m, summary["held_out_rms_mm"], "o-", label="held out: RMS")
    left.plot(m, summary["held_out_max_mm"], "s--", label="held out: largest node")
    loo = summary["leave_one_out_mm"][: len(m)]
    left.plot(np.arange(len(loo)), loo, "^:", label="library: leave-one-out RMS")
    left.axvline(summary["modes"], color="grey", lw=0.8)
    left.set_xlabel("shape modes")
    left.set_ylabel("shape left out [mm]")
    left.set_title("What the modes leave out of a patient's lung")
    left.legend()
    patients_ = list(dict.fromkeys(r["patient"] for r in rows))
    x = np.arange(len(patients_))
    for offset, (key, label) in enumerate(
        (
            ("energy", "population model: energy norm"),
            ("volume_change", "population model: volume / change"),
            ("shape_volume_change", "shape representation: volume change"),
        )
    ):
        values = [max(r[key] for r in rows if r["patient"] == p) for p in patients_]
        right.bar(x + 0.27 * (offset - 1), values, 0.27, label=label)
    right.axhline(1e-2, color="C0", lw=0.8, ls="--")
    right.axhline(1e-3, color="C1", lw=0.8, ls="--")
    right.set_yscale("log")
    right.set_xticks(x, patients_, rotation=30, ha="right")
    right.set_ylabel("relative error (worst over points)")
    right.set_title("Held-out patients")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def command_line(args) -> str:
    return "python benchmarks/population.py" + (" --quick" if args.quick else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="4 patients, 2 modes, h = 40 mm: a smoke run")
    args = parser.parse_args()
    full_run = dict(size="default", spacing=2.5, library=20, held=6, modes=3, train=32, points=2, size_k=30, tau=1e-4)
    quick = dict(size="40", spacing=5.0, library=3, held=1, modes=2, train=4, points=1, size_k=6, tau=1e-2)
    for key, value in (quick if args.quick else full_run).items():
        setattr(args, key, value)
    started = time.perf_counter()
    rows, summary = case(args)
    stem = "population_quick" if args.quick else "population"
    write_results(RESULTS, stem, rows, markdown(rows, summary, command_line(args), args))
    plot(rows, summary, RESULTS / f"{stem}.png")
    say(f"written {RESULTS / stem}.md, .csv, .png in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
