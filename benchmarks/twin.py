"""Twin experiments without an inverse crime: a lung's parameters estimated from synthetic images.

    python benchmarks/twin.py            # 3 phantoms × supine, prone, both × noise 0–40 % (about an hour)
    python benchmarks/twin.py --quick    # 1 phantom, supine, noise 0 and 10 %, a few replicates (< 1 min)

Synthetic patients: lungmech's full model of the imaged lung (poromechanics, the weight balanced
by the pleural pressure, a stiffer base: two stiffness zones by height) on a finer mesh than the
estimate's, each of three shapes (the generic right lung, a taller and narrower right lung, a
left lung with its cardiac notch), at known parameters, imaged supine and prone as
segmentations (end-expiration, end-inspiration) at CT-like voxels. The estimate registers the
*generic* lung of the patient's side onto each end-expiration image (the reference never has
the patient's shape), builds that pair's hyper-reduced model and checks it against the full
model and the lung refined once (:func:`lungmech.app.personalise.prepare`), then fits:

* **this pipeline**: bounded least squares ('trf') with the reduced model's exact
  sensitivities, the Laplace intervals in the parameters' box widened by the model's error as a
  bias;
* **the published approach**: Nelder–Mead on the same misfit (≤ 150 evaluations), on the full
  model (full solves and wall time) and, for the error-against-noise bands, on the reduced one.

The published protocol: Gaussian noise of 0, 5, 10, 20, 40 % of the surface's RMS motion on
every surface datum, replicates per level (supine, prone and both; every phantom), and one
fixed parameter biased (the tissue's density, 80–120 %, in the estimating model). Reported:
each parameter's error (% of the truth), the 95 % intervals' coverage of the truth (pooled and
per cell), the gap (the full model on the estimate's mesh fitted to the same images), solves
and seconds. Writes results/twin{,_quick}.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import machine
import numpy as np
from machine import provenance, read_results, say, write_results  # benchmarks/ is the script folder, first on sys.path

BUNDLED = "lung_personalise.toml"  # the physics of every patient and estimate: the bundled scene's
ZONE = {  # a stiffer base: the skeleton's stiffness below a third of the lung's height (a smooth step)
    "target": "material.c1",
    "range": [100.0, 800.0],
    "scale": "log",
}
GENERIC = {"height": 0.24, "width": 0.11, "depth": 0.17}
PHANTOMS = {
    "generic right": {"side": "right"} | GENERIC,
    "tall narrow right": {"side": "right", "height": 0.27, "width": 0.10, "depth": 0.16},
    "left, cardiac notch": {"side": "left"} | GENERIC,
}
TRUTH = {"stiffness": 200.0, "stiffness_base": 400.0, "breath": 1.15}
POSITIONS = {"supine": ("supine",), "prone": ("prone",), "both": ("supine", "prone")}
DENSITY = 315.0  # kg/m³: the tissue's (lung_personalise's)
SPECIAL = {"density [%]", "correlation [mm]", "flipped [%]"}  # the rows apart from the protocol's noise
LEVEL = 0.95


def scene_of(shape: dict, h: float, zones: int, density: float = DENSITY):
    """The bundled scene with a lung of ``shape`` at mesh size ``h`` (m), ``zones`` stiffness
    zones (2: a base below a third of the height), the tissue at ``density`` (kg/m³)."""
    import copy
    import tomllib
    from importlib import resources

    from lungmech.app import scene as scenes

    table = tomllib.loads((resources.files("lungmech.scenes") / BUNDLED).read_text())
    table = copy.deepcopy(table)
    table["geometry"] |= shape | {"mesh_size": h}
    next(load for load in table["loads"] if load["type"] == "gravity")["density"] = density
    if zones == 2:
        base = {"normal": [0.0, 0.0, 1.0], "position": round(shape["height"] / 3, 4), "width": 0.01}
        table["parameters"]["stiffness_base"] = ZONE | {"region": base}
    return scenes.parse(table)


def patient_images(shape: dict, plan: Plan, positions: list[str]) -> dict:
    """The synthetic patient's pairs of segmentations in ``positions`` (its full model on
    ``plan.truth_h`` cells, voxels of ``plan.voxel`` m)."""
    from lungmech.app.run import full_order_model
    from lungmech.twin.synthetic import image_pair

    truth = full_order_model(scene_of(shape, plan.truth_h, plan.zones), start="inverse_motion")
    values = {name: value for name, value in TRUTH.items() if name in truth.parameters}
    return {
        position: image_pair(truth, values | {"posture": angle}, 1.0, plan.voxel)
        for position, angle in (("supine", -90.0), ("prone", 90.0))
        if position in positions
    }


def one_estimate(fit, error, offset, truth: dict) -> dict:
    """This pipeline's estimate and intervals on ``fit`` with the data ``offset``."""
    from lungmech.twin.fit import estimate
    from lungmech.twin.uncertainty import laplace

    found = estimate(fit, offset=offset)
    intervals = laplace(found, fit, error, LEVEL).intervals
    row: dict = {"evaluations": found.evaluations, "seconds": found.seconds}
    for name in fit.names:
        interval = intervals[name]
        row[f"{name} [%]"] = 100 * (found.values[name] - truth[name]) / truth[name]
        row[f"{name} covered"] = None if interval.low is None else bool(interval.low <= truth[name] <= interval.high)
        row[f"{name} noise [unit]"], row[f"{name} bias [unit]"] = interval.noise, interval.bias  # (half-widths)
    return row


