"""The few distribution functions the fit's checks and intervals need, from ``scipy.special``
(a fifth of a second to import) instead of ``scipy.stats`` (over half a second: issue 26, the
latency of ``dampax fit``), and the normal quantile from the standard library.

Each equals its ``scipy.stats`` counterpart to rounding (tests/fit/test_fit.py).
"""

from __future__ import annotations

from statistics import NormalDist

_NORMAL = NormalDist()


def norm_ppf(p: float) -> float:
    """The standard normal quantile (``scipy.stats.norm.ppf``)."""
    return _NORMAL.inv_cdf(p)


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X ~ chi2(k): the regularised upper incomplete gamma Q(k/2, x/2)."""
    from scipy.special import gammaincc

    return float(gammaincc(0.5 * k, 0.5 * max(x, 0.0)))


def chi2_isf(p: float, k: float) -> float:
    """The x with P(X > x) = p for X ~ chi2(k) (``scipy.stats.chi2.isf``)."""
    from scipy.special import gammainccinv

    return 2.0 * float(gammainccinv(0.5 * k, p))


def f_sf(x: float, d1: float, d2: float) -> float:
    """P(X > x) for X ~ F(d1, d2): the regularised incomplete beta I_{d2/(d2 + d1 x)}(d2/2,
    d1/2)."""
    from scipy.special import betainc

    if not x > 0:
        return 1.0
    return float(betainc(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * x)))
