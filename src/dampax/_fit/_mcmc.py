"""MCMC diagnostics as ArviZ computes them, and InferenceData files without ArviZ (issue 25).

R-hat and ESS (Vehtari, Gelman, Simpson, Carpenter & Buerkner 2021, "Rank-normalization,
folding, and localization: an improved R-hat", Bayesian Analysis 16, 667; arXiv:1903.08008):

- split chains: each chain's first and last ``n // 2`` draws become two chains (the middle draw
  of an odd chain is dropped), section 4.1;
- rank normalisation: z = Phi^-1((r - 3/8) / (S + 1/4)) of the average ranks r over all S
  pooled draws (Blom), eq. 14;
- R-hat = max(split R-hat of z, split R-hat of the ranks-normalised folded draws |x - median|),
  eqs. 3-4 and section 4.2;
- bulk ESS: the ESS (Geyer's initial monotone sequence, eq. 10 with section 3.2) of the split,
  rank-normalised draws; tail ESS: the smaller ESS of the indicators x <= q05 and x <= q95 of
  the split draws (section 4.3).

These numbers match ``arviz.rhat`` (method "rank") and ``arviz.ess`` (methods "bulk", "tail")
of ArviZ 0.23 to rounding; blackjax.diagnostics 1.7.1 computes the same statistics with other
conventions for odd draws and the autocovariance (differences of a few per cent in ESS), and
``potential_scale_reduction`` is the plain (non-split) statistic.

The file: :func:`write_inference_data` writes xarray Datasets as the groups of one netCDF-4
file (h5netcdf engine), the layout of ``arviz.InferenceData.to_netcdf``, so
``arviz.from_netcdf`` reads it while ArviZ stays out of dampax's dependencies.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._io import atomic_path

#: the groups of an InferenceData file that dampax writes, in order
GROUPS = ("posterior", "sample_stats", "observed_data")


def _check_draws(draws) -> np.ndarray:
    a = np.asarray(draws, dtype=float)
    if a.ndim != 2:
        raise ValueError(f"draws must have shape (chain, draw), got shape {a.shape}")
    return a


def _split(a: np.ndarray) -> np.ndarray:
    """Split chains: (c, n) -> (2c, n // 2), first halves then last halves."""
    half = a.shape[1] // 2
    return np.vstack((a[:, :half], a[:, a.shape[1] - half:]))


def _z_scale(a: np.ndarray) -> np.ndarray:
    """Rank normalisation with Blom's offset 3/8 over all draws (average ranks for ties)."""
    from scipy.stats import norm, rankdata

    r = rankdata(a, method="average").reshape(a.shape)
    return norm.ppf((r - 0.375) / (a.size + 0.25))


def _rhat_plain(a: np.ndarray) -> float:
    """sqrt((B/W + n - 1) / n): the potential scale reduction of (c, n) draws."""
    n = a.shape[1]
    between = n * np.var(a.mean(axis=1), ddof=1)
    within = np.mean(np.var(a, axis=1, ddof=1))
    return float(np.sqrt((between / within + n - 1) / n))


def _autocov(a: np.ndarray) -> np.ndarray:
    """Autocovariance of every chain at every lag (FFT), biased (divided by n)."""
    n = a.shape[1]
    m = 1 << (2 * n - 1).bit_length()
    d = a - a.mean(axis=1, keepdims=True)
    f = np.fft.rfft(d, n=m, axis=1)
    return np.fft.irfft(f * np.conjugate(f), n=m, axis=1)[:, :n] / n


def _ess(a: np.ndarray) -> float:
    """ESS of (c, n) draws: Geyer's initial positive, then monotone sequence of the
    multi-chain autocorrelations (Vehtari et al. 2021, eq. 10)."""
    a = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a)):
        return math.nan
    if np.max(a) - np.min(a) < np.finfo(float).resolution:
        return float(a.size)
    c, n = a.shape
    acov = _autocov(a)
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if c > 1:
        var_plus += np.var(a.mean(axis=1), ddof=1)
    rho = np.zeros(n)
    even, odd = 1.0, 1.0 - (mean_var - np.mean(acov[:, 1])) / var_plus
    rho[0], rho[1] = even, odd
    t = 1
    while t < n - 3 and even + odd > 0.0:
        even = 1.0 - (mean_var - np.mean(acov[:, t + 1])) / var_plus
        odd = 1.0 - (mean_var - np.mean(acov[:, t + 2])) / var_plus
        if even + odd >= 0.0:
            rho[t + 1], rho[t + 2] = even, odd
        t += 2
    max_t = t - 2
    if even > 0.0:
        rho[max_t + 1] = even
    t = 1
    while t <= max_t - 2:
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = rho[t + 2] = 0.5 * (rho[t - 1] + rho[t])
        t += 2
    tau = -1.0 + 2.0 * np.sum(rho[:max_t + 1]) + np.sum(rho[max_t + 1:max_t + 2])
    tau = max(tau, 1.0 / np.log10(a.size))
    return float(a.size / tau)


