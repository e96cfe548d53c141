"""Memory and time of the canonical dof layout (lungmech.parallel.layout) on 1 and 2 ranks, against
the allgather implementation it replaced.

    python benchmarks/layout.py                     # box meshes of 89k, 239k and 527k dofs, 1 and 2 ranks (~5 min)
    python benchmarks/layout.py --cells 55          # the 527k-dof mesh only
    python benchmarks/layout.py --ranks 1 2 4       # other rank counts
    python benchmarks/layout.py --quick             # boxes of 8 and 12 cells a side (seconds): layout_quick.*

Each case (implementation, mesh, ranks) runs in a process of its own, under ``mpiexec -n RANKS``,
which this script starts. A case builds a unit box of CELLS³ × 6 tetrahedra and its P1 vector
space (3 (CELLS + 1)³ dofs) and a random basis of VECTORS columns (its owned rows), then

1. computes the layout and fingerprint (``layout(space)``);
2. writes the basis through the store path (``lungmech.rom.store.write``, which lays out again,
   gathers the vectors to rank 0 and writes the ``.npz`` there). The model it is given is a
   stand-in holding only the space: ``write`` reads nothing else, and a real Model would add form
   compilation that has nothing to do with the layout.

Memory is getrusage's ru_maxrss per rank (Linux: kB, shown in MiB = 2^20 bytes). Before each
step the kernel's high-water mark is reset to the current RSS (/proc/self/clear_refs), so the
step's peak is its own; its increment is that peak minus the RSS of the mesh, space and basis
alone (measured after malloc_trim, so that freed memory does not hide new allocations). Times are
wall times between barriers.

The ``allgather`` implementation is the one before issue 12's deliverable 4, copied below for
this comparison only: every rank gathers the keys (field, component, quantised coordinates) of
every dof and the midpoints of every cell, sorts them all, and gathers whole vectors.

Writes benchmarks/results/layout/layout.{md,csv,png}.
"""

from __future__ import annotations

import argparse
import csv
import ctypes
import datetime
import hashlib
import importlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import machine
from machine import STARTED, cpu_and_memory, reset_peak, status_kb, tic, toc  # benchmarks/ is first on sys.path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = machine.RESULTS / "layout"
sys.path.insert(0, str(ROOT))

IMPLEMENTATIONS = ("allgather", "distributed")
MARK = "LAYOUT-CASE "  # the line of a case's output that carries its results

COLUMNS = {  # CSV column -> header with its unit
    "implementation": "implementation [name]",
    "ranks": "ranks [count]",
    "rank": "rank [id]",
    "cells": "cells [count]",
    "dofs": "dofs [count]",
    "vectors": "basis vectors [count]",
    "baseline_rss": "mesh+space+basis RSS [MiB]",
    "baseline_peak": "peak RSS while building mesh+space [MiB]",
    "layout_peak": "peak RSS during layout [MiB]",
    "layout_increment": "layout increment over mesh+space [MiB]",
    "write_peak": "peak RSS during store write [MiB]",
    "write_increment": "store-write increment over mesh+space [MiB]",
    "peak": "peak RSS of the case [MiB]",
    "layout_seconds": "layout time [s]",
    "write_seconds": "store-write time [s]",
    "file": "file size [MiB]",
    "fingerprint": "fingerprint [hex]",
}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--cells", type=int, nargs="+", default=[30, 42, 55, 70], help="cells per box edge (default 30 42 55 70)"
    )
    p.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="MPI rank counts (default 1 2)")
    p.add_argument("--vectors", type=int, default=5, help="columns of the basis written (default 5)")
    p.add_argument("--quick", action="store_true", help="boxes of 8 and 12 cells a side (the suite's case)")
    p.add_argument("--case", choices=IMPLEMENTATIONS, help=argparse.SUPPRESS)  # one case, under mpiexec
    return p.parse_args(argv)


# --- the allgather implementation, as it was before deliverable 4 (for the comparison only) ------


