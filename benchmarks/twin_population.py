"""A new patient on a population's model against a model of its own, on the twin experiments.

    python benchmarks/twin_population.py            # 2 right-lung phantoms × supine, prone, both × noise 0, 10 %
    python benchmarks/twin_population.py --quick    # 1 phantom, supine, no noise, a library of 3: the suite's smoke run

The synthetic patients, their images and their estimate are those of ``benchmarks/twin.py``
(the full model on finer cells at known parameters, imaged as segmentations at CT-like voxels;
the estimate registers the *generic* right lung onto the end-expiration image). Each patient
is personalised two ways on the same images, with the same noise:

* **its own model** (``lungmech personalise``): a reduced model built for the registered mesh
  and checked against the full model and the mesh refined once, per pair;
* **the population's model** (``lungmech personalise --model``): one reduced model built
  beforehand, once, over the parameters and the first ``--modes`` shape coefficients (±2
  standard deviations) of a library of right lungs (``benchmarks/population.py``'s patients:
  phantoms of varied shape, warped phantoms and lungs of another generator; the twin's
  patients are not among them), the template's surface nodes its probes; per pair, a
  registration, the mapping's projection on the modes and the surface fit of the
  coefficients and the pose, and a check against the full model on χ_a(Ω₀).

Reported: each parameter's error (% of the truth) both ways without noise and at 10 % noise
(mean absolute error over the replicates and the coverage of the 95 % intervals), the same with
the shape coefficients estimated jointly, and the time of each step (registration, the pair's
own offline build, the check, the estimate) beside the population's one offline build.
Writes results/twin_population{,_quick}.{md,csv,png}. One rank.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import machine
import numpy as np
from machine import provenance, say, write_results
from population import BOX, patients
from twin import GENERIC, PHANTOMS, POSITIONS, Plan, one_estimate, patient_images, scene_of

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app import scene as scenes

HOWS = ("own", "population")


@dataclass(frozen=True)
class Setup:
    """What a run measures: the twin's ``plan`` (its patients, images and noise) and the
    population: a library of ``library`` right lungs at ``spacing`` m voxels, ``modes``
    shape coefficients, a model from ``train`` Sobol' points of at most ``size`` vectors,
    hyper-reduced by ECSW at ``tau``."""

    plan: Plan
    library: int
    spacing: float
    modes: int
    train: int
    size: int
    tau: float
    phantoms: tuple[str, ...]
    joint: bool  # also estimate the shape coefficients with the rest

    @classmethod
    def of(cls, quick: bool) -> Setup:
        if quick:
            plan = replace(Plan.of(True, None, 1), noises=(0.0,), correlated=0.0)
            return cls(plan, 3, 0.005, 2, 4, 6, 1e-2, tuple(PHANTOMS)[:1], False)
        plan = replace(Plan.of(False, None, 5), noises=(0.0, 0.1), biases=(), flips=(), correlated=0.0)
        right = tuple(name for name, shape in PHANTOMS.items() if shape["side"] == "right")
        return cls(plan, 16, 0.0025, 3, 24, 16, 1e-4, right, True)


def population_model(setup: Setup, folder: Path):
    """The population's scene and its reduced model (built once, timed): the library's
    registrations, its modes (pose "rigid": the size kept) and the build."""
    from mpi4py import MPI

    from lungmech.app.reduce import build, load
    from lungmech.app.template import with_surface_probes
    from lungmech.registration.library import mapping_library

    plan = setup.plan
    base = scene_of({"side": "right"} | GENERIC, plan.estimate_h, plan.zones)
    images, kinds = patients(setup.library, 0, setup.spacing, seed=11)
    reference = scenes.build_geometry(base.geometry, MPI.COMM_WORLD)
    tic = time.perf_counter()
    library = mapping_library(reference.mesh, images)
    registration = time.perf_counter() - tic
    modes = library.modes("rigid")
    modes.save(folder / "modes.npz")
    table = dict(base.table) | {"geometry": base.table["geometry"] | {"shape_modes": "modes.npz"}}
    table["parameters"] = dict(table["parameters"]) | {
        f"shape_{k}": {"target": f"shape.mode_{k}", "range": [-BOX, BOX]} for k in range(1, setup.modes + 1)
    }
    scene = scenes.parse(table, folder=folder)
    say(f"library: {len(images)} right lungs, modes σ = {', '.join(f'{1e3 * s:.1f}' for s in modes.deviations[:6])} mm")
    tic = time.perf_counter()
    summary = build(
        with_surface_probes(scene, MPI.COMM_WORLD),
        folder / "population.npz",
        size=setup.size,
        samples=setup.train,
        hyper="ecsw",
        hyper_tolerance=setup.tau,
        cache=folder / "cache",  # a cache of its own: every training solve is done (and timed) here
    )
    offline = time.perf_counter() - tic
    say(f"population model: {summary['size']} vectors, built in {offline:.0f} s")
    facts = {
        "library": len(images),
        "kinds": {kind: list(kinds.values()).count(kind) for kind in set(kinds.values())},
        "deviations_mm": [1e3 * s for s in modes.deviations[: setup.modes]],
        "library_registration_s": registration,
        "population_offline_s": offline,
        "vectors": summary["size"],
        "dofs": summary["dofs"],
    }
    return scene, load(folder / "population.npz"), facts


def phantom_rows(setup: Setup, phantom: str, scene, reduced, source: Path, timings: list[dict]) -> list[dict]:
    """Every estimate of one synthetic patient, both ways: without noise and with the noise's
    replicates, for each set of positions; and with its shape estimated too."""
    from lungmech.app import population
    from lungmech.app.personalise import Pair, checked_request, prepare
    from lungmech.twin.fit import Fit, estimate
    from lungmech.twin.synthetic import surface_noise

    plan = setup.plan
    shape = PHANTOMS[phantom]
    say(phantom, ": the patient's images")
    needed = sorted({p for label in plan.positions for p in POSITIONS[label]})
    images = patient_images(shape, plan, needed)
    own_scene = scene_of({"side": shape["side"]} | GENERIC, plan.estimate_h, plan.zones)
    shapes = tuple(population.shape_names(scene))
    prepared: dict[str, dict] = {how: {} for how in HOWS}
    for position in needed:
        pairs = [Pair(*images[position], position)]
        say(phantom, position, ": its own model (registration, build, check)")
        prepared["own"][position] = prepare(own_scene, pairs, plan.setting())
        say(phantom, position, ": the population's model (registration, shape, check)")
        names, end = checked_request(scene, tuple(pairs), plan.setting())
        prepared["population"][position] = population.prepare(scene, reduced, pairs, plan.setting(), names, end, source)
        for how in HOWS:
            patient = prepared[how][position]
            timings.append({"phantom": phantom, "position": position, "how": how} | patient.seconds)
            if how == "population":
                registered = patient.registered[0]
                timings[-1] |= {
                    "shape": registered["shape_coefficients"],
                    "surface_rms_mm": 1e3 * registered["shape_surface_rms"],
                    "left_out_rms_mm": 1e3 * registered["shape_left_out_rms"],
                }
    rows = []
    for label in plan.positions:
        used = POSITIONS[label]
        for how in HOWS:
            fit = Fit([view for p in used for view in prepared[how][p].views], plan.names)
            errors = np.hstack([prepared[how][p].errors for p in used])
            for noise in plan.noises:
                for replicate in range(1 if noise == 0 else plan.replicates):
                    offset = surface_noise(fit, noise, 1000 * replicate + int(1000 * noise)) if noise else None
                    rows.append(
                        {"phantom": phantom, "positions": label, "how": how, "noise [%]": 100 * noise}
                        | {"replicate": replicate}
                        | one_estimate(fit, errors, offset, plan.truth)
                    )
        if setup.joint:  # without noise: the shape coefficients fitted with the rest
            # the population's views, their shape no longer fixed at the registration's
            views = [
                replace(view, fixed={n: v for n, v in view.fixed.items() if n not in shapes})
                for p in used
                for view in prepared["population"][p].views
            ]
            found = estimate(Fit(views, (*plan.names, *shapes)))
            registered = prepared["population"][used[0]].registered[0]["shape_coefficients"]
            rows.append(
                {"phantom": phantom, "positions": label, "how": "joint", "noise [%]": 0.0, "replicate": 0}
                | {"evaluations": found.evaluations, "seconds": found.seconds}
                | {f"{n} [%]": 100 * (found.values[n] - plan.truth[n]) / plan.truth[n] for n in plan.names}
                | {f"{n} change [sd]": found.values[n] - a for n, a in zip(shapes, registered)}
            )
    return rows


def markdown(rows: list[dict], timings: list[dict], facts: dict, setup: Setup, command: str) -> str:
    plan = setup.plan
    names = plan.names
    lines = [
        "# A new patient on a population's model, against a model of its own (twin experiments)",
        "",
        provenance(command),
        "",
        f"The population: {facts['library']} right lungs ("
        + ", ".join(f"{count} {kind}" for kind, count in sorted(facts["kinds"].items()))
        + f") at {1e3 * setup.spacing:g} mm voxels, registered from the generic right lung "
        f"({1e3 * plan.estimate_h:.0f} mm cells, {facts['dofs']} dofs) in {facts['library_registration_s']:.0f} s; "
        f"its first {setup.modes} modes (σ = "
        + ", ".join(f"{s:.1f}" for s in facts["deviations_mm"])
        + f" mm) ±{BOX:g} σ with the parameters: one model of {facts['vectors']} vectors (ECSW, τ = {setup.tau:g}) "
        f"from {setup.train} training points, built once in **{facts['population_offline_s']:.0f} s**. "
        f"The patients: the twin experiments' ({', '.join(setup.phantoms)}; the truth on "
        f"{1e3 * plan.truth_h:.0f} mm cells, imaged at {1e3 * plan.voxel:.0f} mm voxels), none of them in the "
        "library. Errors in % of the truth. Validated on synthetic patients only.",
        "",
        "## Without noise",
        "",
        "| phantom | positions | " + " | ".join(f"{n} [%] own | {n} [%] population" for n in names) + " |",
        "|---|---|" + "---|---|" * len(names),
    ]
    for phantom in setup.phantoms:
        for label in plan.positions:
            chosen = {
                r["how"]: r for r in rows if (r["phantom"], r["positions"], r["noise [%]"]) == (phantom, label, 0)
            }
            cells = " | ".join(f"{chosen['own'][f'{n} [%]']:+.2f} | {chosen['population'][f'{n} [%]']:+.2f}" for n in names)  # fmt: skip
            lines.append(f"| {phantom} | {label} | {cells} |")
    noisy = [level for level in sorted({r["noise [%]"] for r in rows}) if level > 0]
    for level in noisy:
        lines += [
            "",
            f"## At {level:g} % noise ({plan.replicates} replicates per cell)",
            "",
            "Mean absolute error, and the coverage of the truth by the 95 % intervals (pooled over the parameters).",
            "",
            "| phantom | positions | how | " + " | ".join(f"abs {n} [%]" for n in names) + " | coverage |",
            "|---|---|---|" + "---|" * len(names) + "---|",
        ]
        for phantom in setup.phantoms:
            for label in plan.positions:
                for how in HOWS:
                    cell = [r for r in rows if (r["phantom"], r["positions"], r["how"], r["noise [%]"]) == (phantom, label, how, level)]  # fmt: skip
                    held = [r[f"{n} covered"] for r in cell for n in names if r[f"{n} covered"] is not None]
                    errors = " | ".join(f"{statistics.mean(abs(r[f'{n} [%]']) for r in cell):.2f}" for n in names)
                    lines.append(f"| {phantom} | {label} | {how} | {errors} | {_share(held)} |")
    joint = [r for r in rows if r["how"] == "joint" and r["noise [%]"] == 0]
    if joint:
        lines += [
            "",
            "## The shape estimated too (without noise)",
            "",
            "The shape coefficients fitted with the parameters to the breath's data as well (from the mean "
            "shape): their difference from the registration's, in standard deviations of the library.",
            "",
            "| phantom | positions | " + " | ".join(f"{n} [%]" for n in names) + " | shape a − registered [sd] |",
            "|---|---|" + "---|" * len(names) + "---|",
        ]
        for r in joint:
            change = ", ".join(f"{v:+.2f}" for k, v in r.items() if k.endswith(" change [sd]"))
            lines.append(f"| {r['phantom']} | {r['positions']} | " + " | ".join(f"{r[f'{n} [%]']:+.2f}" for n in names) + f" | {change} |")  # fmt: skip
    lines += _times(rows, timings, facts, setup)
    return "\n".join(lines) + "\n"


def _share(held: list[bool]) -> str:
    return f"{sum(held) / len(held):.2f} of {len(held)}" if held else "no interval"


def _times(rows: list[dict], timings: list[dict], facts: dict, setup: Setup) -> list[str]:
    lines = [
        "",
        "## Times (s, one rank)",
        "",
        "Per pair. The own model's check is against the full model"
        + (" and the mesh refined once" if setup.plan.setting().mesh_check else "")
        + "; the population's registration holds the projection and the surface fit. The population's model "
        f"itself: built once, {facts['population_offline_s']:.0f} s, for every patient.",
        "",
        "| phantom | position | how | registration | offline | check | shape a | surface RMS [mm] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in timings:
        shape = " ".join(f"{v:+.2f}" for v in t["shape"]) if "shape" in t else ""
        rms = f"{t['surface_rms_mm']:.2f}" if "surface_rms_mm" in t else ""
        lines.append(
            f"| {t['phantom']} | {t['position']} | {t['how']} | {t['registration']:.1f} | {t['offline']:.1f} | "
            f"{t['check']:.1f} | {shape} | {rms} |"
        )
    for how in HOWS:
        seconds = [r["seconds"] for r in rows if r["how"] == how]
        lines.append("")
        lines.append(
            f"The estimate on the {how} model: median {np.median(seconds):.2f} s, largest {np.max(seconds):.2f} s."
        )
    own = sum(t["registration"] + t["offline"] + t["check"] for t in timings if t["how"] == "own")
    mine = sum(t["registration"] + t["offline"] + t["check"] for t in timings if t["how"] == "population")
    pairs = sum(t["how"] == "own" for t in timings)
    lines += [
        "",
        f"Before the estimates, {pairs} pairs: {own:.0f} s with a model each, {mine:.0f} s on the population's "
        f"({own / mine:.1f}× less); with the population's build counted, {mine + facts['population_offline_s']:.0f} s.",
    ]
    return lines


def plot(rows: list[dict], timings: list[dict], setup: Setup, path: Path) -> None:
    """Left: each parameter's absolute error without noise and (mean) with noise, own model
    beside the population's, over every phantom and set of positions. Right: each pair's time
    before its estimate, by step, both ways."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = setup.plan.names
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.4))
    levels = sorted({r["noise [%]"] for r in rows})
    width = 0.8 / (2 * len(levels))
    for j, level in enumerate(levels):
        for k, (how, colour) in enumerate(zip(HOWS, ("tab:blue", "tab:orange"))):
            means = [
                np.mean([abs(r[f"{n} [%]"]) for r in rows if r["how"] == how and r["noise [%]"] == level])
                for n in names
            ]
            x = np.arange(len(names)) + (2 * j + k - len(levels) + 0.5) * width
            left.bar(x, means, width, color=colour, alpha=1.0 - 0.4 * j, label=f"{how}, noise {level:g} %")
    left.set_xticks(np.arange(len(names)), names)
    left.set_ylabel("mean abs error [% of the truth]")
    left.set_title("every phantom and set of positions", fontsize=9)
    left.legend(fontsize=7)
    left.grid(alpha=0.3, axis="y")
    labels = [f"{t['phantom'].split()[0]}\n{t['position']}\n{t['how'][:3]}." for t in timings]
    bottom = np.zeros(len(timings))
    for step, colour in (("registration", "tab:green"), ("offline", "tab:red"), ("check", "tab:purple")):
        values = np.array([t[step] for t in timings])
        right.bar(labels, values, bottom=bottom, color=colour, label=step)
        bottom += values
    right.set_ylabel("time before the estimate [s]")
    right.set_title("per pair, one rank (the population's build apart, once)", fontsize=9)
    right.tick_params(axis="x", labelsize=7)
    right.legend(fontsize=7)
    fig.suptitle("A new patient: a model of its own against the population's (synthetic patients)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="1 phantom, supine, no noise, a library of 3: a smoke run")
    args = parser.parse_args()
    setup = Setup.of(args.quick)
    started = time.perf_counter()
    rows, timings = [], []
    with tempfile.TemporaryDirectory() as folder:
        scene, reduced, facts = population_model(setup, Path(folder))
        for phantom in setup.phantoms:
            rows += phantom_rows(setup, phantom, scene, reduced, Path(folder) / "population.npz", timings)
    command = "python benchmarks/twin_population.py" + (" --quick" if args.quick else "")
    stem = "twin_population_quick" if args.quick else "twin_population"
    write_results(machine.RESULTS, stem, rows, markdown(rows, timings, facts, setup, command))
    plot(rows, timings, setup, machine.RESULTS / f"{stem}.png")
    say(f"written {machine.RESULTS / stem}.md, .csv, .png in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
