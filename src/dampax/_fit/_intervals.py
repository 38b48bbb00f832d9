"""Confidence intervals that survive correlated residuals (issue 11, item 4), numpy.

Method: a heteroskedasticity-and-autocorrelation-consistent ("HAC", Newey-West) sandwich
covariance of the least-squares optimum,

    cov = H^-1 S H^-1,  H = J^T J,  S = sum_l w_l sum_t g_t g_(t+l)^T,  g_t = J_t r_t,

with J the Jacobian of the residuals in the physical parameters, r the residuals at the optimum
and Bartlett weights w_l = 1 - |l|/(L+1). For white noise S -> s2 H and this is the delta
method; for correlated residuals (measurement noise that is not white, and the slow phase drift
of a model that is nearly right) S counts the correlated samples once instead of many times.
The residuals are first prewhitened by their fitted AR(1) filter (Andrews & Monahan 1992; see
:func:`hac_covariance`): the Bartlett kernel alone, with a bandwidth of a few periods, covered
AR(1) noise of coefficient 0.9 in only 75-85 % of 90 % intervals (it under-weights the long
correlations), the prewhitened estimate is exact for AR(1) noise and keeps the kernel for the
rest.

Why this and not a bootstrap or a profile likelihood: it needs no refits (the Jacobian and the
residuals of the fit are enough, so it costs milliseconds and works for every model, the
reference integrator included), it makes no assumption on the form of the correlation (an AR(1)
profile would miss the oscillating correlation of a phase drift), and a block bootstrap of
residuals needs the same block length choice as the bandwidth here. The kernel is used only
where the prewhitened residuals are not white (Ljung-Box test at 1 %): for AR(1) or white noise
the prewhitened sandwich alone is exact (issue 25: a kernel of a few periods is biased low on
short windows). Its bandwidth L comes from the data: the lag at which the envelope (running
maximum over one period) of the autocorrelation of the summed scores falls below 0.1, doubled,
and kept between two periods and a quarter of the trace. Intervals are normal: value +- z sd
(clipped at 0 for the damping constants, which are >= 0). The calibrations
(benchmarks/calibration.py, issue 11 item 6; benchmarks/fit_calibration.py, issue 25) measure
how often they contain the truth.
"""

from __future__ import annotations

import math
import numbers
from statistics import NormalDist

import numpy as np

from ._dist import chi2_sf

#: a line for the reports and the docs
METHOD = ("AR(1)-prewhitened Newey-West (HAC) sandwich covariance; Bartlett kernel (bandwidth "
          "from the score autocorrelation) only where the prewhitened residuals are not white")


