"""The pressurised thick sphere written by hand in plain DOLFINx: the baseline lungmech is timed against.

Only dolfinx, ufl, basix and petsc4py; ``lungmech.mesh`` is used for the mesh alone, so
both codes solve on the very same cells. Everything else mirrors what lungmech builds for

    Model(geometry, NeoHookean(mu, lmbda), degree=..., mixed=...,
          loads=[FollowerPressure("inner", P)],
          constraints=[symmetry("x0", "x"), symmetry("y0", "y"), symmetry("z0", "z")])
    solve(model, Stepping(initial_step=0.25, growth=1.0))

term by term: the same energy density, the same follower-pressure virtual work (Nanson), the
same quadrature degree, the same SNES/KSP options, the same four load steps and the same linear
predictor between steps (lungmech extrapolates from the last two converged states; doing it
here too keeps the Newton iteration counts equal, so the timings compare equal work).

Run alone:  python benchmarks/handwritten.py --formulation P2 --h 0.15
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI
from petsc4py import PETSc

import basix.ufl
import ufl
from dolfinx import default_scalar_type, fem
from dolfinx.fem.petsc import NonlinearProblem

import lungmech.mesh  # the mesh only (its import also orders MPI before the bindings)

# lungmech's NewtonOptions() defaults, written out.
PETSC_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "bt",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-12,
    "snes_stol": 1e-12,
    "snes_max_it": 25,
    "snes_max_funcs": 350,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
    "mat_mumps_icntl_14": 200,
}


def quadrature_degree(mesh, degree: int) -> int:
    """2g + 2 for a law with logarithms, g = polynomial degree of grad u on a cell (0 -> 0)."""
    g = (degree - 1) + (mesh.geometry.cmaps[0].degree - 1)  # affine simplices; curved cells add cmap - 1
    return 2 * g + 2 if g > 0 else 0


class Problem:
    """Forms, boundary conditions and the SNES of the sphere problem; ``setup_seconds`` = JIT + setup."""

    def __init__(self, geometry, formulation: str, mu: float, lmbda: float, pressure: float, line_search: str = "bt"):
        mesh, tags = geometry.mesh, geometry.facet_tags
        degree, mixed = {"P1": (1, False), "P2": (2, False), "mixed": (2, True)}[formulation]
        cell = mesh.basix_cell()
        element_u = basix.ufl.element("Lagrange", cell, degree, shape=(3,))
        if mixed:
            element = basix.ufl.mixed_element([element_u, basix.ufl.element("Lagrange", cell, degree - 1)])
        else:
            element = element_u
        V = fem.functionspace(mesh, element)
        self.state = fem.Function(V)
        u, p = ufl.split(self.state) if mixed else (self.state, None)
        v = ufl.TestFunction(V)
        v_u = ufl.split(v)[0] if mixed else v

        mu_, lmbda_ = fem.Constant(mesh, mu), fem.Constant(mesh, lmbda)
        self.load = fem.Constant(mesh, default_scalar_type(0.0))
        self.pressure = pressure

        F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
        J = ufl.det(F)
        psi_iso = mu_ / 2 * (ufl.tr(F.T * F) - 3) - mu_ * ufl.ln(J)
        if mixed:  # eliminating p gives back psi exactly
            psi = psi_iso - p * ufl.ln(J) - p**2 / (2 * lmbda_)
        else:
            psi = psi_iso + lmbda_ / 2 * ufl.ln(J) ** 2

        self.quadrature_degree = quadrature_degree(mesh, degree)
        dx = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": self.quadrature_degree})
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
        N = ufl.FacetNormal(mesh)
        residual = ufl.derivative(psi * dx, self.state, v) + self.load * ufl.dot(J * ufl.inv(F).T * N, v_u) * ds(
            geometry.boundaries["inner"]
        )
        jacobian = ufl.derivative(residual, self.state, ufl.TrialFunction(V))

        Vu = V.sub(0) if mixed else V
        bcs = []
        for axis, name in enumerate(("x0", "y0", "z0")):
            dofs = fem.locate_dofs_topological(Vu.sub(axis), 2, tags.find(geometry.boundaries[name]))
            bcs.append(fem.dirichletbc(default_scalar_type(0.0), dofs, Vu.sub(axis)))

        tic = time.perf_counter()
        self.problem = NonlinearProblem(
            residual,
            self.state,
            bcs=bcs,
            J=jacobian,
            petsc_options_prefix="sphere_",
            petsc_options=PETSC_OPTIONS | {"snes_linesearch_type": line_search},
        )
        self.setup_seconds = time.perf_counter() - tic
        self.u, self.bcs, self.residual, self.jacobian = u, bcs, residual, jacobian

    def solve(self, steps: int = 4) -> dict:
        """Ramp the pressure in ``steps`` equal steps; returns iterations and times."""
        snes, x = self.problem.solver, self.state.x.array
        last, previous = x.copy(), None
        iterations, step_seconds = 0, []
        tic = time.perf_counter()
        for k in range(1, steps + 1):
            t0 = time.perf_counter()
            if previous is not None:  # linear predictor (equal steps)
                x[:] = last + (last - previous)
            self.load.value = self.pressure * k / steps
            self.problem.solve()
            if snes.getConvergedReason() <= 0:
                raise RuntimeError(f"step {k}: SNES diverged, reason {snes.getConvergedReason()}")
            iterations += snes.getIterationNumber()
            previous, last = last, x.copy()
            step_seconds.append(time.perf_counter() - t0)
        return {
            "seconds": time.perf_counter() - tic,
            "iterations": iterations,
            "steps": steps,
            "step_seconds": step_seconds,
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--formulation", choices=("P1", "P2", "mixed"), default="P2")
    parser.add_argument("--h", type=float, default=0.2, help="gmsh mesh size")
    parser.add_argument("--pressure", type=float, default=0.2)
    parser.add_argument("--nu", type=float, default=0.4999)
    parser.add_argument("--line-search", default="bt")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    mu = 1.0
    lmbda = 2 * mu * args.nu / (1 - 2 * args.nu)
    order = 1 if args.formulation == "P1" else 2
    geometry = lungmech.mesh.sphere(comm, 1.0, 2.0, mesh_size=args.h, octant=True, order=order)
    problem = Problem(geometry, args.formulation, mu, lmbda, args.pressure, args.line_search)
    result = problem.solve()
    imap = problem.state.function_space.dofmap.index_map
    dofs = imap.size_global * problem.state.function_space.dofmap.index_map_bs
    PETSc.Sys.Print(  # rank 0 only
        f"{args.formulation} h={args.h}: {dofs} dofs, setup {problem.setup_seconds:.2f} s, "
        f"solve {result['seconds']:.2f} s, {result['iterations']} Newton iterations in {result['steps']} steps"
    )


if __name__ == "__main__":
    main()