def rhat(draws) -> float:
    """Rank-normalised split R-hat of one quantity (Vehtari et al. 2021, section 4.2).

    Arguments:
        draws: array (chain, draw).

    Returns:
        max(bulk, folded) split R-hat of the rank-normalised draws, as ``arviz.rhat``; NaN
        with fewer than 2 chains or 4 draws, or non-finite draws.
    """
    a = _check_draws(draws)
    if a.shape[0] < 2 or a.shape[1] < 4 or not np.all(np.isfinite(a)):
        return math.nan
    s = _split(a)
    return max(_rhat_plain(_z_scale(s)), _rhat_plain(_z_scale(np.abs(s - np.median(s)))))


def ess_bulk(draws) -> float:
    """Bulk effective sample size: the ESS of the split, rank-normalised draws (Vehtari et al.
    2021, section 4.3), as ``arviz.ess(method="bulk")``.

    Arguments:
        draws: array (chain, draw), at least 4 draws.

    Returns:
        The ESS (NaN for fewer than 4 draws or non-finite draws).
    """
    a = _check_draws(draws)
    if a.shape[1] < 4 or not np.all(np.isfinite(a)):
        return math.nan
    return _ess(_z_scale(_split(a)))


def ess_tail(draws, prob=(0.05, 0.95)) -> float:
    """Tail effective sample size: the smaller ESS of the indicators x <= q(prob) of the split
    draws (Vehtari et al. 2021, section 4.3), as ``arviz.ess(method="tail")``.

    Arguments:
        draws: array (chain, draw), at least 4 draws.
        prob: the two quantile levels.

    Returns:
        The ESS (NaN for fewer than 4 draws or non-finite draws).
    """
    a = _check_draws(draws)
    if a.shape[1] < 4 or not np.all(np.isfinite(a)):
        return math.nan
    out = []
    for p in prob:
        q = np.quantile(a, p)  # type 7, as arviz's mquantiles(alphap=1, betap=1)
        out.append(_ess(_split((a <= q).astype(float))))
    return float(min(out))


def write_inference_data(groups: dict, path) -> Path:
    """Write xarray Datasets as the groups of one netCDF-4 file (the InferenceData layout).

    ``arviz.from_netcdf(path)`` opens it as InferenceData with these groups. Coordinates carry
    no ``_FillValue`` (CF conventions 2.5.1); boolean variables are stored as int8 with the
    attribute ``dtype = "bool"`` (xarray decodes them back).

    Arguments:
        groups: {group name: xarray Dataset}, e.g. "posterior", "sample_stats",
            "observed_data".
        path: the file (written whole or not at all).

    Returns:
        The path.
    """
    import xarray as xr

    if not groups:
        raise ValueError("groups: give at least one group")
    tree = xr.DataTree.from_dict({f"/{name}": ds for name, ds in groups.items()})
    encoding = {f"/{name}": {c: {"_FillValue": None} for c in ds.coords}
                for name, ds in groups.items()}
    with atomic_path(path) as tmp:
        tree.to_netcdf(tmp, engine="h5netcdf", encoding=encoding)
    return Path(path)
