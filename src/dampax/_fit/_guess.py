"""Initial guesses (numpy): the parameters a fit starts from, from what a trace says before
any fit (``_analysis``).

(d0, d1, d2) of eq. 21 from the envelope decrement dE/dt = -(d0 + d1 E + d2 E^2) (eq. 20) by
non-negative least squares between the turning points, and the initial state from a
least-squares sinusoid over the part that moves (docs/DESIGN.md, fitting).
"""

from __future__ import annotations

import math

import numpy as np

from ._analysis import Analysis, analyse
from ._analysis import despike as despike
from ._params import (
    DAMPING,
    MAD,
    POWER,
    EnvelopeParams,
    TraceParams,
    check_free,
    d_to_physical,
    damping_d,
    oscillator_values,
)


def _nnls_small(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Non-negative least squares for a few columns, by trying every active set."""
    k = X.shape[1]
    best, best_res = np.zeros(k), float(np.sum(y * y))
    for mask in range(1, 1 << k):
        cols = [j for j in range(k) if mask >> j & 1]
        coef, *_ = np.linalg.lstsq(X[:, cols], y, rcond=None)
        if np.all(coef >= 0.0):
            full = np.zeros(k)
            full[cols] = coef
            res = float(np.sum((X @ full - y) ** 2))
            if res < best_res:
                best, best_res = full, res
    return best


def _guess_d(t_e, E, free, fixed_d, *, step: int = 2, noise: float = 0.0):
    """First estimates of the free (d0, d1, d2) of eq. 21 from the decrement of the envelope.

    dE/dt = -(d0 + d1 E + d2 E^2) (eq. 20) between extremes ``step`` apart (2: one full cycle,
    which cancels an offset error), by non-negative least squares; small floors for zeros.

    Arguments:
        t_e, E: times and amplitudes of the extremes.
        free: the damping constants to estimate.
        fixed_d: (d0, d1, d2) of the oscillator (kept for the constants not in ``free``).
        step: extremes between the two ends of a difference.
        noise: amplitudes below 5 noise are left out.

    Returns:
        ((d0, d1, d2), whether there were enough extremes).
    """
    powers = [POWER[f] for f in free]
    d = np.asarray(fixed_d, dtype=float).copy()
    if len(E) <= step + 1:
        return d, False
    rate = (E[:-step] - E[step:]) / (t_e[step:] - t_e[:-step])
    Em = 0.5 * (E[:-step] + E[step:])
    ok = (Em > 5.0 * noise) & np.isfinite(rate)
    if np.sum(ok) < max(2, len(powers)):
        return d, False
    rate, Em = rate[ok], Em[ok]
    basis = np.stack([np.ones_like(Em), Em, Em * Em], axis=1)  # E^0, E^1, E^2
    rhs = rate - basis @ np.where(np.isin(np.arange(3), powers), 0.0, d)
    cols = basis[:, powers]
    norms = np.linalg.norm(cols, axis=0)
    coef = _nnls_small(cols / norms, rhs) / norms
    mean_rate = max(float(np.mean(np.abs(rate))), 1e-300)
    floors = np.array([1e-2 * mean_rate, 1e-2 * mean_rate / np.mean(Em),
                       1e-2 * mean_rate / np.mean(Em * Em)])
    for j, c in zip(powers, coef, strict=True):
        d[j] = max(float(c), floors[j])
    return d, True


def _initial_state(t, y, omega, t_start, t_end=math.inf):
    """x0, v0 at t_start by linear least squares of the first 1.5 periods (before
    ``t_end``, where the data stop moving):
    y = (a + a' s) cos(w s) + (c + c' s) sin(w s), s = t - t_start."""
    s = t - t_start
    sel = s <= min(3.0 * math.pi / omega, max(t_end - t_start, 0.5 * math.pi / omega))
    if np.sum(sel) < 8:
        sel = np.arange(len(s)) < min(len(s), 8)
    s, y = s[sel], y[sel]
    cw, sw = np.cos(omega * s), np.sin(omega * s)
    X = np.stack([cw, s * cw, sw, s * sw], axis=1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(coef[0]), float(omega * coef[2] + coef[1])


def _damping_from_d(d, free, osc, w0):
    """(mu, b, D) by name: eq. 21 inverted for the free ones, the oscillator's for the rest."""
    vals = dict(zip(DAMPING, d_to_physical(d[0], d[1], d[2], w0, osc["m"], osc["g"]),
                    strict=True))
    return {name: vals[name] if name in free else osc[name] for name in DAMPING}


def guess_trace(t, x, free, osc: dict, fit_omega0: bool, offset: bool,
                an: Analysis | None = None) -> TraceParams:
    """Initial :class:`TraceParams` of a trace that starts at t[0].

    Arguments:
        t, x: the fit window.
        free: the damping constants to fit.
        osc: the oscillator's constants (``oscillator_values``).
        fit_omega0, offset: w0 from the data (else sqrt(k/m)); offset from the data (else 0).
        an: the window's :class:`Analysis` (default: computed).
    """
    an = an or analyse(t, x, omega0=None if fit_omega0 else osc["w0"])
    off = an.offset if offset else 0.0
    w0 = an.omega if fit_omega0 else osc["w0"]
    fixed_d = damping_d(osc["mu"], osc["b"], osc["D"], w0, osc["m"], osc["g"])
    E = np.abs(an.ext_x) if offset else np.abs(x[an.ext_i])
    step = 2 if E.size >= 5 else 1
    d, ok = _guess_d(an.ext_t, E, free, fixed_d, step=step, noise=an.noise)
    x0, v0 = _initial_state(t, x - off, w0, t[0], an.end_t)
    if not ok and free:  # too few turning points: the decay over the moving part
        A = math.hypot(x0, v0 / w0)
        if an.halted:  # from A to rest within the moving part
            span = max(an.end_t - t[0], math.pi / w0)
            lost = A
        else:
            span = max(t[-1] - t[0], 1e-12)
            lost = 0.5 * A if E.size < 2 else max(float(E[0] - E[-1]), 0.1 * A)
        share = lost / span / len(free)
        d = list(d)
        for f in free:
            d[POWER[f]] = share / [1.0, A, A * A][POWER[f]]
    return TraceParams(**_damping_from_d(d, free, osc, w0), w0=w0, offset=off, x0=x0, v0=v0)


def guess_envelope(t, E, free, osc: dict, omega0: float) -> EnvelopeParams:
    """Initial :class:`EnvelopeParams` of maxima E(t): (d0, d1, d2) from the decrement between
    successive maxima, A = E[0], no offset."""
    fixed_d = damping_d(osc["mu"], osc["b"], osc["D"], omega0, osc["m"], osc["g"])
    noise = float(MAD * np.median(np.abs(np.diff(E, 2)))) / math.sqrt(6) if len(E) > 4 else 0
    d, _ = _guess_d(t, E, free, fixed_d, step=1, noise=0.2 * noise)
    return EnvelopeParams(**_damping_from_d(d, free, osc, omega0), A=E[0], offset=0.0)


def initial_guess(t, x, *, free=("mu", "D"), oscillator=None, fit_omega0: bool | None = None,
                  offset: bool = True):
    """Initial parameters for :func:`~dampax.fit_arrays`, from a trace that starts at t[0].

    Offset from the midpoints of successive turning points, w0 from their spacing (a
    least-squares sinusoid when there are few), (d0, d1, d2) of eq. 21 from the envelope
    decrement (eq. 20) by non-negative least squares, x0 and v0 from a least-squares sinusoid
    over the first 1.5 periods (of the part that moves).

    Arguments:
        t, x: the trace.
        free: the damping constants to fit; the others stay at the oscillator's values.
        oscillator: the known constants (default None: unit mass, w0 from the data).
        fit_omega0: w0 from the data (else sqrt(k/m)); default: True without an oscillator.
        offset: the offset from the data (else 0).

    Returns:
        p0 in the layout ``PARAMS`` (numpy array).
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if fit_omega0 is None:
        fit_omega0 = oscillator is None
    if oscillator is None and not fit_omega0:
        raise ValueError("fit_omega0=False needs an oscillator (m and k)")
    osc = oscillator_values(oscillator)
    return np.array(guess_trace(t, x, check_free(free), osc, fit_omega0, offset), dtype=float)