def nelder_mead(fit, offset, truth: dict, most: int) -> dict:
    """The published approach on ``fit``: Nelder–Mead on ½‖r‖² in the unit box from the
    defaults, at most ``most`` evaluations (each a solve of every view's model)."""
    from scipy.optimize import minimize

    shift = np.zeros(fit.rows) if offset is None else offset
    start = fit.unit({p.name: p.default for p in fit.parameters})
    before = fit.evaluations
    tic = time.perf_counter()
    result = minimize(
        lambda theta: 0.5 * float(np.sum((fit.residual(theta) + shift) ** 2)),
        start,
        method="Nelder-Mead",
        bounds=[(0.0, 1.0)] * len(start),
        options={"maxfev": most, "xatol": 1e-4, "fatol": 1e-14},
    )
    values = fit.values(np.clip(result.x, 0.0, 1.0))
    row: dict = {"evaluations": fit.evaluations - before, "seconds": time.perf_counter() - tic}
    for name in fit.names:
        row[f"{name} [%]"] = 100 * (values[name] - truth[name]) / truth[name]
    return row


@dataclass(frozen=True)
class Plan:
    """What a run measures: the full protocol, or the quick case the suite runs."""

    quick: bool
    zones: int
    replicates: int
    truth_h: float = 0.015  # m: the synthetic patients' mesh
    estimate_h: float = 0.03  # m: the estimate's reference lung
    voxel: float = 0.002  # m: the segmentations' voxels
    phantoms: tuple[str, ...] = tuple(PHANTOMS)
    positions: tuple[str, ...] = tuple(POSITIONS)
    noises: tuple[float, ...] = (0.0, 0.05, 0.1, 0.2, 0.4)
    biases: tuple[float, ...] = (0.8, 0.9, 1.1, 1.2)  # the density assumed, of the truth's
    flips: tuple[float, ...] = (0.25, 0.5)  # fractions of the segmentations' surface voxels flipped
    correlated: float = 0.02  # m: the correlation length of the correlated noise (0: none)
    nelder_mead: tuple[int, int] = (150, 150)  # its most evaluations: on the reduced model, the full one
    nelder_mead_replicates: int = 5
    full_noises: tuple[float, ...] = (0.0, 0.1)  # where both methods run on the full model too

    @classmethod
    def of(cls, quick: bool, zones: int | None, replicates: int | None) -> Plan:
        if not quick:
            return cls(False, zones or 2, replicates or 12)
        return cls(
            True, zones or 1, replicates or 2, 0.025, 0.04, 0.004, tuple(PHANTOMS)[:1], ("supine",), (0.0, 0.1), (),
            (), 0.0, (20, 4), 1, (0.0,),
        )  # fmt: skip

    @property
    def names(self) -> tuple[str, ...]:
        return ("stiffness", "stiffness_base", "breath") if self.zones == 2 else ("stiffness", "breath")

    @property
    def truth(self) -> dict[str, float]:
        return {name: TRUTH[name] for name in self.names}

    def setting(self):
        from lungmech.app.personalise import Setting

        quick = self.quick
        return Setting(estimate=self.names, training=4 if quick else 10, size=6 if quick else 12, mesh_check=not quick)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--quick", action="store_true", help="1 phantom, supine, noise 0 and 10 %%, 2 replicates, no flips or bias"
    )
    parser.add_argument("--replicates", type=int, default=None, help="per (phantom, positions, noise) (default 12)")
    parser.add_argument("--zones", type=int, choices=(1, 2), default=None, help="stiffness zones (default 2)")
    parser.add_argument("--replot", action="store_true", help="draw the plot again from the results' CSV")
    args = parser.parse_args()
    plan = Plan.of(args.quick, args.zones, args.replicates)
    if args.replot:  # (the markdown needs the timings, which the CSV does not hold)
        stem = "twin_quick" if plan.quick else "twin"
        rows = [_typed(row) for row in read_results(machine.RESULTS / f"{stem}.csv")]
        plot(rows, plan.names, machine.RESULTS / f"{stem}.png")
        return
    rows, timings = [], []
    for index, phantom in enumerate(plan.phantoms):
        rows += phantom_rows(plan, phantom, first=index == 0, timings=timings)
    command = "python benchmarks/twin.py" + (" --quick" if plan.quick else "")
    stem = "twin_quick" if plan.quick else "twin"
    write_results(machine.RESULTS, stem, rows, markdown(rows, timings, plan, command))
    plot(rows, plan.names, machine.RESULTS / f"{stem}.png")
    print((machine.RESULTS / f"{stem}.md").read_text())


