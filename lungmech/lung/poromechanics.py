"""The quasi-static poromechanical lung model of Patte, Genet & Chapelle (2022).

Unknowns: the displacement u and Φs, the current solid volume per unit reference volume
(Φf = J − Φs is the fluid, i.e. air, volume). The total potential is

    Π(u, Φs) = ∫ s·W_skel(F) + W_bulk(Φs) + W_pore(J − Φs) − p_f (J − Φs) dX  + (pleural loads),

W_skel = α(e^{γ(J²−1−2lnJ)} − 1) + c1(I1−3−2lnJ) + c2(I2−3−4lnJ) (:func:`skeleton`),
W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)), the optional porosity barrier W_pore and the skeleton
scaling s (Φs0 or 1) as in :class:`Poromechanics`; p_f is the alveolar (air) pressure
(:class:`AlveolarPressure`). Without W_pore, its Φs-equation is the reference's
∂W_bulk/∂Φs + p_f = 0, and at that solution its u-equation is the reference's, so the total
Cauchy stress is σ_skel + (∂W_bulk/∂Φs) I = σ_skel − p_f I. Energies are per unit reference
volume, in Pa; pressures in Pa; Φs, Φs0 and Φf are volume fractions (1).

Φs lives in DG0: its equation holds pointwise (no derivative of Φs appears), and with P1
displacements on affine cells J is constant per cell, so DG0 is exact there.
"""

from __future__ import annotations

import copy
import math
import numbers
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from ufl.core.expr import Expr

from lungmech import checks
from lungmech.errors import ParameterError
from lungmech.fem.loads import Named
from lungmech.fem.materials import CiarletGeymonat, ExponentialCiarletGeymonat, Material, Sum
from lungmech.fem.ramp import Ramp


def skeleton(alpha: float, gamma: float, c1: float, c2: float) -> Sum:
    """The lung skeleton's law W_skel (scene ``law = "lung_skeleton"``): the exponential
    Ciarlet–Geymonat bulk term plus the CGNHMR shear terms.

    .. math:: W_skel(F) = α (e^{γ (J² − 1 − 2 ln J)} − 1) + c1 (I1 − 3 − 2 ln J) + c2 (I2 − 3 − 4 ln J)

    Parameters
    ----------
    alpha : float
        Volumetric stiffness α (Pa), > 0.
    gamma : float
        Exponential rate γ (1), > 0: how fast the volume stiffness grows.
    c1, c2 : float
        Shear coefficients (Pa), ≥ 0, with c1 + c2 > 0.

    Returns
    -------
    Sum
        ``Sum((ExponentialCiarletGeymonat(alpha, gamma), CiarletGeymonat(0, c1, c2)))``.

    Notes
    -----
    Small-strain limit: μ = 2(c1 + c2), λ = 4(αγ + c2) (per unit solid volume when the
    formulation scales the skeleton by Φs0). ψ → ∞ as J → 0. The bundled lung scene uses
    α = 160 Pa, γ = 0.5, c1 = 200 Pa, c2 = 400 Pa.
    """
    for name, value in (("alpha", alpha), ("gamma", gamma)):
        checks.real(name, value, positive=True)
    for name, value in (("c1", c1), ("c2", c2)):
        checks.real(name, value, nonnegative=True)
    if c1 + c2 == 0:
        raise ParameterError("the skeleton needs shear stiffness: c1 + c2 must be > 0")
    return Sum((ExponentialCiarletGeymonat(alpha, gamma), CiarletGeymonat(0.0, c1, c2)))


ReferenceFraction = float | Callable[[np.ndarray], np.ndarray] | str | Path


