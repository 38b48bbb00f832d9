"""What a trace says before any fit (numpy): :func:`analyse` and its :class:`Analysis`.

Noise from higher differences; the turning points (velocity zeros) by a zigzag with a noise
and range based reversal, the noise's wiggles merged away and the data's halt found where
they come to rest; the offset from the midpoints of successive turning points, the frequency
from their spacing (pi/w0 for Coulomb friction, which moves the zero crossings but not them;
a least-squares sinusoid when there are fewer than two) (docs/DESIGN.md, fitting). The
initial guesses built on it are ``_guess``'s.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace

import numpy as np

from ._noise import above_noise, despike, noise_sigma
from ._params import MAD


@dataclass
class Analysis:
    """What :func:`analyse` finds in a trace, before any fit.

    Everything comes from the turning points (velocity zeros), which friction and drag do not
    move off the motion's own clock: Coulomb friction shifts the centre of each half swing by
    +-mu m g/k, which moves the zero crossings, but the turning points of eq. 3 stay pi/w0
    apart (pi/w_d with viscous damping).

    Attributes:
        offset: the equilibrium position (mean of the centres of successive half swings).
        omega: angular frequency: pi / the spacing of the turning points, or a least-squares
            sinusoid over the moving part when there are fewer than two.
        noise: sigma of the white part of the measurement noise (second differences).
        ext_i, ext_t: sample index and time of every turning point inside the trace (the
            rest point last when the data halt).
        ext_x: the turning points, relative to the offset.
        n_turns: number of turning points.
        halted: the data stop moving inside the trace (no reversal after the last turning
            point for at least half a period).
        end_t: where the data stop moving (the last turning point when halted, else t[-1]).
        omega_spread: relative uncertainty of ``omega`` as a start (a few turning points
            fix it to a few per cent, many to a few per mille).
        level: the reversal a turning point needs (noise and range based).
        window: (i0, i1), the slice of the given arrays that was analysed (the fit window
            when :func:`analyse` placed one, else the whole trace).
        whole: the scan of the whole trace that placed the window (itself when no window
            was placed or the window is the whole trace, scanned alike).
    """

    offset: float
    omega: float
    noise: float
    ext_i: np.ndarray
    ext_t: np.ndarray
    ext_x: np.ndarray
    n_turns: int = 0
    halted: bool = False
    end_t: float = math.nan
    omega_spread: float = 0.3
    level: float = 0.0
    window: tuple = (0, -1)
    whole: Analysis | None = None


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


def zigzag(y: np.ndarray, h: float):
    """Turning points of a trace: the extremes confirmed by a reversal of more than ``h``.

    Returns:
        (indices, pending): the confirmed extremes in time order (an extreme at the first
        sample is the window's edge, not a reversal, and is left out) and the index of the
        extreme after the last one, which no reversal has confirmed (the data halt there, or
        the trace ends).
    """
    n = y.size
    out = []
    imax = imin = 0
    trend = 0
    for i in range(1, n):
        v = y[i]
        if trend >= 0 and v > y[imax]:
            imax = i
        if trend <= 0 and v < y[imin]:
            imin = i
        if trend >= 0 and y[imax] - v > h:
            out.append(imax)
            trend, imin = -1, i
        elif trend <= 0 and v - y[imin] > h:
            out.append(imin)
            trend, imax = 1, i
    pending = imax if trend == 1 else imin if trend == -1 else -1
    out = [i for i in out if i > 0]
    return np.asarray(out, dtype=int), pending


def _sinusoid_frequency(t, y, lo, hi):
    """Angular frequency in [lo, hi] of the least-squares c + (a + a' s) cos(w s) + (b + b' s)
    sin(w s): a log grid, then a finer one around the best (normal equations, 32 at a time)."""
    s, u = t - t[0], (t - t[0]) / max(float(t[-1] - t[0]), 1e-300)

    def best(ws):
        out = []
        for w in np.split(ws, range(32, ws.size, 32)):
            cw, sw = np.cos(w[:, None] * s), np.sin(w[:, None] * s)
            X = np.stack([np.broadcast_to(1.0, cw.shape), cw, sw, u * cw, u * sw], axis=1)
            G, r = X @ X.transpose(0, 2, 1), (X @ y)[..., None]
            try:
                coef = np.linalg.solve(G, r)
            except np.linalg.LinAlgError:  # singular (coincident times): least squares
                coef = np.linalg.pinv(G) @ r
            out.append(np.sum((y - np.sum(X * coef, axis=1)) ** 2, axis=1))
        return float(ws[int(np.argmin(np.concatenate(out)))])

    w = best(np.exp(np.linspace(math.log(lo), math.log(hi), 160)))
    return best(np.linspace(w / 1.03, w * 1.03, 61))


def _merge_wiggles(y, idx, t, half):
    """Turning points without the noise's wiggles: while two successive ones are closer than
    0.4 half periods, the pair is dropped (keeping, of the two extremes of the same kind, the
    more extreme one)."""
    idx = list(idx)
    while len(idx) >= 2:
        gaps = np.diff(t[idx])
        j = int(np.argmin(gaps))
        if not gaps[j] < 0.4 * half:
            break
        a, b = idx[j], idx[j + 1]  # a short swing a -> b
        # b is a max (min) when y[b] > y[a]; the previous extreme of b's kind is idx[j - 1]
        if j >= 1:
            prev = idx[j - 1]
            b_more = (y[b] > y[prev]) if y[b] > y[a] else (y[b] < y[prev])
            drop = (j - 1, j) if b_more else (j, j + 1)
        elif j + 2 < len(idx):
            nxt = idx[j + 2]
            a_more = (y[a] > y[nxt]) if y[a] > y[b] else (y[a] < y[nxt])
            drop = (j + 1, j + 2) if a_more else (j, j + 1)
        else:
            drop = (j, j + 1)
        idx = [i for k, i in enumerate(idx) if k not in drop]
    return np.asarray(idx, dtype=int)


def _search_band(T: float, dt: float) -> tuple[float, float]:
    """(lo, hi): the angular frequencies a least-squares sinusoid over a span ``T`` is sought
    in (from a quarter of a half swing over the span to 8, below a quarter of the sampling's
    Nyquist frequency)."""
    lo = 0.25 * math.pi / max(T, 1e-300)
    hi = max(min(8.0 * math.pi / max(T, 1e-300), math.pi / (4.0 * dt)), 1.01 * lo)
    return lo, hi


def _half_period(t, y, idx, level: float, dt: float, omega0: float | None) -> float:
    """The half period: the given one (pi/omega0), else the duration of the largest swing
    between two turning points (a noisy tail cannot disturb it), else a least-squares sinusoid
    over the part of the trace that moves (NaN for fewer than 8 samples).

    Arguments:
        t, y: the trace (despiked); ``idx``: its turning points; ``level``: the reversal they
            need; ``dt``: the sampling step; ``omega0``: the known frequency, or None.
    """
    if omega0 is not None:
        return math.pi / omega0
    if idx.size >= 2:
        k = int(np.argmax(np.abs(np.diff(y[idx]))))
        return float(t[idx[k + 1]] - t[idx[k]])
    if t.size < 8:
        return math.nan
    ref = float(np.median(y[-max(t.size // 8, 4):]))
    moving = np.flatnonzero(np.abs(y - ref) > level)
    stop = max(int(moving[-1]) + 1 if moving.size else t.size, 8)
    lo, hi = _search_band(float(t[stop - 1] - t[0]), dt)
    return math.pi / _sinusoid_frequency(t[:stop], y[:stop], lo, hi)


def _drop_pauses(y, idx, t, half: float):
    """(turning points, truncated): the noise's wiggles merged away (:func:`_merge_wiggles`)
    and, as a free oscillation reverses every half period, the turning points after a pause
    longer than 1.6 half periods dropped (the data had stopped: what follows are the noise's
    reversals); unchanged where the half period is unknown (NaN)."""
    if not math.isfinite(half):
        return idx, False
    idx = _merge_wiggles(y, idx, t, half)
    long = np.flatnonzero(np.diff(t[idx]) > 1.6 * half)
    if long.size:
        return idx[: long[0] + 1], True
    return idx, False


def _halt(t, y, idx, level: float, half: float, dt: float, truncated: bool):
    """(turning points, halted): whether after the last turning point the data come to rest
    and stay there (for half a period at least; at once where ``truncated``: a pause was
    cut off); the arrival at rest is appended as a turning point where the last swing ends
    outside the rest band. Else the pending extreme is the window's edge (not halted).

    Arguments:
        t, y: the trace (despiked); ``idx``: its turning points; ``level``: the reversal they
            need; ``half``: the half period (NaN: unknown); ``dt``: the sampling step.
    """
    last = int(idx[-1]) if idx.size else 0
    tail = y[last:]
    if tail.size <= 8:
        return idx, False
    end_part = tail[-max(tail.size // 4, 4):]
    rest = float(np.median(end_part))
    band = max(0.5 * level, 3.0 * MAD * float(np.median(np.abs(end_part - rest))))
    inside = np.abs(tail - rest) <= band
    # arrival: the first sample after which 95 % of the samples stay inside the band
    later_out = np.cumsum(~inside[::-1])[::-1]
    frac = later_out / np.arange(tail.size, 0, -1)
    ok = np.flatnonzero(inside & (frac <= 0.05))
    if not ok.size and truncated:
        ok = np.flatnonzero(inside)
    if not ok.size:
        return idx, False
    arrive = last + int(ok[0])
    stay = float(t[-1] - t[arrive])
    ref = half if math.isfinite(half) else float(t[arrive] - t[0])
    if not (truncated or (stay >= 0.5 * ref and stay > 4 * dt)):
        return idx, False
    # the data rest for half a period (a swing would have reversed): they halted, at the
    # arrival (the last turning point itself when the last swing is within the band)
    if arrive > last and abs(y[arrive] - y[last]) > level:
        return np.append(idx, arrive), True
    return idx, bool(idx.size)


def _offset(t, y, idx, tx, halted: bool, end_t: float) -> float:
    """The offset: the centres of successive half swings alternate about it by the friction's
    shift (and the decrement): the mean of an even number of them; with fewer than four
    turning points of data that halt, the rest position (within mu g/w0^2 of it; the centre of
    one half swing is off by half its decrement, which drag makes large).

    Arguments:
        t, y: the trace (despiked); ``idx``, ``tx``: the turning points and their positions;
            ``halted``, ``end_t``: whether and where the data stop moving.
    """
    if halted and tx.size <= 3 and int(idx[-1]) < t.size - 8:
        return float(np.median(y[int(idx[-1]):]))
    if tx.size >= 3:
        mids = 0.5 * (tx[:-1] + tx[1:])
        k = min(mids.size, 40)
        k -= k % 2
        return float(np.mean(mids[:k]))
    if tx.size == 2:
        return float(0.5 * (tx[0] + tx[1]))
    moving = t <= end_t
    return float(np.median(y[moving])) if np.any(moving) else float(np.median(y))


def _spacing_frequency(t, y, conf, off: float) -> tuple[float, float]:
    """(omega, spread) from three or more confirmed turning points: pi over the slope of a
    line through their times (the spectrum's peak where it is not positive); the spread from
    the slope's standard error."""
    k = np.arange(conf.size, dtype=float)
    tk = t[conf]
    coef = np.polyfit(k, tk, 1)
    slope = float(coef[0])
    omega = math.pi / slope if slope > 0 else _frequency_fft(t, y - off)
    resid = tk - np.polyval(coef, k)
    se = float(np.sqrt(np.sum(resid * resid) / max(conf.size - 2, 1)
                       / np.sum((k - k.mean()) ** 2)))
    return omega, float(min(0.3, max(3e-3, 4.0 * se / max(slope, 1e-300),
                                     0.5 / conf.size ** 2)))


def _frequency(t, y, conf, off: float, end_t: float, half: float, dt: float,
               omega0: float | None) -> tuple[float, float]:
    """(omega, spread): the given omega0 (spread 0); else from the spacing of the confirmed
    turning points ``conf`` (:func:`_spacing_frequency`; two: pi over their distance, spread
    0.15); else a least-squares sinusoid over the part that moves (the spectrum's peak for
    fewer than 8 samples), spread 0.3.

    Arguments:
        t, y: the trace (despiked); ``off``: its offset; ``end_t``: where the data stop
            moving; ``half``: the half period (NaN: unknown); ``dt``: the sampling step.
    """
    if omega0 is not None:
        return float(omega0), 0.0
    if conf.size >= 3:
        return _spacing_frequency(t, y, conf, off)
    if conf.size == 2:
        return math.pi / float(t[conf[1]] - t[conf[0]]), 0.15
    stop = int(np.searchsorted(t, end_t + (0.5 * half if math.isfinite(half) else 0.0)))
    stop = min(max(stop, 8), t.size)
    tm, ym = t[:stop], y[:stop]
    T = float(tm[-1] - tm[0]) if tm.size > 1 else float(t[-1] - t[0])
    lo, hi = _search_band(T, dt)
    omega = _sinusoid_frequency(tm, ym, lo, hi) if tm.size >= 8 else \
        _frequency_fft(t, y - off)
    return omega, 0.3


#: the last scans (:func:`_scan`), by the digests of their arrays: the fits of one trace
#: (a model ranking's seven, a search's) read it once (16 scans of 5,000 samples took
#: 0.2-0.3 s of ``dampax fit --example``)
_SCANS: dict = {}
_SCANS_KEPT = 8


def _scan(t: np.ndarray, x: np.ndarray, omega0: float | None) -> Analysis:
    """:func:`_scan_arrays`, remembered for the last :data:`_SCANS_KEPT` traces (an
    Analysis is not changed after it is made: ``analyse`` replaces, never assigns)."""
    t, x = np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(x, dtype=float)
    key = (hashlib.blake2b(t.tobytes(), digest_size=16).digest(),
           hashlib.blake2b(x.tobytes(), digest_size=16).digest(), t.size,
           None if omega0 is None else float(omega0))
    if key not in _SCANS:
        if len(_SCANS) >= _SCANS_KEPT:
            _SCANS.pop(next(iter(_SCANS)))
        _SCANS[key] = _scan_arrays(t, x, omega0)
    return _SCANS[key]


def _scan_arrays(t: np.ndarray, x: np.ndarray, omega0: float | None) -> Analysis:
    """Turning points, offset, frequency, noise and where the data stop moving.

    Arguments:
        t, x: the trace (sorted, finite).
        omega0: the angular frequency when it is known (an oscillator without
            ``fit_omega0``): it sets the half period that separates a halt from a pause.

    Returns:
        An :class:`Analysis`.
    """
    noise = noise_sigma(x)
    y = despike(x)
    half_range = 0.5 * float(np.ptp(y))
    level = max(8.0 * noise, 0.05 * half_range)
    idx, _ = zigzag(y, level)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    known = omega0 if omega0 is not None and math.isfinite(omega0) and omega0 > 0 else None
    half = _half_period(t, y, idx, level, dt, known)
    idx, truncated = _drop_pauses(y, idx, t, half)
    idx, halted = _halt(t, y, idx, level, half, dt, truncated)
    end_t = float(t[idx[-1]]) if halted else float(t[-1])
    tx = y[idx]
    off = _offset(t, y, idx, tx, halted, end_t)
    # the frequency from the turning points that reversals confirmed (the arrival at rest is
    # not one: the data reach the rest band a little before they stop)
    omega, spread = _frequency(t, y, idx[:-1] if halted else idx, off, end_t, half, dt, known)
    return Analysis(offset=off, omega=omega, noise=noise, ext_i=idx, ext_t=t[idx],
                    ext_x=tx - off, n_turns=int(idx.size), halted=halted, end_t=end_t,
                    omega_spread=spread, level=level)


#: the motion before a record's first turning point counts as free when it covers at least
#: this share of what a sinusoid of the next half swing's range covers in that time
#: (:func:`free_from_start`)
FREE_SHARE = 0.5
#: ... and when that turning point comes within this many half periods: a half swing, with room
#: for noise on the flat bottom of a strongly damped swing (no hold longer than T/8 passes)
FREE_HALF = 1.25


def free_from_start(t, y, an: Analysis) -> bool:
    """Whether the record moves freely from its first sample: nothing to skip.

    A hand release leaves a hold (the data still) or a slow lead-in before the release, its
    first turning point; a record of the free decay itself reaches its first turning point
    within half a period, moving as the oscillation does. Over the time d before the first
    turning point a sinusoid of amplitude A covers A (1 - cos w d) = 2 A sin^2(w d / 2), where
    2 A is the range of the next half swing (to the second turning point, or the record's
    end): the record is free from its start when d < :data:`FREE_HALF` pi / w and the data
    cover at least :data:`FREE_SHARE` of that. Skipping the first half swing of such a record
    discards the swing that carries the most information: on records of 1.5-3 half swings
    the fit lost half its samples or more, and with them the decay (confident wrong answers:
    fit_calibration.py seed 2, draws 3 and 10).

    Arguments:
        t, y: the whole trace (despiked positions).
        an: its :class:`Analysis` (turning points, angular frequency).
    """
    if an.ext_i.size == 0 or not (math.isfinite(an.omega) and an.omega > 0):
        return False
    first = int(an.ext_i[0])
    d = float(t[first] - t[0])
    if d >= FREE_HALF * math.pi / an.omega:
        return False
    nxt = int(an.ext_i[1]) if an.ext_i.size > 1 else len(y) - 1
    covered = float(np.ptp(y[:first + 1]))
    span = float(np.ptp(y[first:nxt + 1]))
    return covered >= FREE_SHARE * span * math.sin(0.5 * an.omega * d) ** 2


def start_index(t, x, an: Analysis, start) -> int:
    """Index of the first sample of the fit window.

    Arguments:
        t, x: the whole trace.
        an: its :class:`Analysis`.
        start: "auto" (the first turning point after the largest excursion, which skips a
            hand release; for a trace with fewer than 8 turning points, the largest excursion
            itself when the trace begins within the swing that reaches it and the data move in
            the quarter period before it), "data" / None (the first sample) or a time.
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
    y = despike(x)
    if free_from_start(t, y, an):
        return 0
    i_big = int(np.argmax(np.abs(y - an.offset)))
    quarter = 0.5 * math.pi / an.omega
    before = (t >= t[i_big] - quarter) & (t <= t[i_big])
    near = an.ext_i[np.abs(an.ext_t - t[i_big]) <= 0.25 * quarter]
    spare = 0.25 * 0.5 * float(np.ptp(y[i_big:]))
    if an.n_turns < 8 and near.size and t[i_big] - t[0] <= 2.0 * quarter and (
            t[i_big] - t[0] < quarter or float(np.ptp(y[before])) > 2.0 * an.level) and \
            0.5 * float(np.ptp(y[near[0]:])) >= spare:
        # a trace that halts within a few swings cannot spare one: when it begins within the
        # swing that reaches the largest excursion, and that is a turning point (the data
        # move before it: no hold, no lead-in of a hand release), the fit starts there
        return int(near[0])
    later = an.ext_i[an.ext_t > t[i_big] + 0.25 * math.pi / an.omega]
    if later.size:
        # skip the release only when that leaves a swing to fit: the data after the first
        # turning point must still move by a quarter of what they moved from the release on,
        # above their noise (after an early halt a noise extreme passes the first test at a
        # noise of 7 % of the amplitude: wide draw 49 of fit_calibration.py seed 13)
        if 0.5 * float(np.ptp(y[later[0]:])) >= spare and above_noise(x[later[0]:]):
            return int(later[0])
        return i_big
    return 0


def analyse(t: np.ndarray, x: np.ndarray, *, omega0: float | None = None,
            window: tuple | None = None) -> Analysis:
    """What a trace says before any fit; with ``window``, where the fit window lies, too.

    Arguments:
        t, x: the trace (sorted, finite).
        omega0: the angular frequency when it is known (an oscillator without
            ``fit_omega0``): it sets the half period that separates a halt from a pause.
        window: None (analyse the whole trace) or (start, end) of ``dp.Window``: the whole
            trace is scanned (without ``omega0``) to place the window (:func:`start_index`),
            then the window is scanned with ``omega0`` (one scan when that is the same).

    Returns:
        An :class:`Analysis` of the window (``window`` holds its indices, ``whole`` the
        scan of the whole trace).

    Raises:
        ValueError: the window holds fewer than 10 samples, or ``start`` is not valid.
    """
    if window is None:
        an = _scan(t, x, omega0)
        return replace(an, window=(0, len(t)), whole=an)
    start, end = window
    whole = _scan(t, x, None)
    i0 = start_index(t, x, whole, start)
    i1 = len(t) if end is None else int(np.searchsorted(t, float(end), side="right"))
    if i1 - i0 < 10:
        raise ValueError(f"Window.start, Window.end: the fit window [{t[min(i0, len(t) - 1)]:g}, "
                         f"{end}] holds fewer than 10 samples (the trace runs from {t[0]:g} "
                         f"to {t[-1]:g} s)")
    same = i0 == 0 and i1 == len(t) and omega0 is None
    an = whole if same else _scan(t[i0:i1], x[i0:i1], omega0)
    return replace(an, window=(i0, i1), whole=whole)