def phantom_rows(plan: Plan, phantom: str, first: bool, timings: list[dict]) -> list[dict]:
    """Every estimate of one synthetic patient: the protocol's noise for each set of positions
    (and, for the first phantom, Nelder–Mead beside it, the segmentations' noise and the
    biased density)."""
    from lungmech.app.personalise import Pair, prepare
    from lungmech.twin.fit import Fit, estimate
    from lungmech.twin.synthetic import flip_boundary

    shape = PHANTOMS[phantom]
    say(phantom, ": the patient's images")
    needed = sorted({p for label in plan.positions for p in POSITIONS[label]})
    images = patient_images(shape, plan, needed)
    generic = {"side": shape["side"]} | GENERIC  # the reference lung: never the patient's shape
    patients = {}
    for position in needed:
        say(phantom, position, ": registration, reduced model, check")
        patients[position] = prepare(
            scene_of(generic, plan.estimate_h, plan.zones), [Pair(*images[position], position)], plan.setting()
        )
        timings.append({"phantom": phantom, "positions": position} | patients[position].seconds)  # fmt: skip
    rows = []
    for label in plan.positions:
        used = POSITIONS[label]
        fit = Fit([view for p in used for view in patients[p].views], plan.names)
        full = Fit([view for p in used for view in patients[p].full_views], plan.names)
        errors = np.hstack([patients[p].errors for p in used])
        gap = estimate(full)  # the full model on the estimate's mesh, fitted to the same images
        gaps = {f"{n} gap [%]": 100 * (gap.values[n] - plan.truth[n]) / plan.truth[n] for n in plan.names}
        common = {"phantom": phantom, "positions": label}
        rows += [common | row for row in protocol(plan, fit, full, errors, gaps, first and label == "supine")]
    alike = {"phantom": phantom, "positions": "supine", "noise [%]": 0.0, "replicate": 0, "method": "trf, reduced"}
    for fraction in plan.flips if first else ():  # noise on the segmentations themselves
        say(phantom, f"{100 * fraction:.0f} % of the surface voxels flipped")
        noisy = [flip_boundary(image, fraction, seed=k) for k, image in enumerate(images["supine"])]
        flipped = prepare(scene_of(generic, plan.estimate_h, plan.zones), [Pair(*noisy, "supine")], plan.setting())
        rows.append(
            alike | {"flipped [%]": 100 * fraction} | one_estimate(flipped.fit(), flipped.errors, None, plan.truth)
        )
    for bias in plan.biases if first else ():  # the density assumed wrong in the estimating model
        say(phantom, f"density at {100 * bias:.0f} %")
        scene = scene_of(generic, plan.estimate_h, plan.zones, DENSITY * bias)
        biased = prepare(scene, [Pair(*images["supine"], "supine")], plan.setting())
        rows.append(alike | {"density [%]": 100 * bias} | one_estimate(biased.fit(), biased.errors, None, plan.truth))
    return rows