@dataclass(frozen=True)
class AllgatherLayout:
    index: object
    size: int
    fingerprint: str
    comm: object

    def gather(self, local, root=0):
        """Rows of every rank in canonical order, on every rank (the store then writes on rank 0)."""
        import numpy as np

        pieces = self.comm.allgather((self.index, np.asarray(local)))
        result = np.empty((self.size, *np.shape(local)[1:]), dtype=float)
        for index, values in pieces:
            result[index] = values
        return result


def allgather_layout(space) -> AllgatherLayout:
    import numpy as np

    from lungmech.parallel.layout import _RESOLUTION, _diameter, field_dofs

    comm = space.mesh.comm
    owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
    keys = np.zeros((owned, 5), dtype=np.int64)
    grid = _RESOLUTION * _diameter(space.mesh)
    for field, (collapsed, parent) in enumerate(field_dofs(space)):
        bs = collapsed.dofmap.index_map_bs
        nodes = collapsed.dofmap.index_map.size_local
        points = np.round(collapsed.tabulate_dof_coordinates()[:nodes] / grid).astype(np.int64)
        for component in range(bs):
            rows = parent[np.arange(nodes) * bs + component]
            keys[rows, 0], keys[rows, 1], keys[rows, 2:] = field, component, points
    pieces = comm.allgather(keys)
    everything = np.concatenate(pieces)
    order = np.lexsort(everything.T[::-1])
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    offset = sum(len(k) for k in pieces[: comm.rank])
    digest = hashlib.sha256(str(space.ufl_element()).encode())
    digest.update(np.ascontiguousarray(everything[order]).tobytes())
    mesh = space.mesh
    cells = mesh.topology.index_map(mesh.topology.dim).size_local
    midpoints = np.round(mesh.geometry.x[mesh.geometry.dofmaps[0][:cells]].mean(axis=1) / grid).astype(np.int64)
    every_midpoint = np.concatenate(comm.allgather(midpoints))
    digest.update(np.ascontiguousarray(every_midpoint[np.lexsort(every_midpoint.T[::-1])]).tobytes())
    return AllgatherLayout(position[offset : offset + owned], len(order), digest.hexdigest()[:16], comm)


# --- one case, on every rank of mpiexec ----------------------------------------------------------


def rss_mib() -> float:
    return (status_kb("VmRSS") or 0) / 1024


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB


def release() -> None:
    """Give freed heap memory back to the system (glibc), so that it does not hide new allocations."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def case(implementation: str, cells: int, vectors: int) -> None:
    importlib.import_module("lungmech")  # first: it loads the MPI library that DOLFINx links to
    from mpi4py import MPI

    import dolfinx.mesh
    import numpy as np
    from dolfinx import fem

    from lungmech.parallel.layout import layout
    from lungmech.rom import store
    from lungmech.rom.basis import Basis

    comm = MPI.COMM_WORLD
    lay = {"allgather": allgather_layout, "distributed": layout}[implementation]
    store.layout = lay  # the store path with this implementation's layout and gather
    mesh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [1, 1, 1]], [cells] * 3, dolfinx.mesh.CellType.tetrahedron)
    space = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
    rows = np.random.default_rng(comm.rank).standard_normal((owned, vectors))
    release()
    row = {"baseline_peak": peak_mib(), "baseline_rss": rss_mib()}

    reset_peak()
    start = tic()
    where = lay(space)
    row |= {"layout_seconds": toc(start), "layout_peak": peak_mib()}

    folder = comm.bcast(tempfile.mkdtemp(prefix="lungmech-layout-") if comm.rank == 0 else None)
    path = Path(folder) / "basis.npz"
    basis = Basis(rows, np.ones(vectors), "benchmark", "l2", where.fingerprint)
    release()
    reset_peak()
    start = tic()
    store.write(path, SimpleNamespace(space=space), basis)
    row |= {"write_seconds": toc(start), "write_peak": peak_mib()}
    if comm.rank == 0:
        row["file"] = path.stat().st_size / 2**20
        path.unlink()
        Path(folder).rmdir()

    row |= {
        "implementation": implementation,
        "ranks": comm.size,
        "rank": comm.rank,
        "cells": comm.allreduce(mesh.topology.index_map(3).size_local),
        "dofs": where.size,
        "vectors": vectors,
        "fingerprint": where.fingerprint,
        "dolfinx": dolfinx.__version__,
        "layout_increment": row["layout_peak"] - row["baseline_rss"],
        "write_increment": row["write_peak"] - row["baseline_rss"],
    }
    row["peak"] = max(row["baseline_peak"], row["layout_peak"], row["write_peak"])
    rows_of_ranks = comm.gather(row)
    if comm.rank == 0:
        file = rows_of_ranks[0]["file"]
        print(MARK + json.dumps([r | {"file": file} for r in rows_of_ranks]), flush=True)


# --- the driver: one process per case, then the tables and the plot ----------------------------


def run_case(implementation: str, cells: int, ranks: int, vectors: int) -> list[dict]:
    mpiexec = Path(sys.executable).parent / "mpiexec"
    command = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", str(ranks), sys.executable, __file__]
    command += ["--case", implementation, "--cells", str(cells), "--vectors", str(vectors)]
    environment = os.environ | {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run(command, env=environment, capture_output=True, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith(MARK)]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return json.loads(lines[-1].removeprefix(MARK))


def growth(rows: list[dict], implementation: str, ranks: int, rank: int, step: str) -> float:
    """Least-squares slope of a rank's increment against dofs, in bytes per dof."""
    import numpy as np

    chosen = [r for r in rows if (r["implementation"], r["ranks"], r["rank"]) == (implementation, ranks, rank)]
    if len({r["dofs"] for r in chosen}) < 2:
        return float("nan")
    dofs = np.array([r["dofs"] for r in chosen], dtype=float)
    increment = np.array([r[f"{step}_increment"] for r in chosen]) * 2**20
    return float(np.polyfit(dofs, increment, 1)[0])