@dataclass(frozen=True)
class Poromechanics:
    """The (u, Φs) formulation of the lung (scene ``type = "poromechanics"``): a skeleton law
    plus the solid bulk energy W_bulk(Φs) and an optional porosity barrier W_pore(Φf).

    .. math:: Π(u, Φs) = ∫ [s·ψ(F) + W_bulk(Φs) + W_pore(J − Φs)] dX + (load potentials)

    with W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)), s = Φs0 if ``scale_skeleton`` else 1, and
    W_pore(Φf) = η(lower/r − 1)² for r < lower, η(r/upper − 1)² for r > upper, else 0, where
    r = Φf/Φf0 = Φf/(1 − Φs0). u is Lagrange P_k, Φs is DG0 (cellwise); ψ is any law, normally
    :func:`skeleton`. The alveolar pressure enters as a load (:class:`AlveolarPressure`).

    Parameters
    ----------
    kappa : float
        Solid bulk modulus κ (Pa), > 0. At equilibrium without W_pore, Φs = 1/(1/Φs0 + p_f/κ):
        κ ≫ |p_f| keeps the solid nearly incompressible.
    phi_s0 : float, callable or path
        Reference solid volume fraction Φs0 (1) in (0, 1): a number, a function of the points
        (array of shape (3, n) -> n values, evaluated at cell midpoints), or a ``.npy``/``.txt``
        file with one value per cell in the mesh file's cell order.
    scale_skeleton : bool
        Multiply ψ by Φs0 (skeleton parameters then count per unit of solid volume, so denser
        tissue is stiffer). Default False.
    pore_barrier : float
        η (Pa) of the porosity barrier W_pore, ≥ 0; 0 (the default) leaves it out.
    pore_range : (float, float)
        (lower, upper) bounds (1) of r = Φf/Φf0 between which W_pore vanishes, with
        0 ≤ lower < 1 < upper ≤ inf; default (0.5, inf). Below ``lower`` the barrier resists
        alveolar collapse, above ``upper`` overdistension. W_pore is C¹ at the bounds, and the
        collapse branch grows without limit as r → 0.

    Notes
    -----
    The Φs-equation is ∂W_bulk/∂Φs − ∂W_pore/∂Φf + p_f = 0 in every cell. The residual of Φs is
    an energy (J). Model of Patte, Genet & Chapelle (2022), quasi-static.
    """

    kappa: float
    phi_s0: ReferenceFraction
    scale_skeleton: bool = False
    pore_barrier: float = 0.0
    pore_range: tuple[float, float] = (0.5, math.inf)
    fields: ClassVar[tuple[str, ...]] = ("phi_s",)
    residual_units: ClassVar[dict[str, str]] = {"phi_s": "J"}  # ∫ (∂W/∂Φs + p_f) δΦs dX, Pa·m³

    def __post_init__(self):
        checks.real("lung bulk modulus kappa", self.kappa, positive=True)
        if isinstance(self.phi_s0, numbers.Real | bool):
            checks.real("phi_s0", self.phi_s0)
            if not 0 < self.phi_s0 < 1:
                raise ParameterError(f"reference solid fraction phi_s0 must lie in (0, 1) (got {self.phi_s0})")
        elif not (callable(self.phi_s0) or isinstance(self.phi_s0, str | Path | fem.Function)):
            raise ParameterError(f"phi_s0 must be a number or a file of cell values (got {self.phi_s0!r})")
        checks.boolean("scale_skeleton", self.scale_skeleton)
        checks.real("pore_barrier", self.pore_barrier, nonnegative=True)
        if isinstance(self.pore_range, str) or not isinstance(self.pore_range, Sequence) or len(self.pore_range) != 2:
            raise ParameterError(f"pore_range must be two numbers [lower, upper] (got {self.pore_range!r})")
        lower = checks.real("pore_range[0]", self.pore_range[0])
        upper = checks.real("pore_range[1]", self.pore_range[1], infinite=True)
        if not 0 <= lower < 1 < upper:
            raise ParameterError(f"pore_range must satisfy 0 <= lower < 1 < upper (got {self.pore_range})")
        object.__setattr__(self, "pore_range", (float(lower), float(upper)))

    def bind(self, mesh) -> Poromechanics:
        """This formulation on ``mesh``: Φs0 as a cellwise (DG0) field, κ and η as ``fem.Constant``s
        (parameters change them without recompiling; η = 0 leaves the barrier out of the forms)."""
        if isinstance(self.kappa, fem.Constant):
            return self
        bound = copy.copy(self)  # not replace(): the checks of __post_init__ are for numbers
        phi_s0 = self.phi_s0 if isinstance(self.phi_s0, fem.Function) else reference_fraction(self.phi_s0, mesh)
        object.__setattr__(bound, "phi_s0", phi_s0)
        object.__setattr__(bound, "kappa", fem.Constant(mesh, float(self.kappa)))
        if self.pore_barrier > 0:
            object.__setattr__(bound, "pore_barrier", fem.Constant(mesh, float(self.pore_barrier)))
        return bound

    def check(self, material: Material, degree: int) -> None:
        """Every law and degree is accepted (an incompressible law fails in ``psi``)."""

    def elements(self, cell: str, degree: int, quadrature_degree: int) -> list:
        """Φs in DG0: its equation has no derivative of Φs, so it holds cell by cell."""
        return [basix.ufl.element("DG", cell, 0)]

    def skeleton_energy(self, material: Material, F: Expr) -> Expr:
        """s·ψ(F) (Pa), s = Φs0 if ``scale_skeleton`` else 1."""
        return self.phi_s0 * material.psi(F) if self.scale_skeleton else material.psi(F)

    def bulk_energy(self, phi_s: Expr) -> Expr:
        """W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)) (Pa), zero with zero slope at Φs = Φs0."""
        ratio = phi_s / self.phi_s0
        return self.kappa * (ratio - 1 - ufl.ln(ratio))

    def bulk_stress(self, phi_s: Expr) -> Expr:
        """∂W_bulk/∂Φs = κ(1/Φs0 − 1/Φs): at equilibrium the mean stress the solid bulk adds (≈ −p_f)."""
        return self.kappa * (1 / self.phi_s0 - 1 / phi_s)

    def pore_energy(self, phi_f: Expr) -> Expr:
        """W_pore(Φf) (Pa): η(lower/r − 1)² below ``lower``, η(r/upper − 1)² above ``upper``,
        r = Φf/(1 − Φs0); a bound at 0 or inf leaves its branch out."""
        r = phi_f / (1 - self.phi_s0)
        lower, upper = self.pore_range
        collapse = ufl.conditional(ufl.lt(r, lower), (lower / r - 1) ** 2, 0) if lower > 0 else 0
        overdistension = ufl.conditional(ufl.gt(r, upper), (r / upper - 1) ** 2, 0) if math.isfinite(upper) else 0
        return self.pore_barrier * (collapse + overdistension)

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """s·ψ(F) + W_bulk(Φs) (+ W_pore(J − Φs) when η > 0), in Pa."""
        phi_s = fields["phi_s"]
        density = self.skeleton_energy(material, F) + self.bulk_energy(phi_s)
        if not (isinstance(self.pore_barrier, numbers.Real) and self.pore_barrier == 0):
            density += self.pore_energy(ufl.det(F) - phi_s)
        return density

    def initial_values(self) -> dict[str, float | fem.Function]:
        """Φs starts at Φs0 (the unloaded state)."""
        return {"phi_s": self.phi_s0}

    def output_fields(self, model) -> dict[str, Expr]:
        """The lung's cellwise fields for outputs (see :func:`fields`)."""
        return fields(model)