def protocol(plan: Plan, fit, full, error, gaps: dict, beside: bool) -> list[dict]:
    """The published protocol on one set of images: each noise level's replicates estimated
    by this pipeline; ``beside``: Nelder–Mead on the reduced model too, and both methods on the
    full model at ``plan.full_noises``; then noise correlated along the surface."""
    from lungmech.twin.synthetic import surface_noise

    rows = []
    for noise in plan.noises:
        say(f"  noise {100 * noise:.0f} %")
        for replicate in range(1 if noise == 0 else plan.replicates):
            offset = surface_noise(fit, noise, 1000 * replicate + int(1000 * noise)) if noise else None
            common = {"noise [%]": 100 * noise, "replicate": replicate}
            rows.append(common | {"method": "trf, reduced"} | one_estimate(fit, error, offset, plan.truth) | gaps)
            if beside and replicate < plan.nelder_mead_replicates:  # (each up to 150 solves: one cell only)
                rows.append(
                    common
                    | {"method": "Nelder–Mead, reduced"}
                    | nelder_mead(fit, offset, plan.truth, plan.nelder_mead[0])
                )
                if noise in plan.full_noises:
                    rows.append(
                        common
                        | {"method": "Nelder–Mead, full"}
                        | nelder_mead(full, offset, plan.truth, plan.nelder_mead[1])
                    )
                    rows.append(common | {"method": "trf, full"} | one_estimate(full, error, offset, plan.truth))
    if plan.correlated:
        say(f"  noise 10 %, correlated over {1e3 * plan.correlated:.0f} mm")
        for replicate in range(plan.replicates):
            offset = surface_noise(fit, 0.1, 7000 + replicate, correlation=plan.correlated)
            common = {"noise [%]": 10.0, "replicate": replicate, "method": "trf, reduced"}
            rows.append(
                common | {"correlation [mm]": 1e3 * plan.correlated} | one_estimate(fit, error, offset, plan.truth)
            )
    return rows  # fmt: skip


def _typed(row: dict) -> dict:
    """A CSV row as the run made it: "True"/"False" back to booleans, an empty "covered" cell
    None (no interval), other empty cells dropped (the columns of other rows)."""
    booleans = {"True": True, "False": False}
    return {
        key: booleans.get(value, value) if isinstance(value, str) else value
        for key, value in row.items()
        if value is not None or key.endswith(" covered")
    }


def _held(covered: bool | None) -> str:
    return "no interval" if covered is None else ("yes" if covered else "no")


def _mean(values) -> float:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else float("nan")


def coverage(rows: list[dict], names, noise: float | None = None, **where) -> tuple[float, int, int]:
    """(fraction of intervals holding the truth, intervals, estimates without one) of this
    pipeline's reduced-model rows at ``noise`` (all noisy levels when None) matching ``where``."""
    chosen = [
        r
        for r in rows
        if r["method"] == "trf, reduced"
        and not SPECIAL & set(r)
        and (r["noise [%]"] > 0 if noise is None else r["noise [%]"] == 100 * noise)
        and all(r[k] == v for k, v in where.items())
    ]
    held = [r[f"{n} covered"] for r in chosen for n in names if f"{n} covered" in r]
    given = [h for h in held if h is not None]
    return (float(np.mean(given)) if given else float("nan"), len(given), len(held) - len(given))


def markdown(rows: list[dict], timings: list[dict], plan: Plan, command: str) -> str:
    names = plan.names
    lines = [
        "# Twin experiments: a lung's parameters from synthetic images",
        "",
        provenance(command),
        "",
        f"Truth: the full model on {1e3 * plan.truth_h:.0f} mm cells ({plan.zones} stiffness zone"
        f"{'s' if plan.zones > 1 else ''}: " + ", ".join(f"{n} = {TRUTH[n]:g}" for n in names) + "), imaged at "
        f"{1e3 * plan.voxel:.0f} mm voxels; the estimate registers the generic lung of the patient's side "
        f"({1e3 * plan.estimate_h:.0f} mm cells) onto the end-expiration image. Errors in % of the truth; the gap is "
        "the full model on the estimate's mesh fitted to the same images (what the discretisation and the "
        "registration leave, whatever the reduction). Validated on synthetic patients only.",
        *_noise_free(rows, names),
        *_coverage(rows, names),
        *_side_by_side(rows, names),
        *_correlated(rows, names),
        *_apart(rows, names, "flipped [%]", "Noise on the segmentations: surface voxels flipped (both images), supine"),
        *_apart(rows, names, "density [%]", "A fixed parameter biased: the tissue's density in the estimating model, supine"),
        *_times(rows, timings),
    ]  # fmt: skip
    return "\n".join(lines) + "\n"


