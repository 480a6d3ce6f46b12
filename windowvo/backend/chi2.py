"""Chi-square quantiles for the back end's robust thresholds and tests, in the standard library alone.

The back end needs the quantile of a chi-square distribution with a few (1-6) degrees of freedom at a
confidence such as 0.95 or 0.99. ``scipy.special.gammaincinv`` gives it, but importing ``scipy.special``
cost about 0.18 s of CPU at every back-end start (the pipelined run's back-end process, every run of the
sequential mode): measured with ``python -X importtime``. For an integer number of degrees of freedom the
chi-square CDF has a closed form (a finite sum with ``exp`` and, for odd degrees, ``erf``/``erfc``), so the
quantile is a bisection on it, exact to the float's resolution (``tests/test_chi2.py`` compares it with
``scipy.stats.chi2.ppf``).
"""

from __future__ import annotations

import math
from functools import lru_cache
from statistics import NormalDist

MAX_DOF = 30  # the closed form's sum has dof/2 terms; the back end asks for 1, 2 and 3


def chi2_cdf(x: float, dof: int) -> float:
    """P(X <= x) for X chi-square distributed with an integer ``dof`` >= 1."""
    if x <= 0.0:
        return 0.0
    h = 0.5 * x
    if dof % 2 == 0:
        # 1 - exp(-h) * sum_{i < dof/2} h^i / i!
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= h / i
            total += term
        return max(0.0, 1.0 - math.exp(-h) * total)
    # Odd: erf(sqrt(h)) - exp(-h) * sum_{i < (dof-1)/2} h^(i+1/2) / Gamma(i + 3/2)
    s = math.sqrt(h)
    term = s / math.gamma(1.5)
    total = 0.0
    for i in range((dof - 1) // 2):
        total += term
        term *= h / (i + 1.5)
    return min(1.0, max(0.0, math.erf(s) - math.exp(-h) * total))


@lru_cache(maxsize=64)
def chi2_quantile(dof: int, p: float) -> float:
    """The x with P(X <= x) = p for a chi-square X with ``dof`` degrees of freedom (0 < p < 1)."""
    if not 1 <= int(dof) <= MAX_DOF or int(dof) != dof:
        raise ValueError(f"chi2_quantile: dof must be an integer in 1..{MAX_DOF}, got {dof}")
    if not 0.0 < p < 1.0:
        raise ValueError(f"chi2_quantile: p must be in (0, 1), got {p}")
    dof = int(dof)
    if dof == 1:
        return NormalDist().inv_cdf(0.5 + 0.5 * p) ** 2  # the square of a standard normal
    if dof == 2:
        return -2.0 * math.log1p(-p)  # exact
    lo, hi = 0.0, max(1.0, 2.0 * dof)
    while chi2_cdf(hi, dof) < p:
        hi *= 2.0
    for _ in range(2000):  # to adjacent floats (about 60 halvings)
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if chi2_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
    return hi