def reference_fraction(value: ReferenceFraction, mesh) -> fem.Function:
    """Φs0 as a DG0 field, checked to lie in (0, 1) everywhere."""
    space = fem.functionspace(mesh, ("DG", 0))
    phi_s0 = fem.Function(space, name="phi_s0")
    if isinstance(value, numbers.Real):
        phi_s0.x.array[:] = value
    elif callable(value):
        phi_s0.interpolate(lambda x: np.broadcast_to(value(x), x.shape[1]))
    else:
        phi_s0.x.array[:] = _cell_values(Path(value), mesh)
    local = phi_s0.x.array[: space.dofmap.index_map.size_local]
    if not mesh.comm.allreduce(bool(np.isfinite(local).all()), op=MPI.LAND):
        raise ParameterError("reference solid fraction phi_s0 has values that are not finite numbers (nan or inf)")
    low = mesh.comm.allreduce(local.min() if local.size else np.inf, op=MPI.MIN)
    high = mesh.comm.allreduce(local.max() if local.size else -np.inf, op=MPI.MAX)
    if not 0 < low <= high < 1:
        raise ParameterError(f"reference solid fraction phi_s0 must lie in (0, 1) (got values in [{low:g}, {high:g}])")
    return phi_s0


def _cell_values(path: Path, mesh) -> np.ndarray:
    """One value per cell from a file in the mesh's input cell order, for this rank's cells."""
    if not path.is_file():
        raise ParameterError(f"phi_s0 file '{path}' not found")
    try:
        with warnings.catch_warnings():  # an empty file is reported below, not as a warning
            warnings.simplefilter("ignore")
            values = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path, ndmin=1)
        values = np.asarray(values, dtype=float).ravel()
    except (ValueError, TypeError, OSError, EOFError) as e:
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ParameterError(f"phi_s0 file '{path}' is not a list of numbers ({message})") from None
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise ParameterError(
            f"phi_s0 file '{path}' holds values that are not finite numbers (first: {values[bad]} for cell {bad})"
        )
    total = mesh.topology.index_map(mesh.topology.dim).size_global
    if values.size != total:
        raise ParameterError(f"phi_s0 file '{path}' has {values.size} values; the mesh has {total} cells")
    cells = mesh.topology.index_map(mesh.topology.dim)
    original = np.asarray(mesh.topology.original_cell_index)[: cells.size_local + cells.num_ghosts]
    return values[original]