def _protocol(rows: list[dict], method: str = "trf, reduced") -> list[dict]:
    """The rows of the protocol's noise (not the correlated, flipped or biased ones)."""
    return [r for r in rows if r["method"] == method and not SPECIAL & set(r)]


def _noise_free(rows: list[dict], names) -> list[str]:
    lines = [
        "",
        "## Without noise",
        "",
        "| phantom | positions | " + " | ".join(f"{n} [%] | gap [%]" for n in names) + " | within gap + 1 % |",
        "|---|---|" + "---|---|" * len(names) + "---|",
    ]
    for r in _protocol(rows):
        if r["noise [%]"] == 0:
            cells = " | ".join(f"{r[f'{n} [%]']:+.2f} | {r[f'{n} gap [%]']:+.2f}" for n in names)
            within = all(abs(r[f"{n} [%]"]) <= abs(r[f"{n} gap [%]"]) + 1.0 for n in names)
            lines.append(f"| {r['phantom']} | {r['positions']} | {cells} | {'yes' if within else 'no'} |")
    return lines


def _coverage(rows: list[dict], names) -> list[str]:
    lines = [
        "",
        f"## Coverage of the nominal {100 * LEVEL:.0f} % intervals under noise",
        "",
        "Pooled over phantoms, positions and parameters; an estimate at a bound of its range has no interval "
        "(counted apart). Noise: Gaussian on every surface datum, its standard deviation the given fraction of "
        "the surface's RMS observed motion.",
        "",
        "| noise [%] | coverage | intervals | without one | lowest cell (positions, parameter) |",
        "|---|---|---|---|---|",
    ]
    positions = list(dict.fromkeys(r["positions"] for r in rows))
    for level in sorted({r["noise [%]"] for r in _protocol(rows) if r["noise [%]"] > 0}):
        pooled, count, none = coverage(rows, names, level / 100)
        cells = [(coverage(rows, [n], level / 100, positions=p), p, n) for p in positions for n in names]
        low = min(((c[0], p, n) for c, p, n in cells if c[1]), default=(float("nan"), "", ""))
        lines.append(f"| {level:g} | {pooled:.3f} | {count} | {none} | {low[0]:.2f} ({low[1]}, {low[2]}) |")
    pooled, count, none = coverage(rows, names)
    return [*lines, f"| all | {pooled:.3f} | {count} | {none} | |"]


def _side_by_side(rows: list[dict], names) -> list[str]:
    first = rows[0]["phantom"]
    lines = [
        "",
        "## Side by side: this pipeline against Nelder–Mead (the published approach)",
        "",
        f"{first}, supine, the same replicates for each method; means. Evaluations are solves of each pair's "
        "model (full solves for the full model).",
        "",
        "| noise [%] | method | replicates | evaluations | seconds | " + " | ".join(f"abs {n} [%]" for n in names) + " |",
        "|---|---|---|---|---|" + "---|" * len(names),
    ]  # fmt: skip
    for level in sorted({r["noise [%]"] for r in rows}):
        beside = [
            r["replicate"]
            for r in _protocol(rows, "Nelder–Mead, reduced")
            if r["noise [%]"] == level and r["phantom"] == first and r["positions"] == "supine"
        ]
        for method in ("trf, reduced", "Nelder–Mead, reduced", "trf, full", "Nelder–Mead, full"):
            chosen = [
                r
                for r in _protocol(rows, method)
                if r["noise [%]"] == level
                and r["phantom"] == first
                and r["positions"] == "supine"
                and r["replicate"] in beside
            ]
            if chosen:
                errors = " | ".join(f"{_mean(abs(r[f'{n} [%]']) for r in chosen):.2f}" for n in names)
                lines.append(
                    f"| {level:g} | {method} | {len(chosen)} | {_mean(r['evaluations'] for r in chosen):.1f} | "
                    f"{_mean(r['seconds'] for r in chosen):.2f} | {errors} |"
                )
    return lines


def _correlated(rows: list[dict], names) -> list[str]:
    correlated = [r for r in rows if "correlation [mm]" in r]
    if not correlated:
        return []
    held = [r[f"{n} covered"] for r in correlated for n in names if r.get(f"{n} covered") is not None]
    errors = ", ".join(f"{n} {_mean(abs(r[f'{n} [%]']) for r in correlated):.2f} %" for n in names)
    return [
        "",
        f"## Noise correlated over {correlated[0]['correlation [mm]']:.0f} mm (10 %)",
        "",
        "The intervals assume independent data; noise correlated along the surface breaks that. Over "
        f"{len(correlated)} estimates (every phantom and set of positions): coverage "
        f"{_mean(held):.3f} of {len(held)} intervals; mean abs error {errors}.",
    ]


