"""The quasi-static poromechanical lung model of Patte, Genet & Chapelle (2022).

Unknowns: the displacement u and Φs, the current solid volume per unit reference volume
(Φf = J − Φs is the fluid, i.e. air, volume). The total potential is

    Π(u, Φs) = ∫ s·W_skel(F) + W_bulk(Φs) + W_pore(J − Φs) − p_f (J − Φs) dX  + (pleural loads),

W_skel = α(e^{γ(J²−1−2lnJ)} − 1) + c1(I1−3−2lnJ) + c2(I2−3−4lnJ) (:func:`skeleton`),
W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)), the optional porosity barrier W_pore and the scalings
by Φs0 as in :class:`Poromechanics`; p_f is the alveolar (air) pressure
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
from typing import TYPE_CHECKING, ClassVar, cast

from mpi4py import MPI

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from lungmech import checks, jit
from lungmech.errors import ParameterError
from lungmech.fem.averages import Average
from lungmech.fem.loads import Named
from lungmech.fem.materials import CiarletGeymonat, ExponentialCiarletGeymonat, Material, Sum
from lungmech.fem.ramp import Ramp

if TYPE_CHECKING:
    import dolfinx.mesh

    from lungmech.fem.model import Model


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
    return Sum((ExponentialCiarletGeymonat(alpha, gamma), CiarletGeymonat(0.0, c1, c2)), label="lung_skeleton")


CellValues = float | Callable[[np.ndarray], np.ndarray] | str | Path  # a number, a function of x, a file

SCALINGS = {  # which energies Φs0 multiplies (Patte et al. 2022; dolfin_mech's "linear" is all three)
    "none": (),
    "skeleton": ("skeleton",),
    "linear": ("skeleton", "bulk", "pore"),
}


@dataclass(frozen=True)
class Poromechanics:
    """The (u, Φs) formulation of the lung (scene ``type = "poromechanics"``): a skeleton law
    plus the solid bulk energy W_bulk(Φs) and an optional porosity barrier W_pore(Φf).

    .. math:: Π(u, Φs) = ∫ [s_skel ψ(F) + s_bulk (W_bulk(Φs) + W_pore(J − Φs))] dX + (load potentials)

    with W_bulk = κ(Φs/Φs0 − 1 − ln(Φs/Φs0)) and the porosity barrier, of r = Φf/Φf0 =
    Φf/(1 − Φs0),

    .. math:: W_pore = η (lower/r − 1)^m  (r < lower),   η (r/upper − 1)^m  (r > upper),   0 between.

    The scalings s_skel, s_bulk are Φs0 or 1 as ``scaling`` says. u is Lagrange P_k, Φs is DG0
    (cellwise); ψ is any law, normally :func:`skeleton`. The alveolar pressure enters as a load
    (:class:`AlveolarPressure`). Energies are per unit reference volume (Pa); with a scaling,
    the scaled law's parameters count per unit of solid volume, so denser tissue is stiffer.

    Parameters
    ----------
    kappa : float, callable or path
        Solid bulk modulus κ (Pa), > 0. At equilibrium without W_pore, Φs = 1/(1/Φs0 + p_f/(s_bulk κ)):
        κ ≫ |p_f| keeps the solid nearly incompressible.
    phi_s0 : float, callable or path
        Reference solid volume fraction Φs0 (1) in (0, 1), in the unloaded reference.
    scaling : str
        "none" (default), "skeleton" (s_skel = Φs0) or "linear" (s_skel = s_bulk = Φs0: the
        skeleton, bulk and pore energies, as dolfin_mech's ``scaling = "linear"``).
    pore_barrier : float, callable or path
        η (Pa) of the porosity barrier W_pore, ≥ 0; 0 (the default) leaves it out.
    pore_range : (float, float)
        (lower, upper) bounds (1) of r between which W_pore vanishes, 0 ≤ lower ≤ 1 ≤ upper ≤ inf;
        default (0.5, inf). Below ``lower`` the barrier resists alveolar collapse, above
        ``upper`` overdistension; the collapse branch grows without limit as r → 0.
    pore_exponent : float
        m > 1 (default 2): W_pore is C¹ at the bounds. dolfin_mech's barrier with its exponents
        (n, p, q) is m = n + 1, lower = Φf0^(p−1), upper = Φf0^(1/q−1): for its default
        n = p = q = 1, ``pore_range = [1, 1]`` and m = 2.
    imaged_porosity : float, callable or path
        Instead of ``phi_s0``: the porosity φf = 1 − Φs/J (1, in (0, 1)) of the imaged, loaded
        lung — what CT gives. Φs0 is then an unknown of the inverse problem
        (:func:`lungmech.lung.inverse.unloaded_reference`), which finds the reference geometry
        and Φs0 together; until then Φs0 = 1 − imaged_porosity.

    A field (callable or path) is cellwise: a function of the points (array of shape (3, n) ->
    n values, evaluated at cell midpoints), or a ``.npy``/``.txt`` file with one value per cell
    in the mesh file's cell order.

    Notes
    -----
    The Φs-equation is s_bulk (∂W_bulk/∂Φs − ∂W_pore/∂Φf) + p_f = 0 in every cell. The residual
    of Φs is an energy (J). Model of Patte, Genet & Chapelle (2022), quasi-static.
    """

    kappa: CellValues
    phi_s0: CellValues | None = None
    scaling: str = "none"
    pore_barrier: CellValues = 0.0
    pore_range: tuple[float, float] = (0.5, math.inf)
    pore_exponent: float = 2.0
    imaged_porosity: CellValues | None = None
    fields: ClassVar[tuple[str, ...]] = ("phi_s",)
    residual_units: ClassVar[dict[str, str]] = {"phi_s": "J"}  # ∫ (∂W/∂Φs + p_f) δΦs dX, Pa·m³
    cellwise: ClassVar[tuple[str, ...]] = ("kappa", "phi_s0", "pore_barrier", "imaged_porosity")

    def __post_init__(self) -> None:
        if (self.phi_s0 is None) == (self.imaged_porosity is None):
            raise ParameterError(
                "poromechanics needs exactly one of phi_s0 (the reference solid fraction) or imaged_porosity "
                f"(the porosity of the imaged lung) (got phi_s0 = {self.phi_s0!r}, imaged_porosity = "
                f"{self.imaged_porosity!r})"
            )
        for name in self.cellwise:
            value = getattr(self, name)
            if value is None or not isinstance(value, numbers.Real | bool):
                if value is not None and not (callable(value) or isinstance(value, str | Path | fem.Function)):
                    raise ParameterError(f"{name} must be a number or a file of cell values (got {value!r})")
                continue
            checks.real("lung bulk modulus kappa" if name == "kappa" else name, value)
            _CELLWISE[name].check(float(value), name)
        if self.scaling not in SCALINGS:
            raise ParameterError(f"scaling must be one of {', '.join(map(repr, SCALINGS))} (got {self.scaling!r})")
        if isinstance(self.pore_range, str) or not isinstance(self.pore_range, Sequence) or len(self.pore_range) != 2:
            raise ParameterError(f"pore_range must be two numbers [lower, upper] (got {self.pore_range!r})")
        lower = checks.real("pore_range[0]", self.pore_range[0])
        upper = checks.real("pore_range[1]", self.pore_range[1], infinite=True)
        if not 0 <= lower <= 1 <= upper:
            raise ParameterError(f"pore_range must satisfy 0 <= lower <= 1 <= upper (got {self.pore_range})")
        object.__setattr__(self, "pore_range", (float(lower), float(upper)))
        checks.real("pore_exponent", self.pore_exponent)
        if not self.pore_exponent > 1:
            raise ParameterError(
                f"pore_exponent must be > 1 (got {self.pore_exponent}): the barrier is C¹ at its bounds"
            )

    def bind(self, mesh: dolfinx.mesh.Mesh) -> Poromechanics:
        """This formulation on ``mesh``: fields as cellwise (DG0) functions, numbers of κ and η as
        ``fem.Constant`` objects (parameters change them without recompiling; η = 0 leaves the barrier
        out of the forms); Φs0 is always a field."""
        if isinstance(self.kappa, fem.Constant | fem.Function):
            return self
        bound = copy.copy(self)  # not replace(): the checks of __post_init__ are for numbers
        for name in self.cellwise:
            value = getattr(self, name)
            if value is None or isinstance(value, fem.Function):
                continue
            if isinstance(value, numbers.Real) and name in ("kappa", "pore_barrier"):
                value = fem.Constant(mesh, float(value)) if name == "kappa" or cast(float, value) > 0 else 0.0
            else:
                value = cell_values(value, mesh, name)
            object.__setattr__(bound, name, value)
        if bound.imaged_porosity is not None:  # the first guess of the inverse problem: Φs0 ≈ Φs = J φs
            imaged = cast(fem.Function, bound.imaged_porosity)  # a cellwise field now
            phi_s0 = fem.Function(imaged.function_space, name="phi_s0")
            phi_s0.x.array[:] = 1.0 - imaged.x.array
            object.__setattr__(bound, "phi_s0", phi_s0)
        return bound

    def check(self, material: Material, degree: int) -> None:
        """Every law and degree is accepted (an incompressible law fails in ``psi``)."""

    def elements(self, cell: basix.CellType, degree: int, quadrature_degree: int) -> list:
        """Φs in DG0: its equation has no derivative of Φs, so it holds cell by cell."""
        return [basix.ufl.element("DG", cell, 0)]

    def scale(self, energy: str) -> Expr | float:
        """s_energy: Φs0 where ``scaling`` scales that energy ("skeleton", "bulk", "pore"), else 1."""
        return cast(Expr, self.phi_s0) if energy in SCALINGS[self.scaling] else 1.0  # bound: a cellwise field

    def skeleton_energy(self, material: Material, F: Expr) -> Expr:
        """s_skel ψ(F) (Pa)."""
        return self.scale("skeleton") * material.psi(F)

    def bulk_energy(self, phi_s: Expr) -> Expr:
        """s_bulk W_bulk = s_bulk κ(Φs/Φs0 − 1 − ln(Φs/Φs0)) (Pa), zero with zero slope at Φs = Φs0."""
        ratio = phi_s / self.phi_s0
        return self.scale("bulk") * cast(Expr, self.kappa) * (ratio - 1 - ufl.ln(ratio))  # bound: UFL

    def bulk_stress(self, phi_s: Expr) -> Expr:
        """∂(s_bulk W_bulk)/∂Φs = s_bulk κ(1/Φs0 − 1/Φs): at equilibrium the mean stress the solid
        bulk adds (≈ −p_f)."""
        kappa, phi_s0 = cast(Expr, self.kappa), cast(Expr, self.phi_s0)  # bound: UFL
        return self.scale("bulk") * kappa * (1 / phi_s0 - 1 / phi_s)

    def pore_energy(self, phi_f: Expr) -> Expr:
        """s_bulk W_pore(Φf) (Pa): η(lower/r − 1)^m below ``lower``, η(r/upper − 1)^m above
        ``upper``, r = Φf/(1 − Φs0); a bound at 0 or inf leaves its branch out."""
        r = phi_f / (1 - cast(Expr, self.phi_s0))  # bound: a cellwise field
        (lower, upper), m = self.pore_range, self.pore_exponent
        collapse = ufl.conditional(ufl.lt(r, lower), (lower / r - 1) ** m, 0) if lower > 0 else 0
        overdistension = ufl.conditional(ufl.gt(r, upper), (r / upper - 1) ** m, 0) if math.isfinite(upper) else 0
        return self.scale("pore") * cast(Expr, self.pore_barrier) * (collapse + overdistension)  # bound, not 0

    def energy_density(self, material: Material, F: Expr, fields: dict[str, Expr]) -> Expr:
        """s_skel ψ(F) + s_bulk W_bulk(Φs) (+ s_bulk W_pore(J − Φs) when η is not 0), in Pa."""
        phi_s = fields["phi_s"]
        density = self.skeleton_energy(material, F) + self.bulk_energy(phi_s)
        if not (isinstance(self.pore_barrier, numbers.Real) and self.pore_barrier == 0):
            density += self.pore_energy(ufl.det(F) - phi_s)
        return density

    def initial_values(self) -> dict[str, float | fem.Function]:
        """Φs starts at Φs0 (the unloaded state)."""
        return {"phi_s": cast(fem.Function, self.phi_s0)}  # bound: a cellwise field

    def imaged(self, model: Model) -> ImagedPorosity | None:
        """What an inverse problem matches besides the geometry: the imaged porosity (or None)."""
        return None if self.imaged_porosity is None else ImagedPorosity(model)

    def output_fields(self, model: Model) -> dict[str, Expr]:
        """The lung's cellwise fields for outputs (see :func:`fields`)."""
        return fields(model)

    def averages(self, model: Model) -> dict[str, Average]:
        """The lung's averages (see :func:`averages`), reported as outputs."""
        return averages(model)


@dataclass(frozen=True)
class _Range:
    """Where a cellwise value may lie: above ``low`` (or at it, if ``closed``), below ``high``."""

    what: str
    low: float
    high: float = math.inf
    closed: bool = False

    def check(self, value: float, name: str, shown: str = "") -> None:
        above = value >= self.low if self.closed else value > self.low
        if not (above and value < self.high):
            if math.isfinite(self.high):
                where = f"lie in {'[' if self.closed else '('}{self.low:g}, {self.high:g})"
            else:
                where = f"be {'>=' if self.closed else '>'} {self.low:g}"
            raise ParameterError(f"{self.what} {name} must {where} (got {shown or value})")


_CELLWISE = {
    "kappa": _Range("lung bulk modulus", 0.0),
    "phi_s0": _Range("reference solid fraction", 0.0, 1.0),
    "pore_barrier": _Range("porosity barrier", 0.0, closed=True),
    "imaged_porosity": _Range("imaged porosity", 0.0, 1.0),
}


def cell_values(value: CellValues, mesh: dolfinx.mesh.Mesh, name: str) -> fem.Function:
    """The cellwise (DG0) field ``name`` (one of :attr:`Poromechanics.cellwise`) from a number, a
    function of the points or a file of cell values, checked to lie in its range everywhere."""
    space = fem.functionspace(mesh, ("DG", 0))
    field_ = fem.Function(space, name=name)
    if isinstance(value, numbers.Real):
        field_.x.array[:] = value
    elif callable(value):
        field_.interpolate(lambda x: np.broadcast_to(value(x), x.shape[1]))
    else:
        field_.x.array[:] = _cell_values(Path(cast(str | Path, value)), mesh, name)  # not a number, nor a function
    local = field_.x.array[: space.dofmap.index_map.size_local]
    allowed = _CELLWISE[name]
    if not mesh.comm.allreduce(bool(np.isfinite(local).all()), op=MPI.LAND):
        raise ParameterError(f"{allowed.what} {name} has values that are not finite numbers (nan or inf)")
    low = mesh.comm.allreduce(local.min() if local.size else np.inf, op=MPI.MIN)
    high = mesh.comm.allreduce(local.max() if local.size else -np.inf, op=MPI.MAX)
    allowed.check(low, name, f"values in [{low:g}, {high:g}]")
    allowed.check(high, name, f"values in [{low:g}, {high:g}]")
    return field_


def reference_fraction(value: CellValues, mesh: dolfinx.mesh.Mesh) -> fem.Function:
    """Φs0 as a DG0 field, checked to lie in (0, 1) everywhere."""
    return cell_values(value, mesh, "phi_s0")


def _cell_values(path: Path, mesh: dolfinx.mesh.Mesh, name: str) -> np.ndarray:
    """One value per cell from a file in the mesh's input cell order, for this rank's cells."""
    values = read_cell_values(path, name)
    total = mesh.topology.index_map(mesh.topology.dim).size_global
    if values.size != total:
        raise ParameterError(f"{name} file '{path}' has {values.size} values; the mesh has {total} cells")
    cells = mesh.topology.index_map(mesh.topology.dim)
    original = np.asarray(mesh.topology.original_cell_index)[: cells.size_local + cells.num_ghosts]
    return values[original]


def read_cell_values(path: Path, name: str) -> np.ndarray:
    """The finite numbers of a file of cell values (``.npy``, or text), in its order."""
    if not path.is_file():
        raise ParameterError(f"{name} file '{path}' not found")
    try:
        with warnings.catch_warnings():  # an empty file is reported below, not as a warning
            warnings.simplefilter("ignore")
            values = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path, ndmin=1)
        values = np.asarray(values, dtype=float).ravel()
    except (ValueError, TypeError, OSError, EOFError) as e:
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ParameterError(f"{name} file '{path}' is not a list of numbers ({message})") from None
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise ParameterError(
            f"{name} file '{path}' holds values that are not finite numbers (first: {values[bad]} for cell {bad})"
        )
    return values


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

    def __post_init__(self) -> None:
        self._check(vector=False)

    def potential(self, model: Model, value: Expr) -> ufl.Form:
        """−∫ p_f (J − Φs) dX (J): the work of the air pressure on the air volume."""
        return -value * (ufl.det(model.F) - model.fields["phi_s"]) * model.dx