@dataclass(frozen=True)
class AlveolarPressure(Named):
    """Air pressure p_f in the alveoli ("internal" loading): the potential −p_f Φf = −p_f (J − Φs).

    Scene load ``type = "alveolar_pressure"``. Needs the :class:`Poromechanics` formulation.

    Parameters
    ----------
    value : float
        p_f (Pa) at ramp value 1; positive inflates (a ventilator's pressure).
    ramp : Ramp
        The factor (1) ``value`` is multiplied by at time t (s); default 0 → 1 over t ∈ [0, 1]
        (:class:`lungmech.fem.ramp.Ramp`).
    name : str
        Its label in outputs (default "alveolar pressure").
    """

    value: float
    ramp: Ramp = field(default_factory=Ramp)
    name: str = ""
    kind: ClassVar[str] = "alveolar pressure"

    def __post_init__(self):
        self._check(vector=False)

    def potential(self, model, value: Expr) -> ufl.Form:
        """−∫ p_f (J − Φs) dX (J): the work of the air pressure on the air volume."""
        return -value * (ufl.det(model.F) - model.fields["phi_s"]) * model.dx


def stresses(model) -> dict[str, Expr]:
    """The Cauchy stress split: skeleton (from W_skel), bulk (∂W_bulk/∂Φs I) and their sum, the total.

    At equilibrium the bulk part equals (∂W_pore/∂Φf − p_f) I, so the total is the stress the
    lung carries: σ_skel − p_f I without the porosity barrier.
    """
    formulation, F = model.formulation, model.F
    J = ufl.det(F)
    skeleton = ufl.diff(formulation.skeleton_energy(model.material, F), F) * F.T / J
    bulk = formulation.bulk_stress(model.fields["phi_s"]) * ufl.Identity(3)
    return {"skeleton": skeleton, "bulk": bulk, "total": skeleton + bulk}


def fields(model) -> dict[str, Expr]:
    """Cellwise scalars of the lung: Φs0, Φs, φf = 1 − Φs/J (current porosity) and the mean stresses."""
    phi_s, J = model.fields["phi_s"], ufl.det(model.F)
    scalars = {"phi_s0": model.formulation.phi_s0, "phi_s": phi_s, "porosity": 1 - phi_s / J}
    return scalars | {f"mean_stress_{name}": ufl.tr(sigma) / 3 for name, sigma in stresses(model).items()}


def averages(model) -> dict[str, Callable[[], float]]:
    """Averages of the lung's fractions, strain and stresses, compiled once.

    Per reference volume: Φs (solid), Φf = J − Φs (air), φs = Φs/J (current solid fraction),
    the mean Green–Lagrange strain tr(E)/3. Per current volume: the mean normal stress tr(σ)/3
    of the skeleton, bulk and total stresses.
    """
    from lungmech.fem.kinematics import green_lagrange
    from lungmech.fem.quantities import integral

    comm = model.geometry.mesh.comm
    volume = model.geometry.volume()
    J, phi_s = ufl.det(model.F), model.fields["phi_s"]
    per_reference = {
        "phi_s": phi_s,
        "phi_f": J - phi_s,
        "phi_s_current": phi_s / J,
        "green_lagrange_mean": ufl.tr(green_lagrange(model.F)) / 3,
    }
    per_current = {f"mean_stress_{name}": ufl.tr(sigma) / 3 for name, sigma in stresses(model).items()}
    current_volume = integral(J * model.dx, comm)
    means = {name: integral(expr * model.dx, comm) for name, expr in per_reference.items()}
    weighted = {name: integral(expr * J * model.dx, comm) for name, expr in per_current.items()}
    return {name: (lambda f=f: f() / volume) for name, f in means.items()} | {
        name: (lambda f=f: f() / current_volume()) for name, f in weighted.items()
    }
