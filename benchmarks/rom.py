"""Reduced-order models: speed against accuracy, for every basis kind and size the reductor makes.

    python benchmarks/rom.py                 # the bundled lung and two cantilevers, k up to 40 (minutes)
    python benchmarks/rom.py --quick         # a coarse cantilever, k in {2, 5, 10} (seconds)
    mpiexec -n 2 python benchmarks/rom.py    # the same on two ranks

Every reduced model is one :mod:`lungmech.rom.reductor` build of a scene's full model (started
as its reduced models are: an imaged lung unloaded once at the defaults): POD of the training
load paths (one :class:`~lungmech.rom.reductor.Reductor` at the largest size; the smaller
models are its leading vectors, a POD being nested), the lowest modes (``Modal``), the modes
with their static modal derivatives (the most modes m whose m + m(m+1)/2 vectors fit k) and
monomials of the coordinates (``Polynomial``, the lowest order that gives k), each in the energy
inner product where it has a choice. A basis the model cannot have (modes of a mixed model) is
a row that says why, in the reductor's own words.

The loads are scaled as :meth:`FullOrderModel.solve` scales them (a factor on each load's change
from the start): the training scales build the POD; the test scales are not among them — within
their range ("interp"), beyond it ("extrap"), or in a direction the training never moved
("direction"). Errors (:func:`lungmech.rom.reductor.errors`, against the full model at the same
scale): the state in the energy norm relative to the path's largest change, the volume relative
to the path's volume change, worst over the output times and the tests of a kind, and the best
the basis can do (the state's energy-norm projection on it). Online: the
reduced ``solve`` at the timing scale (median of ``--repeats`` after a warm-up), against the full
model's; offline: the reductor's timings. Writes results/rom.{md,csv,png} (--quick: rom_quick.*).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tomllib
from importlib import resources
from math import comb
from pathlib import Path

from mpi4py import MPI

import machine
from machine import SAME_START, provenance, say, write_results

import lungmech  # noqa: F401  (before dolfinx: it loads the MPI library dolfinx's bindings need)
from lungmech.app import scene as scenes
from lungmech.app.run import full_order_model
from lungmech.errors import LungmechError
from lungmech.rom.reductor import POD, Modal, Polynomial, Reductor, TrainingSet, errors, reduce

RESULTS = machine.RESULTS
KINDS = ("pod", "modal", "modal+derivatives", "polynomial")
SIZES = (2, 5, 10, 20, 40)
QUICK_SIZES = (2, 5, 10)
BEAM = """title = "cantilever"
[geometry]
builder = "box"
lengths = [10.0, 1.0, 1.0]
cells = [{nx}, {n}, {n}]
[material]
law = "neo_hookean"
E = 100.0
nu = 0.3
[[constraints]]
type = "clamp"
boundary = "x0"
[[loads]]
type = "body_force"
value = [0.0, 0.0, {f}]
[[loads]]
type = "body_force"
value = [0.0, {f}, 0.0]
[stepping]
max_step = 0.1
times = [0.25, 0.5, 0.75, 1.0]
[output]
fields = false
"""


@dataclasses.dataclass(frozen=True)
class Test:
    scale: float | tuple[float, ...]
    label: str  # "interp", "extrap" or "direction"
    timing: bool = False  # the load of the timed solves


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    title: str
    scene: scenes.Scene
    train: tuple  # load scales of the POD's training paths
    tests: tuple[Test, ...]


def cases(quick: bool) -> list[Case]:
    """The bundled breathing lung and the cantilever under a small and a large body force (its
    tip dropping 10–35 % and 70–95 % of its length); with ``quick``, a coarse cantilever under
    the small force alone."""
    cells = dict(nx=20, n=2) if quick else dict(nx=40, n=4)
    beam = {"train": ((1.0, 0.0), (2.0, 0.0), (3.0, 0.0))}
    beam["tests"] = (
        Test((1.5, 0.0), "interp"),
        Test((2.5, 0.0), "interp", timing=True),
        Test((3.5, 0.0), "extrap"),
        Test((2.0, 1.0), "direction"),
    )
    found = [
        Case(
            name, f"Neo-Hookean cantilever 10 × 1 × 1 (E = 100 Pa, ν = 0.3), body force {f} N/m³ × scale", scene, **beam
        )
        for name, f in (("beam", 0.01), ("beam-large", 0.1))[: 1 if quick else 2]
        for scene in [scenes.parse(tomllib.loads(BEAM.format(f=-f, **cells)))]
    ]
    if not quick:
        with resources.as_file(resources.files("lungmech.scenes") / "lung_breathing.toml") as path:
            table = tomllib.loads(Path(path).read_text())
        table["output"] = {"fields": False}
        lung = scenes.parse(table)
        tests = (Test(1.25, "interp", timing=True), Test(1.75, "extrap"))
        found.insert(0, Case("lung", "Breathing right lung (bundled scene), poromechanics", lung, (0.5, 1.5), tests))
    return found


def recipe(kind: str, k: int):
    """The basis recipe of ``kind`` with k vectors."""
    if kind == "pod":
        return POD(k)
    if kind == "modal":
        return Modal(k)
    if kind == "modal+derivatives":
        modes = max((m for m in range(1, k + 1) if m + m * (m + 1) // 2 <= k), default=1)
        return Modal(modes, derivatives=True)
    order = next(order for order in range(1, 12) if 3 * (comb(order + 3, 3) - 1) >= k)  # the components' monomials
    return Polynomial(order, k)


def measured(reduced, full, references: dict, case: Case, repeats: int) -> dict:
    """The errors of ``reduced`` at every test (worst per label) and its online time."""
    row = {}
    for test in case.tests:
        found = errors(reduced, references[test], reduced.solve(scale=test.scale))
        for key, value in (
            ("energy", found.energy),
            ("projection", found.projection),
            ("volume_change", found.volume_change),
        ):
            name = f"{test.label}_{key}"
            row[name] = max(row.get(name, 0.0), value)
    timing = next(test for test in case.tests if test.timing)
    answers = [reduced.solve(scale=timing.scale) for _ in range(repeats + 1)][1:]  # after a warm-up
    row["online_s"] = statistics.median(a.seconds for a in answers)
    row["online_newton"] = answers[0].newton_iterations
    return row


def run_case(case: Case, sizes: tuple[int, ...], repeats: int, comm: MPI.Comm) -> list[dict]:
    say(f"{case.name}: the full model")
    full = full_order_model(case.scene, comm, start="defaults")  # the defaults' reference moved to μ
    space = full.model.space
    dofs = space.dofmap.index_map.size_global * space.dofmap.index_map_bs
    references = {test: full.solve(scale=test.scale) for test in case.tests}
    timing = next(test for test in case.tests if test.timing)
    full_s = statistics.median(full.solve(scale=timing.scale).seconds for _ in range(repeats))
    base = {"case": case.name, "dofs": dofs, "full_s": full_s, "full_newton": references[timing].newton_iterations}
    say(f"  {dofs} dofs, {full_s:.2f} s a solve")
    training = TrainingSet([{}], case.train)
    rows = []
    with Reductor(full, POD(max(sizes)), training) as pod:  # the POD's paths solved once: every k from it
        largest = pod.reduce()
        for kind in KINDS:
            for k in sizes:
                row = base | {"basis": kind, "k": k}
                try:
                    if kind == "pod":
                        if k > largest.size:
                            rows.append(row | {"status": f"n/a (only {largest.size} POD directions)"})
                            continue
                        reduced = largest.truncated(k)
                    else:
                        reduced = reduce(full, recipe(kind, k), training)
                    row |= {"size": reduced.size, "status": "ok"} | measured(reduced, full, references, case, repeats)
                    spent = pod.timings if kind == "pod" else reduced.built["timings"]
                    row["offline_s"] = sum(spent.values())
                except LungmechError as error:  # a basis the model cannot have, a solve that fails: said
                    row["status"] = f"n/a: {error}"
                rows.append(row)
                say(
                    f"  {kind} k = {k}: {row['status']}"
                    + (
                        f", energy error {row['interp_energy']:.1e}, {row['online_s']:.3f} s"
                        if row["status"] == "ok"
                        else ""
                    )
                )
    for row in rows:
        if row["status"] == "ok":
            row["speed_up"] = full_s / row["online_s"]
    return rows


def markdown(rows: list[dict], found: list[Case], command: str, ranks: int) -> str:
    lines = [
        "# Reduced-order models: speed against accuracy",
        "",
        provenance(command, "one rank" if ranks == 1 else f"{ranks} ranks"),
        "",
        SAME_START,
        "",
        "Errors are the worst over the output times and the tests of each kind, relative to the path's "
        "largest change (state: energy norm; volume: the path's volume change); the best of the basis: the "
        "state's projection on it in the energy norm. Online: the reduced solve at "
        "the timing scale, median after a warm-up; speed-up: the full model's median over it.",
    ]
    for case in found:
        mine = [r for r in rows if r["case"] == case.name]
        kinds = list(dict.fromkeys(t.label for t in case.tests))
        lines += [
            "",
            f"## {case.title}",
            "",
            f"{mine[0]['dofs']} dofs; training scales {', '.join(map(str, case.train))}; tests "
            + "; ".join(f"{t.scale} ({t.label}{', timed' if t.timing else ''})" for t in case.tests)
            + f"; the full model {mine[0]['full_s']:.2f} s ({mine[0]['full_newton']} Newton iterations) a solve.",
            "",
            "| basis | k | size | "
            + " | ".join(f"energy error ({label}) | best of the basis | volume error ({label})" for label in kinds)
            + " | online [s] | Newton | speed-up | offline [s] |",
            "|" + "---|" * (7 + 3 * len(kinds)),
        ]
        for r in mine:
            if r["status"] != "ok":
                lines.append(f"| {r['basis']} | {r['k']} | — | {r['status']} |" + " |" * (3 + 3 * len(kinds)))
                continue
            errors_text = " | ".join(
                f"{r[f'{label}_energy']:.1e} | {r[f'{label}_projection']:.1e} | {r[f'{label}_volume_change']:.1e}"
                for label in kinds
            )
            lines.append(
                f"| {r['basis']} | {r['k']} | {r['size']} | {errors_text} | {r['online_s']:.3f} | {r['online_newton']} | "
                f"{r['speed_up']:.1f}× | {r['offline_s']:.1f} |"
            )
    return "\n".join(lines) + "\n"


def pareto(rows: list[dict], found: list[Case], path: Path) -> None:
    """Per case, the interpolating energy-norm error against the online time, a line per basis
    kind through its sizes, the full model's time marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig, axes = plt.subplots(1, len(found), figsize=(4.2 * len(found), 4.0), squeeze=False)
    for ax, case in zip(axes[0], found):
        mine = [r for r in rows if r["case"] == case.name]
        for kind, marker, colour in zip(KINDS, "osD^", ("C0", "C1", "C2", "C3")):  # a kind's look in every panel
            ok = [r for r in mine if r["basis"] == kind and r["status"] == "ok"]
            if ok:
                times, found = [r["online_s"] for r in ok], [r["interp_energy"] for r in ok]
                ax.loglog(times, found, f"{marker}-", color=colour, label=kind)
                for r in ok:
                    ax.annotate(str(r["size"]), (r["online_s"], r["interp_energy"]), fontsize=6, xytext=(3, 2),
                                textcoords="offset points")  # fmt: skip
        ax.axvline(mine[0]["full_s"], color="grey", ls=":", label="full model")
        ax.set_title(f"{case.name} ({mine[0]['dofs']} dofs)", fontsize=9)
        ax.set_xlabel("online time of a solve [s]")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(alpha=0.3, which="both")
    axes[0][0].set_ylabel("energy-norm error, interpolating tests [1]")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle("Reduced models: error against time (labels: basis size)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: a coarse cantilever, k in {2, 5, 10}")
    parser.add_argument("--sizes", default=None, help=f"basis sizes k (default {','.join(map(str, SIZES))})")
    parser.add_argument("--cases", default=None, help="comma list of lung, beam, beam-large (default: all)")
    parser.add_argument("--repeats", type=int, default=3, help="timed solves at the timing scale (median)")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    sizes = tuple(int(k) for k in args.sizes.split(",")) if args.sizes else (QUICK_SIZES if args.quick else SIZES)
    found = cases(args.quick)
    if args.cases:
        names = [name.strip() for name in args.cases.split(",")]
        unknown = sorted(set(names) - {case.name for case in found})
        if unknown:
            parser.error(f"--cases: unknown {', '.join(unknown)} (known: {', '.join(c.name for c in found)})")
        found = [case for case in found if case.name in names]
    repeats = 1 if args.quick else args.repeats
    rows = [row for case in found for row in run_case(case, sizes, repeats, comm)]
    stem = "rom_quick" if args.quick else "rom"
    command = "python benchmarks/rom.py" + (" --quick" if args.quick else "")
    command += "".join(f" --{name} {getattr(args, name)}" for name in ("sizes", "cases") if getattr(args, name))
    if comm.size > 1:
        command = f"mpiexec -n {comm.size} {command}"
    if comm.rank == 0:
        RESULTS.mkdir(parents=True, exist_ok=True)
        write_results(RESULTS, stem, rows, markdown(rows, found, command, comm.size))
        pareto(rows, found, RESULTS / f"{stem}.png")
        print((RESULTS / f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