def markdown(rows: list[dict], args: argparse.Namespace, load: tuple[float, float]) -> str:
    import numpy as np

    cpu, memory = cpu_and_memory()
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    lines = [
        "# Canonical dof layout: memory and time per rank, distributed against allgather",
        "",
        f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; {os.cpu_count()} cores "
        f"({cpu}), {memory}; 1-min load average {load[0]:.2f} at the start, {load[1]:.2f} at the end "
        "(the machine is shared: above the number of ranks, other work ran too).",
        f"- DOLFINx {rows[0]['dolfinx']}, NumPy {np.__version__}, Python {platform.python_version()}; "
        f"lungmech at {commit.stdout.strip()}.",
        f"- Command: `{' '.join(['python benchmarks/layout.py', *sys.argv[1:]])}`; "
        f"total wall time {(time.perf_counter() - STARTED) / 60:.1f} min.",
        "- Case: `create_box` of cells³ × 6 tetrahedra, P1 vector space, a random basis of "
        f"{args.vectors} vectors. **layout**: `layout(space)` (order + fingerprint). **write**: "
        "`lungmech.rom.store.write` (layout again, gather to rank 0, `.npz` on rank 0). One process "
        "per case; increments are each step's peak RSS (ru_maxrss after resetting the high-water mark) "
        "minus the RSS of mesh + space + basis. MiB = 2^20 bytes.",
        "",
        "| implementation | ranks | rank | cells | dofs | mesh+space RSS [MiB] | layout peak [MiB] | "
        "layout increment [MiB] | write peak [MiB] | write increment [MiB] | layout [s] | write [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['implementation']} | {r['ranks']} | {r['rank']} | {r['cells']:,} | {r['dofs']:,} | "
            f"{r['baseline_rss']:.0f} | {r['layout_peak']:.0f} | {r['layout_increment']:.1f} | "
            f"{r['write_peak']:.0f} | {r['write_increment']:.1f} | {r['layout_seconds']:.2f} | "
            f"{r['write_seconds']:.2f} |"
        )
    lines += [
        "",
        "## How memory per rank grows",
        "",
        "Slope of the increment against the global number of dofs (least squares over the meshes), "
        "bytes per dof. A rank that holds O(N / ranks) has a slope that halves from 1 to 2 ranks; "
        "one that holds everything keeps it.",
        "",
        "| implementation | ranks | rank | layout [B/dof] | write [B/dof] |",
        "|---|---|---|---|---|",
    ]
    for implementation in IMPLEMENTATIONS:
        for ranks in args.ranks:
            for rank in range(ranks):
                lines.append(
                    f"| {implementation} | {ranks} | {rank} | "
                    f"{growth(rows, implementation, ranks, rank, 'layout'):.1f} | "
                    f"{growth(rows, implementation, ranks, rank, 'write'):.1f} |"
                )
    prints = {(r["implementation"], r["cells"]): set() for r in rows}
    for r in rows:
        prints[r["implementation"], r["cells"]].add(r["fingerprint"])
    same = all(len(p) == 1 for p in prints.values())
    lines += [
        "",
        f"Fingerprints are {'identical' if same else 'NOT identical'} on every rank count for each mesh "
        "and implementation (the two implementations hash different things, so theirs differ).",
        "",
    ]
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = {
        "layout_increment": ("layout: peak RSS increment per rank [MiB]", "Memory of the layout"),
        "write_increment": ("store write: peak RSS increment per rank [MiB]", "Memory of a store write"),
        "layout_seconds": ("layout time [s]", "Time of the layout"),
    }
    fig, axes = plt.subplots(1, len(panels), figsize=(15, 4.4))
    for (key, (ylabel, title)), ax in zip(panels.items(), axes):
        for implementation, colour in zip(IMPLEMENTATIONS, ("tab:red", "tab:blue")):
            for ranks in sorted({r["ranks"] for r in rows}):
                for rank, marker in ((0, "o"), (1, "s")):
                    chosen = [
                        r for r in rows if (r["implementation"], r["ranks"], r["rank"]) == (implementation, ranks, rank)
                    ]
                    if not chosen or (key == "layout_seconds" and rank > 0):  # times are the same on every rank
                        continue
                    label = f"{implementation}, {ranks} rank{'s' if ranks > 1 else ''}"
                    ax.plot(
                        [r["dofs"] / 1e3 for r in chosen],
                        [r[key] for r in chosen],
                        "-" if ranks == 1 else "--",
                        marker=marker,
                        color=colour,
                        label=label if key == "layout_seconds" else f"{label}, rank {rank}",
                    )
        ax.set(xlabel="dofs [thousands]", ylabel=ylabel, title=title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    args = parse_args()
    if args.case is not None:
        case(args.case, args.cells[0], args.vectors)
        return
    if args.quick:
        args.cells = [8, 12]
    stem = "layout_quick" if args.quick else "layout"
    start_load = os.getloadavg()[0]
    rows = []
    for cells in args.cells:
        for implementation in IMPLEMENTATIONS:
            for ranks in args.ranks:
                found = run_case(implementation, cells, ranks, args.vectors)
                worst = max(found, key=lambda r: r["layout_increment"])
                print(
                    f"[{(time.perf_counter() - STARTED) / 60:5.1f} min] {implementation:11s} {ranks} rank(s) "
                    f"{found[0]['dofs']:>9,} dofs: layout +{worst['layout_increment']:.1f} MiB "
                    f"{found[0]['layout_seconds']:.2f} s, write +{max(r['write_increment'] for r in found):.1f} MiB "
                    f"{found[0]['write_seconds']:.2f} s",
                    flush=True,
                )
                rows += found
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f"{stem}.csv", "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(COLUMNS.values())
        for r in rows:
            writer.writerow([r[key] for key in COLUMNS])
    text = markdown(rows, args, (start_load, os.getloadavg()[0]))
    (RESULTS / f"{stem}.md").write_text(text)
    plot(rows, RESULTS / f"{stem}.png")
    print(text)


if __name__ == "__main__":
    main()
