"""Every law reproduces homogeneous deformations and their closed-form stresses.

The references (tests/analytic.py) are hand-derived NumPy formulas, independent of UFL.
"""

import analytic as A
import numpy as np
import pytest
from fem import homogeneous, lateral_stretch, mean_cauchy, relative_error, uniaxial

from lungmech.fem import materials as M

MU, LMBDA = 1.3, 2.1
# A general (non-symmetric) deformation gradient with det F > 0.
F_BAR = np.array([[1.25, 0.20, -0.10], [-0.05, 0.90, 0.15], [0.10, -0.20, 1.10]])

LAWS = {
    "linear": (M.LinearElastic(MU, LMBDA), "linear", A.LameParams(MU, LMBDA)),
    "svk": (M.SaintVenantKirchhoff(MU, LMBDA), "svk", A.LameParams(MU, LMBDA)),
    "neo_hookean": (M.NeoHookean(MU, LMBDA), "neo_hookean", A.LameParams(MU, LMBDA)),
    "stable_neo_hookean": (M.StableNeoHookean(MU, LMBDA), "stable_neo_hookean", A.LameParams(MU, LMBDA)),
    "mooney_rivlin": (M.MooneyRivlin(0.4, 0.25, 3.0), "mooney_rivlin", A.MooneyRivlinParams(0.4, 0.25, 3.0)),
    "ciarlet_geymonat": (M.CiarletGeymonat(0.5, 0.3, 0.2), "ciarlet_geymonat", A.CiarletGeymonatParams(0.5, 0.3, 0.2)),
    "exponential_cg": (M.ExponentialCiarletGeymonat(0.16, 0.5), "exponential_cg", A.ExponentialCGParams(0.16, 0.5)),
}


@pytest.mark.parametrize("name", LAWS)
def test_general_homogeneous_deformation(name):
    law, reference, params = LAWS[name]
    model = homogeneous(law, F_BAR)
    assert relative_error(mean_cauchy(model), A.cauchy(reference, params, F_BAR)) < 1e-8


def test_sum_of_laws_is_sum_of_stresses():
    law = M.Sum((M.ExponentialCiarletGeymonat(0.16, 0.5), M.CiarletGeymonat(0.0, 0.2, 0.4)))
    expected = A.cauchy("exponential_cg", A.ExponentialCGParams(0.16, 0.5), F_BAR) + A.cauchy(
        "ciarlet_geymonat", A.CiarletGeymonatParams(0.0, 0.2, 0.4), F_BAR
    )
    assert relative_error(mean_cauchy(homogeneous(law, F_BAR)), expected) < 1e-8


@pytest.mark.parametrize("law_class", [M.NeoHookean, M.StableNeoHookean])
def test_mixed_formulation_nearly_incompressible(law_class):
    """ν = 0.4999: the Taylor–Hood formulation reproduces the compressible closed form."""
    law = law_class.from_young(1.0, 0.4999)
    F = np.diag([1.2, 0.95, 0.9]) + 0.05 * np.eye(3)[[1, 2, 0]]
    reference = A.cauchy(law_class.name, A.LameParams(law.mu, law.lmbda), F)
    assert relative_error(mean_cauchy(homogeneous(law, F, degree=2, mixed=True)), reference) < 1e-8


def test_mixed_mooney_rivlin_nearly_incompressible():
    law = M.MooneyRivlin.from_young(1.0, 0.4999, c2_share=0.3)
    F = np.diag([1.2, 0.95, 0.9])
    reference = A.cauchy("mooney_rivlin", A.MooneyRivlinParams(law.c1, law.c2, law.bulk), F)
    assert relative_error(mean_cauchy(homogeneous(law, F, degree=2, mixed=True)), reference) < 1e-8


@pytest.mark.parametrize("stretch", [0.6, 1.5])
def test_incompressible_neo_hookean_uniaxial(stretch):
    model = uniaxial(M.NeoHookean.incompressible(1.0), stretch, degree=2, mixed=True)
    sigma = mean_cauchy(model)
    assert abs(sigma[0, 0] - A.incompressible_neo_hookean_uniaxial(stretch, 1.0)) < 1e-8 * abs(sigma[0, 0])
    assert abs(lateral_stretch(model) - stretch**-0.5) < 1e-10
    assert np.abs(sigma[1:, 1:]).max() < 1e-8 * abs(sigma[0, 0])


def test_incompressible_neo_hookean_equibiaxial():
    model = uniaxial(M.NeoHookean.incompressible(1.0), 1.5, degree=2, mixed=True, biaxial=True)
    sigma = mean_cauchy(model)
    assert sigma[0, 0] == pytest.approx(2.0524691358, rel=1e-8)
    assert sigma[1, 1] == pytest.approx(2.0524691358, rel=1e-8)


def test_incompressible_mooney_rivlin_uniaxial():
    model = uniaxial(M.MooneyRivlin.incompressible(0.5, 0.25), 1.5, degree=2, mixed=True)
    assert mean_cauchy(model)[0, 0] == pytest.approx(2.1111111111, rel=1e-8)


@pytest.mark.parametrize("name", ["neo_hookean", "stable_neo_hookean", "svk", "ciarlet_geymonat"])
def test_uniaxial_free_lateral_faces(name):
    """The lateral contraction is found by the solver, not imposed."""
    law, reference, params = LAWS[name]
    stretch = 1.4
    t, sigma11 = A.uniaxial(reference, params, stretch)
    model = uniaxial(law, stretch)
    assert lateral_stretch(model) == pytest.approx(t, rel=1e-9)
    assert mean_cauchy(model)[0, 0] == pytest.approx(sigma11, rel=1e-8)


def test_simple_shear_neo_hookean():
    gamma = 0.4
    F = np.eye(3) + gamma * np.outer([1, 0, 0], [0, 1, 0])
    sigma = mean_cauchy(homogeneous(M.NeoHookean(MU, LMBDA), F))
    assert sigma[0, 1] == pytest.approx(MU * gamma, rel=1e-9)
    assert sigma[0, 0] == pytest.approx(MU * gamma**2, rel=1e-9)
    assert abs(sigma[1, 1]) < 1e-9 and abs(sigma[2, 2]) < 1e-9


ROTATION = np.array([[0.36, 0.48, -0.80], [-0.80, 0.60, 0.0], [0.48, 0.64, 0.60]])


@pytest.mark.parametrize("name", [n for n in LAWS if n != "linear"])
def test_frame_indifference(name):
    """A rigid rotation: zero stress and zero residual, for every finite-strain law."""
    law = LAWS[name][0]
    assert np.allclose(ROTATION @ ROTATION.T, np.eye(3)) and np.linalg.det(ROTATION) > 0
    model = homogeneous(law, ROTATION)
    assert np.abs(mean_cauchy(model)).max() < 1e-10 * max(MU, 1.0)


def test_linear_law_is_not_frame_indifferent():
    """Small-strain elasticity stresses a rigid rotation: the reason finite-strain laws exist."""
    assert np.abs(mean_cauchy(homogeneous(LAWS["linear"][0], ROTATION))).max() > 0.1
