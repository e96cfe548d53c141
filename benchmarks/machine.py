"""What machine a benchmark ran on, for the header of its table, and how it runs on N ranks."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

_MPI_ENVIRONMENT = ("PMI_RANK", "PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "PMIX_RANK")
# Where every benchmark writes its tables, plots and raw data: benchmarks/results (the measured
# results the docs quote), or the folder LUNGMECH_BENCHMARK_RESULTS names (the suite's --quick
# runs, which must never overwrite them).
RESULTS = Path(os.environ.get("LUNGMECH_BENCHMARK_RESULTS") or Path(__file__).resolve().parent / "results")
STARTED = time.perf_counter()
# How the full model of an imaged lung is started in the reduced-model benchmarks: as its reduced
# models are, until they solve the imaged problem at every μ (docs/architecture.md, "One problem").
SAME_START = (
    "The full model is started as the reduced models are: the imaged lung unloaded once at the default "
    "parameters and its loaded state moved to μ (not the image at μ; `lungmech run --set` solves the image at μ)."
)


def cpu_and_memory() -> tuple[str, str]:
    """The CPU model and the total RAM, from /proc ("unknown ..." where that is not available)."""
    cpu, memory = "unknown CPU", "unknown memory"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        kb = next(int(line.split()[1]) for line in open("/proc/meminfo") if line.startswith("MemTotal"))
        memory = f"{kb / 2**20:.0f} GiB RAM"
    except (OSError, StopIteration):
        pass
    return cpu, memory


def provenance(command: str, ranks: str = "one rank") -> str:
    """The header line of a table: the command, the date, the machine, DOLFINx and the ranks."""
    import dolfinx  # after lungmech, which loads the MPI library its bindings need

    cpu, memory = cpu_and_memory()
    return f"`{command}` — {time.strftime('%Y-%m-%d')}, {cpu}, {memory}, DOLFINx {dolfinx.__version__}, {ranks}."


def time_against_dofs(rows: list[dict], series: list[tuple[str, str]], ylabel: str, title: str, path: Path) -> None:
    """A log-log plot of each row's ``key`` against its "dofs", one line per (key, label)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 4.2))
    dofs = [r["dofs"] for r in rows]
    for key, label in series:
        ax.loglog(dofs, [r[key] for r in rows], "o-", label=label)
    ax.set_xlabel("degrees of freedom [-]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def stacked_bars(
    labels: list[str],
    parts: dict[str, tuple[list[float], str]],
    notes: list[str],
    xlabel: str,
    title: str,
    path: Path,
) -> None:
    """Horizontal bars, one per label, stacked from ``parts`` (name: (one width per label,
    colour)), each bar's note at its end, the legend below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.0, 0.6 * len(labels) + 2.0))
    left = [0.0] * len(labels)
    for name, (widths, colour) in parts.items():
        ax.barh(labels, widths, left=left, color=colour, label=name)
        left = [a + b for a, b in zip(left, widths, strict=True)]
    for y, (end, note) in enumerate(zip(left, notes, strict=True)):
        ax.text(end, y, f"  {note}", va="center", fontsize=8)
    ax.set_xlabel(xlabel)
    ax.invert_yaxis()
    ax.margins(x=0.45 if max(map(len, notes), default=0) > 20 else 0.2)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=len(parts), fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_results(directory: Path, stem: str, rows: list[dict], markdown: str) -> None:
    """``stem``.md (the table, as written) and ``stem``.csv (the rows; the columns of all rows,
    in the order they first appear) in ``directory``."""
    import csv

    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{stem}.md").write_text(markdown)
    with open(directory / f"{stem}.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(dict.fromkeys(key for row in rows for key in row)))
        writer.writeheader()
        writer.writerows(rows)


def read_results(path: Path) -> list[dict]:
    """The rows of a results CSV, numbers as numbers (for --replot, and the rows a run keeps)."""
    import csv

    def value(text: str):
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return None if text == "" else text

    with open(path, newline="") as stream:
        return [{key: value(text) for key, text in row.items()} for row in csv.DictReader(stream)]


def by_size(args, stem: str, case: Callable, markdown: Callable, plot: Callable, command: str) -> None:
    """Each mesh size of ``args.sizes`` (comma-separated) measured by ``case(size, args)`` (its
    rows, each with its "mesh h [mm]" and "dofs") in turn, and after each ``stem``.md
    (``markdown(rows, command, args, date)``), .csv and .png (``plot(rows, path)``) written, with
    the rows of the sizes this run does not measure kept from ``stem``.csv as it is then (another
    run's may have landed meanwhile); the table printed at the end. With ``args.replot``, only
    the CSV's rows written again, under their own command and date."""
    path = RESULTS / f"{stem}.csv"

    def report(rows: list[dict], command: str, date: str | None = None) -> None:
        write_results(RESULTS, stem, rows, markdown(rows, command, args, date))
        plot(rows, RESULTS / f"{stem}.png")

    if args.replot:
        rows = read_results(path)
        report(rows, rows[-1]["command"], rows[-1]["date"])
        return
    measured: list[dict] = []
    for size in [size.strip() for size in args.sizes.split(",")]:
        measured += case(size, args)
        sizes = {str(r["mesh h [mm]"]) for r in measured}
        kept = [r for r in (read_results(path) if path.exists() else []) if str(r["mesh h [mm]"]) not in sizes]
        report(sorted([r for r in kept if "command" in r] + measured, key=lambda r: r["dofs"]), command)
    print((RESULTS / f"{stem}.md").read_text())


def relaunch(ranks: int, script: str, command_variable: str) -> None:
    """Re-run ``script`` under ``mpiexec -n ranks`` (without ``--ranks``) unless already under MPI;
    the original arguments go to the environment variable ``command_variable``."""
    if ranks <= 1 or any(k in os.environ for k in _MPI_ENVIRONMENT):
        return
    mpiexec = Path(sys.executable).parent / "mpiexec"
    argv, skip = [], False
    for a in sys.argv[1:]:
        if skip:
            skip = False
            continue
        if a == "--ranks":
            skip = True
            continue
        if a.startswith("--ranks="):
            continue
        argv.append(a)
    command = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", str(ranks), sys.executable, script, *argv]
    env = os.environ | {command_variable: " ".join(sys.argv[1:])}
    sys.exit(subprocess.run(command, env=env).returncode)


def say(*parts) -> None:
    """Progress on rank 0, with the minutes since the start."""
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank == 0:
        print(f"[{(time.perf_counter() - STARTED) / 60:5.1f} min]", *parts, flush=True)


def status_kb(key: str) -> int | None:
    """A field of /proc/self/status in kB (``VmRSS``: resident now, ``VmHWM``: peak), or None."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def reset_peak() -> bool:
    """Reset the kernel's peak RSS (VmHWM, and with it getrusage's ru_maxrss) of this process to
    its current RSS (Linux >= 4.0); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as stream:
            stream.write("5")
        return True
    except OSError:
        return False


def tic() -> float:
    """A start time, all ranks together."""
    from mpi4py import MPI

    MPI.COMM_WORLD.Barrier()
    return time.perf_counter()


def toc(start: float) -> float:
    """Seconds since ``tic``, all ranks together, rank 0's clock."""
    from mpi4py import MPI

    MPI.COMM_WORLD.Barrier()
    return MPI.COMM_WORLD.bcast(time.perf_counter() - start, root=0)
