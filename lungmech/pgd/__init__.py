"""Proper Generalised Decomposition: a model's solution over its whole parameter box, built a
priori (no full-order snapshot), as u(x, μ) ≈ Σₖ ūₖ(x) Πⱼ λₖʲ(μⱼ) — a nonlinear model's by
Newton iterations on residual assemblies (:mod:`lungmech.pgd.newton`) —, or fitted to full
solves for a model the a priori one does not take (:mod:`lungmech.pgd.fitted`).

``separated_terms`` reads a linear model's residual as separated terms from its own forms and
parameter assignment (:mod:`lungmech.pgd.terms`); ``pgd`` builds the terms greedily with an
update of all of them (:mod:`lungmech.pgd.greedy`) over each parameter's :class:`Axis` of
cubic splines; the :class:`Decomposition` evaluates u(μ) and its derivatives in μ; ``indicator``
gives its error indicator from the model's own residual (:mod:`lungmech.pgd.indicator`).
"""

from lungmech.pgd.axes import Axis
from lungmech.pgd.decomposition import Decomposition
from lungmech.pgd.greedy import Options, Round, pgd
from lungmech.pgd.indicator import effectivity, indicator
from lungmech.pgd.terms import Terms, separated_terms

__all__ = ["Axis", "Decomposition", "Options", "Round", "Terms", "effectivity", "indicator", "pgd", "separated_terms"]