def bartlett_matrix(g: np.ndarray, lags: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, Gamma_0): S = sum_(|l| <= L) w_|l| Gamma_l with Bartlett weights w_l = 1 - l/(L+1)
    and Gamma_l = sum_t g_t g_(t+l)^T (Gamma_-l = Gamma_l^T), of the scores g (n x p).

    Formed in the frequency domain: with F the DFT of g zero-padded to N >= 2n samples (no
    wrap-around) and V the DFT of the circular weight sequence (real: the weights are
    symmetric), S = Re(F^H diag(V) F) / N, one product of p columns. The p^2 inverse
    transforms of every lag's Gamma_l this replaces were 58 % of a ranking's fits (``dampax
    fit --example``, issue 36, thirty-fifth session); the same sums to rounding.
    """
    g0 = g.T @ g
    n, _ = g.shape
    L = min(int(lags), n - 1)
    if L <= 0:
        return g0, g0
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    lag = np.arange(L + 1)
    v = np.zeros(nfft)
    v[lag] = 1.0 - lag / (L + 1.0)
    v[nfft - lag[1:]] = v[lag[1:]]
    twice = np.full(nfft // 2 + 1, 2.0)
    twice[[0, -1]] = 1.0  # the zero and Nyquist frequencies once, the others for +- k
    F = np.fft.rfft(g, nfft, axis=0)
    S = ((np.conj(F) * (twice * np.fft.rfft(v).real)[:, None]).T @ F).real / nfft
    return 0.5 * (S + S.T), g0


def bandwidth(g: np.ndarray, period_samples: float) -> int:
    """The Bartlett bandwidth L (samples) from the scores g (n x p), see the module doc."""
    n = g.shape[0]
    s = g / np.maximum(np.sqrt(np.sum(g * g, axis=0)), 1e-300)
    z = np.sum(s, axis=1)
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    F = np.fft.rfft(z - z.mean(), nfft)
    acf = np.fft.irfft(np.abs(F) ** 2, nfft)[:n]
    acf = acf / acf[0] if acf[0] > 0 else acf
    w = max(int(round(period_samples)), 1)
    env = np.abs(acf)
    if n > w:
        env = np.lib.stride_tricks.sliding_window_view(np.concatenate([env, np.zeros(w)]),
                                                       w).max(axis=1)[:n]
    below = np.flatnonzero(env < 0.1)
    lag = int(below[0]) if below.size else n
    lo, hi = int(2 * w), max(int(n // 4), 1)
    return int(min(max(2 * lag, lo), hi))


#: rows per block of :func:`_backward_ar1`
AR1_BLOCK = 64


def _backward_ar1(J: np.ndarray, phi: float) -> np.ndarray:
    """K = A^-T J: K_t = J_t + phi K_(t+1) from the last row back.

    In blocks of :data:`AR1_BLOCK` rows: within a block K_i = sum_(j >= i) phi^(j - i) J_j
    (one product with the block's triangular matrix of powers, all blocks at once), plus
    phi^(B - i) times K at the next block's first row (a loop over the blocks, from the
    last). Equal to ``scipy.signal.lfilter([1], [1, -phi], J[::-1], axis=0)[::-1]`` to
    rounding (every power |phi|^k <= 1: no growth), without importing scipy.signal (over a
    second) and without a Python loop over the rows (74 ms for 5,000 rows, a tenth of a
    default fit's assessment).

    Arguments:
        J: an (n, p) array.
        phi: the AR(1) coefficient (|phi| < 1).

    Returns:
        K, shaped like J.
    """
    n, p = J.shape
    size = AR1_BLOCK
    m = -(-n // size)
    blocks = np.zeros((m * size, p), dtype=J.dtype)
    blocks[:n] = J
    blocks = blocks.reshape(m, size, p)
    i = np.arange(size)
    ahead = i[None, :] - i[:, None]  # j - i
    T = np.where(ahead >= 0, float(phi) ** np.maximum(ahead, 0), 0.0)
    K = T @ blocks
    carry = (float(phi) ** (size - i))[:, None]
    for b in range(m - 2, -1, -1):
        K[b] += carry * K[b + 1, 0]
    return K.reshape(m * size, p)[:n]


#: the prewhitened residuals count as white (no kernel: the AR(1) sandwich) unless the
#: Ljung-Box test rejects whiteness at this level
WHITE_P = 0.01


def whiteness_p(e: np.ndarray, period_samples: float) -> float:
    """p-value of the Ljung-Box test that ``e`` is white, over lags 1..m with m one period
    (at least 10, at most n/5 and 200): Q = n (n + 2) sum rho_k^2 / (n - k) ~ chi2(m)."""

    e = np.asarray(e, dtype=float)
    n = e.size
    m = int(min(max(round(period_samples), 10), n // 5, 200))
    if m < 1:
        return 1.0
    e = e - e.mean()
    den = float(e @ e)
    if not den > 0:
        return 1.0
    rho = np.array([float(e[k:] @ e[:-k]) / den for k in range(1, m + 1)])
    q = n * (n + 2) * float(np.sum(rho * rho / (n - np.arange(1, m + 1))))
    return chi2_sf(q, m)


def ar1_coefficient(r: np.ndarray, *, clip: tuple[float, float] = (-0.99, 0.999),
                    pearson: bool = False) -> float:
    """The lag-1 autocorrelation phi of residuals ``r``, the coefficient of their AR(1) model:
    sum r_t r_(t-1) / sum r_t^2 (``pearson``: numpy's correlation of r[:-1] with r[1:],
    each centred on its own mean), clipped to ``clip``; 0 for fewer than 3 (``pearson``: 4)
    residuals or all zero.

    The one home of the estimate (issue 33). The callers keep the clips they had: the
    sandwich (-0.99, 0.999), the residual tests (-0.99, 0.99), the k3 profile's variance
    inflation (0, 0.99, Pearson); unifying them would change the reported numbers.
    """
    r = np.asarray(r, dtype=float)
    n = r.size
    if pearson:
        phi = float(np.corrcoef(r[:-1], r[1:])[0, 1]) if n > 3 else 0.0
    else:
        phi = float(np.dot(r[1:], r[:-1]) / max(np.dot(r, r), 1e-300)) if n > 2 else 0.0
    return min(max(phi, clip[0]), clip[1])


def gram_basis(J: np.ndarray):
    """(T, w): J^T J = T^-T diag(1/w) T^-1 from the singular values of the column-scaled J:
    T = diag(1/d) V (d the column norms, V the right singular vectors of J/d), so that the
    columns of J T are orthogonal with squared norms 1/w. w is 0 for singular values below
    eps max(n, p) s_max (the least-squares cut: no inverse, as a pseudo-inverse); NaN where
    J is not finite."""
    J = np.asarray(J, dtype=float)
    p = J.shape[1]
    if not np.all(np.isfinite(J)):
        return np.full((p, p), np.nan), np.full(p, np.nan)
    d = np.sqrt(np.einsum("ij,ij->j", J, J))
    d = np.where(d > 0, d, 1.0)
    R = np.linalg.qr(J / d, mode="r") if J.shape[0] > p else J / d
    _, s, vt = np.linalg.svd(R, full_matrices=False)
    cut = np.finfo(float).eps * max(J.shape) * (s[0] if s.size else 0.0)
    w = np.where(s > cut, 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
    return vt.T / d[:, None], w


def gram_inverse(J: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 = T diag(w) T^T from :func:`gram_basis`, never by forming J^T J (which
    squares the condition number: a fit whose damping constants sit at 0 has columns that
    agree to 1e-8, cond(J^T J) ~ 1e16, where the pseudo-inverse of J^T J dropped that
    direction or flipped its sign by the last bits of the data, issue 34). Singular values
    below the least-squares cut and zero columns get no inverse (0, as a pseudo-inverse); NaN
    where J is not finite (a Jacobian with NaN gives no interval, a named failure).

    Arguments:
        J: (n, p) Jacobian, rows of the data only.

    Returns:
        (p, p) symmetric matrix.
    """
    T, w = gram_basis(J)
    return (T * w) @ T.T


def score_matrix(J: np.ndarray, r: np.ndarray, *, period_samples: float,
                 lags: int | None = None, basis: np.ndarray | None = None):
    """(S, L): the middle of the AR(1)-prewhitened HAC sandwich (:func:`hac_covariance`):
    S = K^T A^T Cov(e) A K from the scores K_t e_t of the prewhitened residuals, with the
    Bartlett kernel of bandwidth L only where those are not white.

    Arguments:
        J: residual Jacobian (n x p) at the optimum, rows of the data only.
        r: residuals (n).
        period_samples: samples per oscillation period (sets the bandwidth's floor).
        lags: bandwidth L (default: 0 where the prewhitened residuals are white, else
            :func:`bandwidth`).
        basis: T^T S T instead (:func:`hac_covariance`): the sum formed from the scores in
            that basis, the bandwidth and :func:`_at_least`'s floor from the parameters'.
    """
    r = np.asarray(r, dtype=float)
    phi = ar1_coefficient(r)
    e = np.empty_like(r)
    e[0] = math.sqrt(1.0 - phi * phi) * r[0]
    e[1:] = r[1:] - phi * r[:-1]
    K = _backward_ar1(J, phi)
    K[0] = K[0] / math.sqrt(1.0 - phi * phi)
    g = K * e[:, None]
    if lags is not None:
        L = int(lags)
    elif whiteness_p(e, period_samples) >= WHITE_P:
        L = 0  # AR(1) noise: the prewhitened residuals are white, the sandwich is exact
    else:
        L = bandwidth(g, period_samples)
    L = min(L, g.shape[0] - 1)
    if basis is not None and L == 0:  # the prewhitened sandwich: formed in the basis alone
        return bartlett_matrix(g @ basis, 0)[0], L
    S, g0 = bartlett_matrix(g, L)
    floor = 0.0 if L == 0 else _at_least(S, g0) - S  # what the kernel may not take
    if basis is None:
        return S + floor, L
    return bartlett_matrix(g @ basis, L)[0] + basis.T @ floor @ basis, L


def _at_least(S: np.ndarray, S0: np.ndarray) -> np.ndarray:
    """S0 + (S - S0)_+: a symmetric matrix above both S and S0 in the positive semidefinite
    order (S0 plus the positive part of S - S0: along each eigenvector of S - S0 the larger).

    The kernel takes up correlation the AR(1) filter leaves; it is not to remove variance
    that the prewhitened sandwich S0 (L = 0) counts. Where it does, that is its bias (the
    scores of a least-squares optimum sum to zero, so a long bandwidth over a short window
    cancels them) and not negative correlation: a white trace of 1,066 samples that the
    Ljung-Box test rejected by chance (p = 0.008, 1 % of white traces) got L = 266 and sd
    0.37 times the delta method's, every constant 5 of those sd from the truth
    (fit_calibration.py seed 1, draw 70; benchmarks/README.md, issue 36, eleventh session).
    """
    vals, vecs = np.linalg.eigh(0.5 * ((S - S0) + (S - S0).T))
    return S0 + (vecs * np.maximum(vals, 0.0)) @ vecs.T


def hac_covariance(J: np.ndarray, r: np.ndarray, *, period_samples: float,
                   lags: int | None = None):
    """AR(1)-prewhitened HAC covariance of the parameters (columns of J): (cov, L).

    cov = H^-1 S H^-1 with S = K^T Cov(r) K computed as S = K^T A^T Cov(e) A K: the residuals
    are whitened by their fitted AR(1) filter A (e_t = r_t - phi r_(t-1), e_0 = sqrt(1 -
    phi^2) r_0, phi the lag-1 autocorrelation of r), K = A^-T J (a backward recursion
    K_t = J_t + phi K_(t+1)), and Cov(e) is estimated by the Bartlett-kernel HAC of the scores
    K_t e_t, which takes up what correlation the AR(1) filter leaves (the oscillating
    residuals of a phase drift). When the prewhitened residuals e pass the Ljung-Box test of
    whiteness (:func:`whiteness_p` >= :data:`WHITE_P`) the kernel is left out (L = 0): the
    noise is AR(1) (or white), for which the prewhitened sandwich is exact, while a Bartlett
    kernel of a few periods is biased low (the scores of a least-squares optimum sum to zero,
    so their long-run variance shrinks as the bandwidth grows: 90 % intervals covered 55-65 %
    of the truths of benchmarks/fit_calibration.py with it). Where the kernel is used, it only
    adds to the prewhitened sandwich, never takes from it (:func:`_at_least`): the same bias
    hits a white trace that the test rejects by chance.

    The sandwich is formed in the orthogonal basis of :func:`gram_basis` (cov = T (S_T / (s^2
    s^2^T)) T^T, S_T from the scores g T), not as H^-1 S H^-1 in the parameters: where two
    columns agree to 1e-8 (damping constants at 0) that product cancels terms 1e16 times its
    result, and a variance took any value from 2.9 to 49 (or <= 0, "no width", on a GPU) with
    the Jacobian moved by 4e-16 (benchmarks/README.md, twenty-fourth session). The same
    covariance in exact arithmetic: the bandwidth and :func:`_at_least`'s positive part stay
    those of the parameters (taken in T's basis, the kernel's intervals moved by up to 49 %).

    Arguments:
        J: residual Jacobian (n x p) at the optimum, rows of the data only.
        r: residuals (n).
        period_samples: samples per oscillation period (sets the bandwidth's floor).
        lags: bandwidth L (default: :func:`bandwidth`).
    """
    r = np.asarray(r, dtype=float)
    J = np.asarray(J, dtype=float)
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        # a fit without a finite Jacobian (it diverged): no interval
        return np.full((J.shape[1], J.shape[1]), np.nan), 0
    T, w = gram_basis(J)
    S, L = score_matrix(J, r, period_samples=period_samples, lags=lags, basis=T)
    cov = T @ (S * np.outer(w, w)) @ T.T
    return 0.5 * (cov + cov.T), L


def normal_intervals(values: dict, sd: dict, level: float, nonneg=(), scale=None) -> dict:
    """{name: (lo, hi)} = value -+ z sd at the two-sided ``level`` (clipped at 0 for
    ``nonneg``); ``scale``: {name: (below, above)} factors of the two sides (the profile's
    correction, ``_profile.PROFILE_FAIL``)."""
    if isinstance(level, bool) or not isinstance(level, numbers.Real) or not 0.0 < level < 1.0:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    z = NormalDist().inv_cdf(0.5 + 0.5 * level)
    out = {}
    for name, v in values.items():
        s = sd[name]
        below, above = (scale or {}).get(name, (1.0, 1.0))
        lo, hi = v - z * s * below, v + z * s * above
        if name in nonneg:
            lo = max(lo, 0.0)
        out[name] = (float(lo), float(hi))
    return out