def _apart(rows: list[dict], names, key: str, title: str) -> list[str]:
    """A table of the rows with ``key`` (flipped voxels, a biased density): each parameter's
    error and whether its interval held the truth."""
    chosen = [r for r in rows if key in r]
    if not chosen:
        return []
    return [
        "",
        f"## {title}, no data noise",
        "",
        f"| phantom | {key} | " + " | ".join(f"{n} [%] | held" for n in names) + " |",
        "|---|---|" + "---|---|" * len(names),
        *(
            f"| {r['phantom']} | {r[key]:.0f} | "
            + " | ".join(f"{r[f'{n} [%]']:+.2f} | {_held(r[f'{n} covered'])}" for n in names)
            + " |"
            for r in chosen
        ),
    ]


def _times(rows: list[dict], timings: list[dict]) -> list[str]:
    estimates = [r["seconds"] for r in rows if r["method"] == "trf, reduced"]
    return [
        "",
        "## Times (s)",
        "",
        f"The estimate itself: median {np.median(estimates):.2f} s, largest {np.max(estimates):.2f} s (one rank). "
        "Per pair, before it:",
        "",
        "| phantom | position | registration | offline (reduced model) | check (full, refined) |",
        "|---|---|---|---|---|",
        *(
            f"| {t['phantom']} | {t['positions']} | {t['registration']:.1f} | {t['offline']:.1f} | {t['check']:.1f} |"
            for t in timings
        ),
    ]


def plot(rows: list[dict], names, path: Path) -> None:
    """Left: each parameter's error against noise on the first phantom, supine, this pipeline
    beside Nelder–Mead on the same replicates (reduced models; median and, for this pipeline,
    the 10–90 % band). Right: the intervals' coverage per noise level over every phantom,
    position set and parameter, against the nominal level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.4))
    levels = sorted({r["noise [%]"] for r in rows})
    colours = plt.cm.tab10(np.arange(len(names)))
    first = rows[0]["phantom"]
    beside = [r for r in rows if r["phantom"] == first and r["positions"] == "supine" and not SPECIAL & set(r)]
    for method, style in (("trf, reduced", "-"), ("Nelder–Mead, reduced", "--")):
        for name, colour in zip(names, colours):
            stats = []
            for level in levels:
                same = {
                    r["replicate"] for r in beside if r["method"] == "Nelder–Mead, reduced" and r["noise [%]"] == level
                }
                errors = [abs(r[f"{name} [%]"]) for r in beside
                          if r["method"] == method and r["noise [%]"] == level and r["replicate"] in same]  # fmt: skip
                stats.append(np.percentile(errors, [10, 50, 90]) if errors else [np.nan] * 3)
            stats = np.array(stats)
            left.plot(levels, stats[:, 1], style, marker="o", color=colour, label=f"{name}, {method}")
            if method.startswith("trf"):
                left.fill_between(levels, stats[:, 0], stats[:, 2], color=colour, alpha=0.15)
    left.set_title(f"{first}, supine: the same replicates for both", fontsize=9)
    left.set_xlabel("noise [% of the surface's RMS motion]")
    left.set_ylabel("abs error [% of the truth]")
    left.grid(alpha=0.3)
    left.legend(fontsize=7)
    noisy = [level for level in levels if level > 0]
    counted = [coverage(rows, names, level / 100) for level in noisy]
    bars = right.bar([f"{level:g}" for level in noisy], [c[0] for c in counted], color="tab:blue", alpha=0.7)
    for bar, (_, count, none) in zip(bars, counted):
        x = bar.get_x() + bar.get_width() / 2
        right.text(x, 0.53, f"{count} intervals\n{none} at a bound", ha="center", fontsize=7, color="white")
    right.axhspan(0.93, 0.97, color="tab:green", alpha=0.2, label="93–97 %")
    right.axhline(LEVEL, color="k", lw=1, label=f"nominal {100 * LEVEL:.0f} %")
    right.set_ylim(0.5, 1.02)
    right.set_title("every phantom, position set and parameter", fontsize=9)
    right.set_xlabel("noise [% of the surface's RMS motion]")
    right.set_ylabel("coverage of the truth [-]")
    right.legend(fontsize=8, loc="upper right")
    fig.suptitle("Twin experiments: error and coverage against noise (synthetic patients)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
