"""Chi-square quantiles without scipy (``backend/chi2.py``) against scipy's, which the back end used before."""

from __future__ import annotations

import math

import pytest
from scipy.stats import chi2

from windowvo.backend.chi2 import chi2_cdf, chi2_quantile
from windowvo.backend.factors import robust_threshold

PROBABILITIES = (1e-4, 0.01, 0.2, 0.5, 0.68, 0.9, 0.95, 0.975, 0.99, 0.995, 0.999, 0.9999)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 5, 6, 7, 10, 15, 30])
def test_quantile_matches_scipy(dof):
    for p in PROBABILITIES:
        assert chi2_quantile(dof, p) == pytest.approx(chi2.ppf(p, dof), rel=1e-12, abs=1e-300), (dof, p)


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 9])
def test_cdf_matches_scipy(dof):
    for x in (1e-6, 0.01, 0.5, 1.0, 2.0, 3.84, 7.8, 15.0, 40.0):
        assert chi2_cdf(x, dof) == pytest.approx(chi2.cdf(x, dof), rel=1e-12, abs=1e-15), (dof, x)


def test_known_values_and_the_robust_thresholds():
    assert chi2_quantile(1, 0.95) == pytest.approx(1.959963984540054**2, rel=1e-14)
    assert chi2_quantile(2, 0.95) == pytest.approx(-2.0 * math.log(0.05), rel=1e-14)
    assert robust_threshold(2, 0.95) == pytest.approx(math.sqrt(chi2.ppf(0.95, 2)), rel=1e-14)


def test_bad_arguments_are_refused():
    for dof, p in ((0, 0.5), (2.5, 0.5), (31, 0.5), (2, 0.0), (2, 1.0)):
        with pytest.raises(ValueError):
            chi2_quantile(dof, p)