class ImagedPorosity:
    """The porosity of an imaged lung as data of the inverse problem: each cell's current porosity
    φf = 1 − Φs V/v (V, v its reference and current volumes; Φs is cellwise) against the imaged
    φ̂f, and the update of Φs0 that matches them.

    The correction scales each cell's Φs0 by the ratio of the solid fraction it needs, Φs* =
    (1 − φ̂f) v/V, to the one it has: ln Φs0 += ln(Φs*/Φs). The solid is nearly incompressible
    (κ ≫ |p_f|), so Φs/Φs0 hardly depends on Φs0 and one correction nearly matches the porosity
    of the current geometry. Where Φs0 also scales the skeleton, it changes the geometry too: the
    inverse problem relaxes both corrections together.
    """

    def __init__(self, model: Model) -> None:
        formulation = cast(Poromechanics, model.formulation)  # the lung's, bound: its fields are Functions
        self.phi_s0 = cast(fem.Function, formulation.phi_s0)
        self.target = cast(fem.Function, formulation.imaged_porosity)
        space = self.phi_s0.function_space  # DG0: entries are cells
        self.owned = space.dofmap.index_map.size_local
        self.comm = model.geometry.mesh.comm
        v = ufl.TestFunction(space)
        self._volumes = [jit.form(v * model.dx), jit.form(ufl.det(model.F) * v * model.dx)]  # V, v
        self._solid = model.state.sub(1)
        self._phi_s = fem.Function(space)  # Φs in Φs0's numbering

    def _fractions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Φs, V/v and φ̂f of this rank's cells."""
        reference, current = (fem.assemble_vector(form).array[: self.owned] for form in self._volumes)
        self._phi_s.interpolate(self._solid)
        return self._phi_s.x.array[: self.owned], reference / current, self.target.x.array[: self.owned]

    def mismatch(self) -> float:
        """max |φf − φ̂f| over all cells, φf = 1 − Φs V/v (collective)."""
        phi_s, ratio, imaged = self._fractions()
        local = float(np.abs(1.0 - phi_s * ratio - imaged).max(initial=0.0))
        return self.comm.allreduce(local, op=MPI.MAX)

    def correction(self) -> np.ndarray:
        """ln(Φs*/Φs) of this rank's cells, Φs* = (1 − φ̂f) v/V: the fixed point's step in ln Φs0."""
        phi_s, ratio, imaged = self._fractions()
        return np.log((1.0 - imaged) / (ratio * phi_s))

    def reset(self) -> None:
        """Φs0 back at its first guess, 1 − φ̂f (collective: ghosts follow)."""
        self.phi_s0.x.array[:] = 1.0 - self.target.x.array
        self.phi_s0.x.scatter_forward()

    def apply(self, step: np.ndarray) -> None:
        """ln Φs0 += step in this rank's cells (collective: ghosts follow)."""
        self.phi_s0.x.array[: self.owned] *= np.exp(step)
        self.phi_s0.x.scatter_forward()


