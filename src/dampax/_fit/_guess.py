"""Initial guesses (numpy): what a trace says before any fit.

Noise from second differences, the offset from the midpoints of successive extremes, the
frequency from the zero crossings (FFT when there are few), (d0, d1, d2) of eq. 21 from the
envelope decrement dE/dt = -(d0 + d1 E + d2 E^2) (eq. 20) by non-negative least squares, and
the initial state from a least-squares sinusoid (docs/DESIGN.md, fitting).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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


@dataclass
class Analysis:
    """What :func:`analyse` finds in a trace.

    Attributes:
        offset: the equilibrium position.
        omega: angular frequency of the zero crossings.
        noise: sigma of the measurement noise.
        ext_i, ext_t: sample index and time of the extreme of every half cycle.
        ext_x: the signed extremes, relative to the offset.
        n_cross: number of zero crossings.
    """

    offset: float
    omega: float
    noise: float
    ext_i: np.ndarray
    ext_t: np.ndarray
    ext_x: np.ndarray
    n_cross: int


def _noise_sigma(x: np.ndarray) -> float:
    """sigma of white noise from the MAD of the second differences (var = 6 sigma^2)."""
    if x.size < 5:
        return 0.0
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(MAD * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _crossings(y: np.ndarray, h: float) -> np.ndarray:
    """Indices i where y changes sign between i and i+1, with hysteresis h (noise-proof)."""
    state = 0
    last_change = -1
    out = []
    sign = np.sign(y)
    for i in np.flatnonzero(np.abs(y) > h):
        s = 1 if y[i] > 0 else -1
        if state != 0 and s != state:
            # the last sign change before i
            j = i - 1
            while j > last_change and sign[j] == s:
                j -= 1
            out.append(max(j, 0))
        if s != state:
            last_change = i
        state = s
    return np.asarray(out, dtype=int)


def _frequency_fft(t: np.ndarray, y: np.ndarray) -> float:
    """Angular frequency of the highest peak of the (zero-padded, Hann-windowed) spectrum."""
    dt = float(np.median(np.diff(t)))
    n = 1 << int(math.ceil(math.log2(max(len(y), 8)))) + 2
    spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y)), n))
    spec[0] = 0.0
    k = int(np.argmax(spec))
    if 0 < k < len(spec) - 1:
        a, b, c = np.log(spec[k - 1: k + 2] + 1e-300)
        k = k + 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else k
    return 2.0 * math.pi * k / (n * dt)


def despike(x: np.ndarray, width: int = 5) -> np.ndarray:
    """Running median over ``width`` samples: removes glitches of one or two samples."""
    if x.size < 3 * width:
        return x
    half = width // 2
    padded = np.concatenate([np.full(half, x[0]), x, np.full(half, x[-1])])
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, width), axis=1)


def analyse(t: np.ndarray, x: np.ndarray) -> Analysis:
    """Offset, frequency, noise and the extreme of every half cycle of a trace (glitches of
    one or two samples removed by a running median first).

    Returns:
        An :class:`Analysis`.
    """
    noise = _noise_sigma(x)
    x = despike(x)
    off = float(np.median(x))
    for _ in range(2):
        y = x - off
        h = max(5.0 * noise, 1e-3 * float(np.max(np.abs(y))))
        cross = _crossings(y, h)
        ext_i = []
        for a, b in zip(cross[:-1], cross[1:], strict=True):
            seg = np.abs(y[a + 1: b + 1])
            ext_i.append(a + 1 + int(np.argmax(seg)))
        ext_i = np.asarray(ext_i, dtype=int)
        if ext_i.size >= 3:
            mids = 0.5 * (y[ext_i[:-1]] + y[ext_i[1:]])
            off += float(np.median(mids[: max(3, min(len(mids), 40))]))
    y = x - off
    if cross.size >= 4:
        tc = []
        for i in cross:  # linear interpolation of the zero between i and i+1
            y0, y1 = y[i], y[min(i + 1, len(y) - 1)]
            frac = y0 / (y0 - y1) if y1 != y0 else 0.0
            tc.append(t[i] + frac * (t[min(i + 1, len(t) - 1)] - t[i]))
        tc = np.asarray(tc)
        dtc = np.diff(tc)
        half = float(np.median(dtc))
        steps = np.maximum(np.round(dtc / half), 1.0)
        k = np.concatenate([[0.0], np.cumsum(steps)])
        slope = np.polyfit(k, tc, 1)[0]
        omega = math.pi / slope
    else:
        omega = _frequency_fft(t, y)
    return Analysis(offset=off, omega=omega, noise=noise, ext_i=ext_i, ext_t=t[ext_i],
                    ext_x=y[ext_i], n_cross=int(cross.size))


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


def _initial_state(t, y, omega, t_start):
    """x0, v0 at t_start by linear least squares of the first 1.5 periods:
    y = (a + a' s) cos(w s) + (c + c' s) sin(w s), s = t - t_start."""
    s = t - t_start
    sel = s <= 3.0 * math.pi / omega
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


def start_index(t, x, an: Analysis, start) -> int:
    """Index of the first sample of the fit window.

    Arguments:
        t, x: the whole trace.
        an: its :class:`Analysis`.
        start: "auto" (the first extreme after the largest excursion, which skips a hand
            release), "data" / None (the first sample) or a time.
    """
    if start is None or start == "data":
        return 0
    if isinstance(start, (int, float)) and not isinstance(start, bool):
        i = int(np.searchsorted(t, float(start)))
        if i >= len(t) - 10:
            raise ValueError(f"start = {start} leaves fewer than 10 samples")
        return i
    if start != "auto":
        raise ValueError(f"start must be 'auto', 'data', None or a time, got {start!r}")
    y = np.abs(despike(x) - an.offset)
    i_big = int(np.argmax(y))
    later = an.ext_i[an.ext_t > t[i_big] + 0.25 * math.pi / an.omega]
    return int(later[0]) if later.size else 0


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
    an = an or analyse(t, x)
    off = an.offset if offset else 0.0
    w0 = an.omega if fit_omega0 else osc["w0"]
    fixed_d = damping_d(osc["mu"], osc["b"], osc["D"], w0, osc["m"], osc["g"])
    E = np.abs(an.ext_x) if offset else np.abs(x[an.ext_i])
    d, ok = _guess_d(an.ext_t, E, free, fixed_d, noise=an.noise)
    x0, v0 = _initial_state(t, x - off, an.omega, t[0])
    if not ok:  # too few extremes: a mild decay over the window
        A = math.hypot(x0, v0 / w0)
        span = max(t[-1] - t[0], 1e-12)
        share = 0.5 * A / span / max(len(free), 1)
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

    Offset from the midpoints of successive extremes, w0 from the zero crossings (FFT when
    there are few), (d0, d1, d2) of eq. 21 from the envelope decrement per cycle (eq. 20) by
    non-negative least squares, x0 and v0 from a least-squares sinusoid over the first 1.5
    periods.

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
