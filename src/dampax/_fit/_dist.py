"""The few distribution functions the fit's checks and intervals need, without
``scipy.stats`` (over half a second to import: issue 26, the latency of ``dampax fit``) and,
for the chi-square of integer degrees of freedom that every check uses, without
``scipy.special`` either (a tenth of a second, most of it scipy parsing docstrings, on the
first fit's critical path and under Python's lock: issue 36); the normal quantile from the
standard library.

Each equals its ``scipy.stats`` counterpart to rounding (tests/fit/test_fit.py).
"""

from __future__ import annotations

import math
from statistics import NormalDist

_NORMAL = NormalDist()


def norm_ppf(p: float) -> float:
    """The standard normal quantile (``scipy.stats.norm.ppf``)."""
    return _NORMAL.inv_cdf(p)


def _integer(k: float) -> int | None:
    """``k`` as a positive int where it is one (the checks' degrees of freedom), else None."""
    return int(k) if k >= 1 and float(k).is_integer() and k < 1e6 else None


def _chi2_sf_int(x: float, k: int) -> float:
    """Q(k/2, x/2) for an integer k in closed form (Abramowitz & Stegun 26.4.4-5):
    e^-y sum_{j<k/2} y^j / j! for even k, erfc(sqrt y) + e^-y sum_{j<(k-1)/2}
    y^(j+1/2) / Gamma(j+3/2) for odd k (y = x/2). Every term is positive (no cancellation)
    and taken from its logarithm (no overflow): relative error about |log term| eps."""
    if not x > 0.0:
        return 1.0
    y = 0.5 * x
    log_y, half = math.log(y), 0.5 * (k % 2)
    total = math.erfc(math.sqrt(y)) if half else 0.0
    for j in range(k // 2):
        total += math.exp(-y + (j + half) * log_y - math.lgamma(j + half + 1.0))
    return min(total, 1.0)


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X ~ chi2(k): the regularised upper incomplete gamma Q(k/2, x/2)."""
    n = _integer(k)
    if n is not None:
        return _chi2_sf_int(float(x), n)
    from scipy.special import gammaincc

    return float(gammaincc(0.5 * k, 0.5 * max(x, 0.0)))


def _chi2_isf_int(p: float, k: int) -> float | None:
    """The x with Q(k/2, x/2) = p for an integer k: Newton's method on log Q from the
    Wilson-Hilferty approximation (None where it does not settle)."""
    z = -norm_ppf(p)
    c = 2.0 / (9.0 * k)
    x = max(k * (1.0 - c + z * math.sqrt(c)) ** 3, 1e-8)
    log_p, log_norm = math.log(p), 0.5 * k * math.log(2.0) + math.lgamma(0.5 * k)
    for _ in range(60):
        q = _chi2_sf_int(x, k)
        if not q > 0.0:
            return None
        log_pdf = (0.5 * k - 1.0) * math.log(x) - 0.5 * x - log_norm
        step = (math.log(q) - log_p) / math.exp(log_pdf - math.log(q))  # g / -g'
        x_new = x + step if x + step > 0.0 else 0.5 * x
        if abs(x_new - x) <= 1e-15 * x:
            return x_new
        x = x_new
    return None


def chi2_isf(p: float, k: float) -> float:
    """The x with P(X > x) = p for X ~ chi2(k) (``scipy.stats.chi2.isf``)."""
    n = _integer(k)
    if n is not None and 0.0 < p < 1.0:
        x = _chi2_isf_int(float(p), n)
        if x is not None:
            return x
    from scipy.special import gammainccinv

    return 2.0 * float(gammainccinv(0.5 * k, p))


def f_sf(x: float, d1: float, d2: float) -> float:
    """P(X > x) for X ~ F(d1, d2): the regularised incomplete beta I_{d2/(d2 + d1 x)}(d2/2,
    d1/2)."""
    from scipy.special import betainc

    if not x > 0:
        return 1.0
    return float(betainc(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * x)))
