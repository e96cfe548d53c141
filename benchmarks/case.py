"""One benchmark case in a process of its own: mesh, set up, solve, measure errors, print JSON.

    python benchmarks/case.py --impl lungmech --formulation P2 --h 0.15
    mpiexec -n 2 python benchmarks/case.py --impl handwritten --formulation P2 --h 0.07

``benchmarks/run.py`` runs this once per (formulation, mesh, implementation), so that peak
memory is that of one case. The last line on stdout is ``RESULT {json}`` (rank 0).

Timings (wall clock, ``time.perf_counter``, max over ranks):
  mesh_seconds   gmsh meshing + distribution (lungmech.mesh.sphere, the same for both codes)
  build_seconds  function spaces, UFL forms, boundary conditions (no compilation)
  setup_seconds  constructing the solver: FFCx/CFFI JIT of residual and Jacobian (cold or warm
                 cache, see ``jit_cache``), matrix sparsity, vectors, SNES/KSP set-up
  solve_seconds  the load stepping loop (Newton: assembly + MUMPS LU + line search), fastest of
                 ``solves`` solves from the undeformed state (repeated only when short, see
                 MAX_SOLVES); ``solve_seconds_first`` is the first one
Errors against the SciPy solution of the radial BVP (tests/analytic.py), see ``reference``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

_started = time.perf_counter()

from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem

import lungmech  # noqa: F401  (orders MPI before the DOLFINx bindings)
from lungmech.mesh import sphere

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))  # tests/analytic.py: plain NumPy/SciPy, no lungmech
import analytic  # noqa: E402

A_RADIUS, B_RADIUS = 1.0, 2.0
MU = 1.0
FORMULATIONS = {"P1": (1, False), "P2": (2, False), "mixed": (2, True)}
ERROR_QUADRATURE = 8  # quadrature degree of the error integrals (the integrands are not polynomials)
# Short solves are timed again (from the undeformed state, same solver) and the fastest kept:
# at a few seconds, process-to-process noise on a shared VM is ~10 %. At most MAX_SOLVES solves,
# no new one once REPEAT_BUDGET seconds have been spent.
MAX_SOLVES, REPEAT_BUDGET = 5, 10.0
SOLVES = {"most": MAX_SOLVES}  # --solves lowers it (a smoke run: 1)


def lame(nu: float, mu: float = MU) -> float:
    """λ for shear modulus μ and Poisson ratio ν (= NeoHookean.from_young(2μ(1 + ν), ν).lmbda)."""
    return 2 * mu * nu / (1 - 2 * nu)


# --- reference ---------------------------------------------------------------------------------


class Reference:
    """u_ref(R) of the compressible neo-Hookean sphere and a UFL expression of it.

    ``tests/analytic.thick_sphere_compressible`` solves the radial BVP with scipy's solve_bvp
    (relative collocation tolerance 1e-10) and returns a cubic spline. For UFL, u_ref is
    re-expressed as a Chebyshev series on [A, B] (interpolation at Chebyshev points of that
    spline; the solution is analytic on [A, B], so the series converges geometrically) and
    evaluated by the Clenshaw recurrence in R = |X|. ``fit_error`` is the max deviation of the
    series from the spline on 4001 points, relative to u_ref(A).
    """

    def __init__(self, pressure: float, nu: float, degree: int = 24):
        self.solution = analytic.thick_sphere_compressible(
            "neo_hookean", analytic.LameParams(MU, lame(nu)), pressure, A_RADIUS, B_RADIUS
        )
        self.u_inner = float(self.solution.u_inner)
        cheb = np.polynomial.chebyshev.Chebyshev.interpolate(self.solution.u, degree, domain=[A_RADIUS, B_RADIUS])
        R = np.linspace(A_RADIUS, B_RADIUS, 4001)
        self.fit_error = float(np.max(np.abs(cheb(R) - self.solution.u(R))) / abs(self.u_inner))
        self.coefficients = cheb.coef

    def ufl_radial(self, R):
        """u_ref(R) as a UFL expression (Clenshaw)."""
        t = (2 * R - (A_RADIUS + B_RADIUS)) / (B_RADIUS - A_RADIUS)
        b1, b2 = 0.0, 0.0
        for c in self.coefficients[:0:-1]:
            b1, b2 = float(c) + 2 * t * b1 - b2, b1
        return float(self.coefficients[0]) + t * b1 - b2


def errors(mesh, geometry, u, reference: Reference) -> dict:
    """Inner-radius and L2 displacement errors of the displacement ``u`` (a UFL expression)."""
    comm = mesh.comm
    X = ufl.SpatialCoordinate(mesh)
    R = ufl.sqrt(ufl.dot(X, X))
    u_ref = reference.ufl_radial(R) * X / R
    dx = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": ERROR_QUADRATURE})
    ds = ufl.Measure(
        "ds", domain=mesh, subdomain_data=geometry.facet_tags, metadata={"quadrature_degree": ERROR_QUADRATURE}
    )
    inner = ds(geometry.boundaries["inner"])
    x = X + u

    def integrate(integrand) -> float:
        return comm.allreduce(fem.assemble_scalar(fem.form(integrand)), op=MPI.SUM)

    area = integrate(1.0 * inner)
    radius = integrate(ufl.sqrt(ufl.dot(x, x)) * inner) / area  # mean |X + u| on the inner surface
    radial = integrate((ufl.sqrt(ufl.dot(x, x)) - R) * inner) / area  # mean of |X + u| - |X|
    e = u - u_ref
    l2 = np.sqrt(integrate(ufl.dot(e, e) * dx) / integrate(ufl.dot(u_ref, u_ref) * dx))
    u_a = radius - A_RADIUS
    return {
        "u_inner": u_a,
        "u_inner_ref": reference.u_inner,
        "err_inner": abs(u_a - reference.u_inner) / abs(reference.u_inner),
        "err_inner_pointwise": abs(radial - reference.u_inner) / abs(reference.u_inner),
        "err_l2": float(l2),
        "reference_fit_error": reference.fit_error,
    }


# --- the two implementations -------------------------------------------------------------------


def repeat(comm, solve_once, times: list[float]) -> None:
    """Call ``solve_once`` (collectively) at least once, appending its wall time (max over ranks)."""
    while True:
        tic = time.perf_counter()
        try:
            solve_once()
        finally:
            times.append(comm.allreduce(time.perf_counter() - tic, op=MPI.MAX))
        if len(times) >= SOLVES["most"] or sum(times) >= REPEAT_BUDGET:
            return


def run_lungmech(geometry, formulation: str, pressure: float, nu: float, steps: int, line_search: str) -> dict:
    from lungmech.errors import SolverError
    from lungmech.fem.constraints import symmetry
    from lungmech.fem.loads import FollowerPressure
    from lungmech.fem.materials import NeoHookean
    from lungmech.fem.model import Model
    from lungmech.fem.solver import NewtonOptions, NewtonSolver, Stepping, solve

    degree, mixed = FORMULATIONS[formulation]
    tic = time.perf_counter()
    model = Model(
        geometry,
        NeoHookean.from_young(2 * MU * (1 + nu), nu),
        degree=degree,
        mixed=mixed,
        loads=[FollowerPressure("inner", pressure)],
        constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")],
    )
    build = time.perf_counter() - tic
    tic = time.perf_counter()
    solver = NewtonSolver(model, NewtonOptions(linear_solver="direct", line_search=line_search))
    setup = time.perf_counter() - tic
    out = {
        "build_seconds": build,
        "setup_seconds": setup,
        "quadrature_degree": model.dx.metadata()["quadrature_degree"],
    }
    stepping = Stepping(initial_step=1.0 / steps, growth=1.0)  # growth 1: equal steps unless Newton fails
    times: list[float] = []
    reports = []

    def solve_once():
        model.state.x.array[:] = 0.0  # every solve starts from the undeformed state
        reports.append(solve(model, stepping, solver=solver))

    try:
        repeat(model.geometry.mesh.comm, solve_once, times)
        out |= {"converged": True, "message": ""}
    except SolverError as error:
        out |= {"converged": False, "message": str(error)[:300]}
    report = reports[-1] if out["converged"] else None
    out |= {"solve_seconds_first": times[0], "solve_seconds": min(times), "solves": len(times)}
    if report is not None:
        out |= {
            "newton_iterations": report.newton_iterations,
            "load_steps": len(report.accepted),
            "failed_steps": report.failures,
            "step_seconds": [s.seconds for s in report.steps],
        }
    space = model.space
    out["dofs"] = space.dofmap.index_map.size_global * space.dofmap.index_map_bs
    return out | {"_u": model.u}


def run_handwritten(geometry, formulation: str, pressure: float, nu: float, steps: int, line_search: str) -> dict:
    from handwritten import Problem

    tic = time.perf_counter()
    problem = Problem(geometry, formulation, MU, lame(nu), pressure, line_search=line_search)
    total = time.perf_counter() - tic
    out = {
        "build_seconds": total - problem.setup_seconds,
        "setup_seconds": problem.setup_seconds,
        "quadrature_degree": problem.quadrature_degree,
    }
    times: list[float] = []
    results = []

    def solve_once():
        problem.state.x.array[:] = 0.0
        results.append(problem.solve(steps))

    try:
        repeat(geometry.mesh.comm, solve_once, times)
        result = results[-1]
        out |= {
            "converged": True,
            "message": "",
            "newton_iterations": result["iterations"],
            "load_steps": result["steps"],
            "failed_steps": 0,
            "step_seconds": result["step_seconds"],
        }
    except RuntimeError as error:
        out |= {"converged": False, "message": str(error)[:300]}
    out |= {"solve_seconds_first": times[0], "solve_seconds": min(times), "solves": len(times)}
    space = problem.state.function_space
    out["dofs"] = space.dofmap.index_map.size_global * space.dofmap.index_map_bs
    return out | {"_u": problem.u}


# --- main --------------------------------------------------------------------------------------


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def main() -> None:
    parser = argparse.ArgumentParser(description="one benchmark case")
    parser.add_argument("--impl", choices=("lungmech", "handwritten"), required=True)
    parser.add_argument("--formulation", choices=tuple(FORMULATIONS), required=True)
    parser.add_argument("--h", type=float, required=True, help="gmsh mesh size")
    parser.add_argument("--pressure", type=float, default=0.2)
    parser.add_argument("--nu", type=float, default=0.4999)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--line-search", default="cp")
    parser.add_argument(
        "--max-dofs", type=int, default=0, help="stop after meshing if the case is larger (0: no limit)"
    )
    parser.add_argument("--solves", type=int, default=MAX_SOLVES, help=f"timed solves at most (default {MAX_SOLVES})")
    args = parser.parse_args()
    SOLVES["most"] = args.solves
    comm = MPI.COMM_WORLD

    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fenics"
    jit_cache = "warm" if cache.is_dir() and any(cache.iterdir()) else "cold"
    jit_cache = comm.bcast(jit_cache, root=0)

    degree, mixed = FORMULATIONS[args.formulation]
    order = 1 if degree == 1 else 2  # P1 on straight cells; P2 and Taylor-Hood on curved quadratic cells
    tic = time.perf_counter()
    geometry = sphere(comm, A_RADIUS, B_RADIUS, mesh_size=args.h, octant=True, order=order)
    mesh_seconds = time.perf_counter() - tic
    mesh = geometry.mesh
    result = {
        "impl": args.impl,
        "formulation": args.formulation,
        "h": args.h,
        "mesh_order": order,
        "ranks": comm.size,
        "cells": mesh.topology.index_map(3).size_global,
        "vertices": mesh.topology.index_map(0).size_global,
        "jit_cache": jit_cache,
        "pressure": args.pressure,
        "nu": args.nu,
        "line_search": args.line_search,
        "mesh_seconds": mesh_seconds,
        "peak_rss_mesh_mb": max(comm.allgather(peak_rss_mb())),
    }
    # dofs before any solve, to honour --max-dofs cheaply (vector Lagrange [+ P1 pressure])
    vertices = result["vertices"]
    mesh.topology.create_entities(1)
    edges = mesh.topology.index_map(1).size_global
    dofs_estimate = 3 * vertices if degree == 1 else 3 * (vertices + edges) + (vertices if mixed else 0)
    if args.max_dofs and dofs_estimate > args.max_dofs:
        if comm.rank == 0:
            print("RESULT " + json.dumps(result | {"skipped": True, "dofs": dofs_estimate}), flush=True)
        return

    run = run_lungmech if args.impl == "lungmech" else run_handwritten
    out = run(geometry, args.formulation, args.pressure, args.nu, args.steps, args.line_search)
    u = out.pop("_u")
    for key in ("build_seconds", "setup_seconds"):
        out[key] = max(comm.allgather(out[key]))
    result |= out
    if out["converged"]:
        result |= errors(mesh, geometry, u, Reference(args.pressure, args.nu))
    rss = comm.allgather(peak_rss_mb())
    result |= {"peak_rss_mb": max(rss), "peak_rss_mb_sum": sum(rss), "process_seconds": time.perf_counter() - _started}
    if comm.rank == 0:
        print("RESULT " + json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
