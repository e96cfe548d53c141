"""Parameters: validated with clear errors; small-strain consistency of the (E, ν) constructors."""

import math
import re

from mpi4py import MPI

import analytic as A
import numpy as np
import pytest
import ufl

from lungmech.errors import ParameterError
from lungmech.fem import materials as M
from lungmech.fem.model import Model
from lungmech.mesh import box


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: M.NeoHookean.from_young(-1.0, 0.3), "E must be > 0"),
        (lambda: M.NeoHookean.from_young(0.0, 0.3), "E must be > 0"),
        (lambda: M.NeoHookean.from_young(1.0, 0.5), "-1 < nu < 0.5"),
        (lambda: M.StableNeoHookean.from_young(1.0, -1.0), "-1 < nu < 0.5"),
        (lambda: M.NeoHookean(-1.0, 1.0), "shear modulus mu must be > 0"),
        (lambda: M.SaintVenantKirchhoff(1.0, -1.0), "bulk modulus"),
        (lambda: M.CiarletGeymonat(-1.0, 1.0), "c0, c1, c2 >= 0"),
        (lambda: M.ExponentialCiarletGeymonat(0.1, 0.0), "gamma > 0"),
        (lambda: M.MooneyRivlin(0.0, 0.0, 1.0), "c1 + c2 > 0"),
        (lambda: M.LinearElastic.from_young(float("nan"), 0.3), "finite number"),
        (lambda: M.NeoHookean.from_young(float("inf"), 0.3), "parameter 'E' must be a finite number"),
        (lambda: M.LinearElastic(1.0, float("inf")), "lmbda must be finite"),
        (lambda: M.SaintVenantKirchhoff(1.0, float("inf")), "lmbda must be finite"),
        (lambda: M.NeoHookean("1 kPa", 1.0), "parameter 'mu' must be a number"),
        (lambda: M.ExponentialCiarletGeymonat(float("inf"), 1.0), "parameter 'alpha' must be a finite number"),
        (lambda: M.MooneyRivlin(1.0, 1.0, float("-inf")), "finite number or +inf"),
        (lambda: M.Sum(()), "at least one law"),
    ],
)
def test_bad_parameters(make, message):
    with pytest.raises(ParameterError, match=re.escape(message)):
        make()


def test_formulation_checks():
    geometry = box(MPI.COMM_WORLD, cells=(1, 1, 1))
    with pytest.raises(ParameterError, match="needs degree >= 2"):
        Model(geometry, M.NeoHookean(1.0, 10.0), degree=1, mixed=True)
    with pytest.raises(ParameterError, match="no volumetric split"):
        Model(geometry, M.SaintVenantKirchhoff(1.0, 1.0), degree=2, mixed=True)
    with pytest.raises(ParameterError, match="needs the mixed formulation"):
        Model(geometry, M.NeoHookean.incompressible(1.0))


@pytest.mark.parametrize(
    "law, reference, params",
    [
        (M.NeoHookean.from_young(3.0, 0.35), "neo_hookean", None),
        (M.StableNeoHookean.from_young(3.0, 0.35), "stable_neo_hookean", None),
        (M.CiarletGeymonat.from_young(3.0, 0.35, c2_share=0.4), "ciarlet_geymonat", None),
        (M.MooneyRivlin.from_young(3.0, 0.35, c2_share=0.4), "mooney_rivlin", None),
    ],
)
def test_from_young_matches_small_strain(law, reference, params):
    """The (E, ν) constructors give a law whose linearisation has those E and ν."""
    if reference in ("neo_hookean", "stable_neo_hookean"):
        params = A.LameParams(law.mu, law.lmbda)
    elif reference == "ciarlet_geymonat":
        params = A.CiarletGeymonatParams(law.c0, law.c1, law.c2)
    else:
        params = A.MooneyRivlinParams(law.c1, law.c2, law.bulk)
    mu, lmbda = A.lame_of(reference, params)
    assert mu == pytest.approx(3.0 / (2 * 1.35), rel=1e-12)
    assert lmbda == pytest.approx(3.0 * 0.35 / (1.35 * 0.3), rel=1e-12)


def test_incompressible_limits_are_structural():
    assert math.isinf(M.NeoHookean.incompressible(1.0).bulk)
    assert math.isinf(M.MooneyRivlin.incompressible(0.5, 0.25).bulk)
    assert np.isinf(M.StableNeoHookean.incompressible(1.0).bulk)


def test_laws_registry_names():
    assert set(M.LAWS) == {
        "linear",
        "saint_venant_kirchhoff",
        "neo_hookean",
        "stable_neo_hookean",
        "mooney_rivlin",
        "ciarlet_geymonat",
        "exponential_ciarlet_geymonat",
    }


@pytest.mark.parametrize(
    "law, mu",
    [
        (M.NeoHookean(3.0, 7.0), 3.0),
        (M.NeoHookean.incompressible(3.0), 3.0),
        (M.MooneyRivlin(1.5, 0.25, 10.0), 2 * (1.5 + 0.25)),
        (M.SaintVenantKirchhoff(3.0, 7.0), 3.0),
        (M.LinearElastic(3.0, 7.0), 3.0),
        (M.CiarletGeymonat.from_young(9.0, 0.25), 9.0 / 2.5),
    ],
)
def test_the_shear_modulus_is_the_second_derivative_in_simple_shear(law, mu):
    """μ₀ = ∂²ψ/∂γ² of F = I + γ e₁⊗e₂ at γ = 0: the Lamé μ (Mooney–Rivlin: 2(c1 + c2);
    from E and ν: E / (2(1 + ν)))."""
    from dolfinx import fem

    mesh = box(MPI.COMM_SELF, cells=(1, 1, 1)).mesh
    value = fem.assemble_scalar(fem.form(M.shear_modulus(law, mesh) * ufl.dx(domain=mesh)))
    assert value == pytest.approx(mu, rel=1e-12)