def stresses(model: Model) -> dict[str, Expr]:
    """The Cauchy stress split: skeleton (from W_skel), bulk (∂W_bulk/∂Φs I) and their sum, the total.

    At equilibrium the bulk part equals (∂W_pore/∂Φf − p_f) I, so the total is the stress the
    lung carries: σ_skel − p_f I without the porosity barrier.
    """
    formulation, F = cast(Poromechanics, model.formulation), model.F  # the lung's
    J = ufl.det(F)
    skeleton = ufl.diff(formulation.skeleton_energy(model.material, F), F) * F.T / J
    bulk = formulation.bulk_stress(model.fields["phi_s"]) * ufl.Identity(3)
    return {"skeleton": skeleton, "bulk": bulk, "total": skeleton + bulk}


def fields(model: Model) -> dict[str, Expr]:
    """Cellwise scalars of the lung: Φs0, Φs, φf = 1 − Φs/J (current porosity) and the mean stresses."""
    phi_s, J = model.fields["phi_s"], ufl.det(model.F)
    phi_s0 = cast(Poromechanics, model.formulation).phi_s0  # the lung's
    scalars = {"phi_s0": phi_s0, "phi_s": phi_s, "porosity": 1 - phi_s / J}
    return scalars | {f"mean_stress_{name}": ufl.tr(sigma) / 3 for name, sigma in stresses(model).items()}


def averages(model: Model) -> dict[str, Average]:
    """The lung's averages: per reference volume, Φs (solid), Φf = J − Φs (air), φs = Φs/J
    (current solid fraction) and the mean Green–Lagrange strain tr(E)/3; per current volume,
    the mean normal stress tr(σ)/3 (Pa) of the skeleton, bulk and total stresses."""
    from lungmech.fem.kinematics import green_lagrange

    J, phi_s = ufl.det(model.F), model.fields["phi_s"]
    per_reference = {
        "phi_s": phi_s,
        "phi_f": J - phi_s,
        "phi_s_current": phi_s / J,
        "green_lagrange_mean": ufl.tr(green_lagrange(model.F)) / 3,
    }
    per_current = {f"mean_stress_{name}": ufl.tr(sigma) / 3 for name, sigma in stresses(model).items()}
    return {name: Average(f, "1") for name, f in per_reference.items()} | {
        name: Average(f, "Pa", per="current") for name, f in per_current.items()
    }
