"""Checks of fits (numpy): degenerate input before a fit, named failures and the adequacy of
the model after it (issue 11, item 3; issue 25: statistics instead of tuned thresholds).

Before a fit, :func:`check_trace` turns input that holds no free decay into a ValueError that
says why: constant time, a constant trace, a trace within the excursions of pure white noise,
an amplitude that grows (growing or time-reversed data). Nothing else is refused: a trace that
halts after one swing is fitted, and the fit says what the data determine.

After a fit, ``_assess.assess`` judges it by what it shows (its table lists the checks) and
returns the failures (``success = False`` with a one-line reason) and, separately, whether the
model describes the data (``adequate``). No check compares with zero crossings (friction and
drag move them) or with thresholds set on measured files; the levels are p-values of tests
whose null distribution is known (calibrated on the generated family of
benchmarks/fit_calibration.py):

failures
    the optimizer did not converge (a fit that ran out of steps on a flat valley, where one
    more Gauss-Newton step would move the parameters by a small fraction of their standard
    errors, counts as converged: :func:`newton_decrement`); a standard error is not finite; a
    parameter ran to absurd values (d0/(w0 A), d1/w0 or d2 A/w0 above :data:`ABSURD`, or an
    amplitude far beyond the data); the motion ends of model and data differ (the residuals
    between them exceed those elsewhere, :func:`end_mismatch`, or grossly:
    :data:`END_PERIODS`); for the exact model ("reference") residuals that AR(1) noise cannot
    produce (:func:`residual_structure`: a local optimum); intervals that do not hold (the
    profile of the cost rises far less over them than they assume, :func:`profile_ratios`
    below :data:`PROFILE_FAIL`; a smaller shortfall widens that side of the interval); or a
    damping constant held at 0 and the rest refitted finds a lower cost (a local optimum;
    :func:`bound_tests`).
refusals (ValueError, the true reason)
    the split between damping terms is not determined: they are measured together, none alone
    (a Wald test), or the Jacobian is singular (:func:`null_directions`: over a single swing
    Coulomb friction only moves the centre, which the offset does too).
notes (success stays True)
    a damping constant whose interval excludes 0 at 1 % is not needed by the likelihood-ratio
    test at 1 % (:func:`bound_tests`: a valley in the cost toward the bound, the split between
    the terms weakly determined): every interval is widened to reach the held fit's values
    (``_profile.widening_toward``: the profile likelihood's interval holds them at levels
    beyond that chi2).
    no measurable decay (the Wald test that the fitted damping constants are all zero, with
    the intervals' covariance, does not reject at 5 %): the values and their intervals, which
    reach 0, are then upper bounds.
adequacy
    the motion ends agree, and the residuals either pass :func:`residual_structure` or stay
    below :data:`RMS_AMPLITUDE` of the amplitude. Structured residuals of an approximate model
    (the ansatz) are a note: the intervals of ``conf_interval`` allow for them.
"""

from __future__ import annotations

import math

import numpy as np

from ._core import FIT_RESULTS, is_code
from ._dist import chi2_sf, f_sf
from ._guess import Analysis, despike
from ._inputs import check_sampling
from ._intervals import ar1_coefficient, hac_covariance
from ._noise import above_noise, noise_excursion

#: the residuals hold structure beyond AR(1) noise below this p-value of
#: :func:`residual_structure` (a failure of the exact model "reference", a note otherwise)
STRUCTURE_P = 1e-3
#: the residuals between the motion ends of model and data exceed those elsewhere below this
#: p-value (:func:`end_mismatch`): a failure
END_P = 1e-3

def check_trace(t: np.ndarray, x: np.ndarray, an: Analysis) -> None:
    """ValueError when the (sorted, finite) trace holds no free decay to fit.

    Refused are only traces that hold no signal or no decay, whatever its damping: constant
    time, a constant trace, a trace within the excursions of pure white noise (half its
    peak-to-peak below ``_noise.noise_excursion`` noise sigmas, the noise from the higher
    differences, and so at every coarser scale of block means: ``_noise.above_noise``), and
    a trace whose turning points grow (growing or time-reversed data). A trace that halts
    after one swing is fitted: whether its constants are separately identifiable is the
    fit's to say (``_assess.assess``).

    Arguments:
        t, x: the fit window.
        an: its :class:`~dampax._fit._guess.Analysis`.

    Raises:
        ValueError: constant time, constant trace, pure noise, or an amplitude that grows.
    """
    check_sampling(t, x)
    if an.noise > 0 and not above_noise(x):
        half = 0.5 * float(np.ptp(despike(np.asarray(x, dtype=float))))
        raise ValueError(f"x: no free oscillation above the noise: the trace's half "
                         f"peak-to-peak ({half:.3g}) is within {noise_excursion(t.size):.1f} "
                         f"noise sigmas (sigma = {an.noise:.3g}), as pure white noise of "
                         f"{t.size} samples, and so are its means over 4, 16, ... samples")
    # growing (or time-reversed) data: the swings between the turning points grow
    swings = np.abs(np.diff(an.ext_x))
    swings = swings[swings > 2.0 * an.level]  # clear of the noise's reversals
    n = swings.size
    if n >= 3:
        first, last = float(np.median(swings[: (n + 1) // 2])), float(np.median(swings[n // 2:]))
        slope = np.polyfit(np.arange(n), np.log(np.maximum(swings, 1e-300)), 1)[0]
        if last > 1.05 * first and slope > 0:
            raise ValueError(f"x: the amplitude grows (swings {0.5 * first:.3g} -> "
                             f"{0.5 * last:.3g}): not a free decay (time-reversed or driven "
                             "data?)")


def motion_end(t: np.ndarray, y: np.ndarray, period: float, level: float) -> float:
    """The last time at which a trace still swings: half its peak-to-peak over one period
    (a sliding window) exceeds ``level``. ``t[0]`` when it never does.

    A block that sticks off centre does not count as moving (peak-to-peak, not distance from
    the offset); glitches of one or two samples are removed by a running median first.
    """
    y = despike(np.asarray(y, dtype=float))
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    w = max(int(round(period / max(dt, 1e-300))), 2)
    if y.size <= w:
        return float(t[-1]) if 0.5 * float(np.ptp(y)) > level else float(t[0])
    view = np.lib.stride_tricks.sliding_window_view(y, w)
    half = 0.5 * (view.max(axis=1) - view.min(axis=1))
    moving = np.flatnonzero(half > level)
    if moving.size == 0:
        return float(t[0])
    return float(t[min(moving[-1] + w - 1, t.size - 1)])


def phase_drift(t: np.ndarray, x: np.ndarray, model: np.ndarray, w0: float, offset: float,
                level: float) -> float:
    """Largest excursion [rad] of the phase of the data relative to the model, period by
    period: the angle of sum (x - offset) e^(-i w0 t) over sum (model - offset) e^(-i w0 t)
    on each whole period where the model swings above ``level``, minus its median."""
    period = 2.0 * math.pi / w0
    k = np.floor((t - t[0]) / period).astype(np.int64)
    phases = []
    rot = np.exp(-1j * w0 * (t - t[0]))
    # only the periods that hold samples (at most t.size of them, however long the gaps
    # between them: a loop over every period ran 1e9 times after one stray time stamp)
    periods, counts = np.unique(k[k < k[-1]], return_counts=True)  # whole periods only
    for j in periods[counts >= 8]:
        sel = k == j
        ym = model[sel] - offset
        if 0.5 * float(np.ptp(ym)) <= level:
            continue
        zd = np.sum((x[sel] - offset) * rot[sel])
        zm = np.sum(ym * rot[sel])
        if abs(zm) > 0:
            phases.append(np.angle(zd / zm))
    if len(phases) < 3:
        return 0.0
    ph = np.unwrap(np.asarray(phases))
    return float(np.max(np.abs(ph - np.median(ph))))


def _block_regressions(t, r, w0: float, phi: float, edges) -> tuple[np.ndarray, float]:
    """(q, rss) of :func:`residual_structure`: per block (rows ``edges[j]`` to
    ``edges[j + 1]``) the explained sum of squares of the prewhitened residuals regressed on
    the prewhitened 1, cos(w0 t), sin(w0 t) (the rows after the block's first), and the sum
    of what the regressions leave. All blocks at once, by their 3 x 3 normal equations
    (pseudo-inverse: a degenerate block explains what its columns span); the same span as
    cos/sin of the time from each block's start, so the same numbers as a least-squares fit
    per block (67 of them took 13-30 ms a call). The phases from the window's start, so that
    clock times far from 0 (a logger's epoch seconds) keep their digits."""
    s = np.asarray(t, dtype=float) - float(t[0])
    X = np.stack([np.ones_like(s), np.cos(w0 * s), np.sin(w0 * s)], axis=1)
    Xw = np.concatenate([X[:1], X[1:] - phi * X[:-1]])
    rw = np.concatenate([r[:1], r[1:] - phi * r[:-1]])
    keep = np.ones(r.size)
    keep[edges[:-1]] = 0.0  # each block's first row has no predecessor in the block
    Xw, rw = Xw * keep[:, None], rw * keep
    starts = edges[:-1]
    A = np.add.reduceat(Xw[:, :, None] * Xw[:, None, :], starts, axis=0)
    b = np.add.reduceat(Xw * rw[:, None], starts, axis=0)
    rr = np.add.reduceat(rw * rw, starts)
    explained = np.einsum("ji,jik,jk->j", b, np.linalg.pinv(A, hermitian=True), b)
    explained = np.clip(explained, 0.0, rr)
    return explained, float(np.sum(rr - explained))


def residual_structure(t: np.ndarray, r: np.ndarray, w0: float) -> dict:
    """A test of the residuals against AR(1) noise: do they hold a level shift or a swing at
    the oscillation's frequency that the noise cannot produce, anywhere in the window?

    The window is cut into blocks of half a period (at least 16 samples). In each block the
    residuals, prewhitened by their own lag-1 autocorrelation phi (AR(1) noise is white after
    it), are regressed on the prewhitened 1, cos(w0 t) and sin(w0 t): what a local optimum,
    an early or late halt or a wrong frequency leaves behind. With s2 the pooled variance of
    what the regressions leave, q_j = (explained sum of squares of block j) / s2 is chi2(3)
    under the null (the residuals are AR(1) noise), their sum chi2(3 J).

    Returns:
        dict with phi, blocks J, p_global (the sum), p_local (the largest q_j, Bonferroni over
        the blocks), p (the smaller of the two, doubled: both tests), the block with the
        largest q_j as (t_from, t_to), and q_share (its share of the sum).
    """

    r = np.asarray(r, dtype=float)
    n = r.size
    out = dict(phi=0.0, blocks=0, p_global=1.0, p_local=1.0, p=1.0, worst=(math.nan, math.nan),
               q_share=0.0)
    if not np.all(np.isfinite(r)):  # a curve that is not finite everywhere: no test (p NaN;
        return {**out, "p_global": math.nan, "p_local": math.nan, "p": math.nan}  # it fails)
    if n < 16 or not (math.isfinite(w0) and w0 > 0):
        return out
    dt = float(np.median(np.diff(t)))
    size = int(max(round(math.pi / w0 / dt), 16))
    J = max(n // size, 1)
    edges = np.linspace(0, n, J + 1).astype(int)
    # phi of the residuals about their mean: AR(1) noise has none, and a level that the model
    # lacks (an offset held at 0 that the data have) read as phi -> 1 whitened itself away
    phi = ar1_coefficient(r - np.mean(r), clip=(-0.99, 0.99))
    q, rss = _block_regressions(t, r, w0, phi, edges)
    dof = n - J * 4  # each block: its rows but the first, less 3 coefficients
    s2 = rss / max(dof, 1)
    if not s2 > 0:
        return out
    q = q / s2
    p_global = chi2_sf(float(q.sum()), 3 * J)
    k = int(np.argmax(q))
    p_local = float(min(1.0, J * chi2_sf(float(q[k]), 3)))
    return dict(phi=phi, blocks=J, p_global=p_global, p_local=p_local,
                p=min(1.0, 2.0 * min(p_global, p_local)),
                worst=(float(t[edges[k]]), float(t[edges[k + 1] - 1])),
                q_share=float(q[k] / q.sum()) if q.sum() > 0 else 0.0)


def model_end(t: np.ndarray, curve: np.ndarray) -> float:
    """Where the model stops moving: after it the curve is constant (the block halted);
    t[-1] when it moves to the end."""
    c = np.asarray(curve, dtype=float)
    scale = float(np.ptp(c))
    moving = np.flatnonzero(np.abs(np.diff(c)) > 1e-9 * max(scale, 1e-300))
    if moving.size == 0:
        return float(t[0])
    return float(t[min(int(moving[-1]) + 1, t.size - 1)])


def end_mismatch(t, r, t_model, t_data, phi):
    """p-value that the residuals between the motion ends of model and data (where one of them
    swings and the other rests) are no larger than elsewhere: the ratio of their mean squares
    against F(m1, m2), m the effective numbers of samples of each part (m (1 - phi^2) /
    (1 + phi^2) for AR(1) noise). 1 when the ends agree."""

    lo, hi = min(t_model, t_data), max(t_model, t_data)
    inside = (t > lo) & (t <= hi)
    m = int(np.sum(inside))
    if m < 4 or m > r.size - 8:
        return 1.0
    ref = float(np.mean(r[~inside] ** 2))
    if not ref > 0:
        return 1.0
    ratio = float(np.mean(r[inside] ** 2)) / ref
    shrink = (1.0 - phi * phi) / (1.0 + phi * phi)
    m1, m2 = m * shrink, (r.size - m) * shrink
    return f_sf(ratio, m1, m2) if m1 > 0 and m2 > 0 else 1.0


def looks_stuck(t, x, curve, an: Analysis, w0: float, code) -> bool:
    """Whether a fit of the exact model shows what a local optimum leaves: the optimizer did
    not converge, the residuals hold structure that AR(1) noise cannot produce
    (:func:`residual_structure`), or the motion ends of model and data disagree
    (:func:`end_mismatch`). Then ``fit`` searches further (a batch of starts)."""

    c = np.asarray(curve, dtype=float)
    if not is_code(code, FIT_RESULTS.successful) or not np.all(np.isfinite(c)):
        return True
    r = np.asarray(x, dtype=float) - c
    st = residual_structure(t, r, w0)
    if st["p"] < STRUCTURE_P:
        return True
    end_d = an.end_t if an.halted else float(t[-1])
    return end_mismatch(t, r, model_end(t, c), end_d, st["phi"]) < END_P


def interval_sd(jac, rows, params, t):
    """The sd of the intervals (:func:`~dampax._fit._intervals.hac_covariance`) of the
    Jacobian's columns, or None."""

    w0 = params.get("w0", math.nan)
    if not (math.isfinite(w0) and w0 > 0) or len(t) < 2:
        return None
    try:
        cov, _ = hac_covariance(jac, rows, period_samples=2.0 * math.pi / w0 / float(
            np.median(np.diff(t))))
    except (ValueError, np.linalg.LinAlgError):
        return None
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return sd if np.all(np.isfinite(sd)) else None


def newton_decrement(jac, rows, values=None, names=()) -> float:
    """What one more Gauss-Newton step would take off the cost, in noise variances:
    r^T J (J^T J)^+ J^T r / s2 with s2 = r^T r / (n - p); its square root bounds how many
    (delta-method) standard errors a parameter would still move. Damping constants that the
    step would push below 0 stay at their bound (their columns are dropped: the optimum of
    a bounded problem).

    Arguments:
        jac, rows: the Jacobian (physical parameters) and residuals of the data rows.
        values, names: the parameters (in the order of the columns) and their names.
    """
    return newton_step(jac, rows, values, names)[0]


def data_rows(out, vary, n: int):
    """(jac, rows) of a fit (a ``_core.CoreResult``) on its window's ``n`` samples: the
    Jacobian's columns those of the varied parameters (in the order of their fields), None
    where the fit returned none."""
    idx = [i for i, on in enumerate(vary._asdict().values()) if on]
    jac = np.asarray(out.jac, dtype=float)[:n][:, idx] if out.jac is not None else None
    rows = np.asarray(out.resid, dtype=float)[:n] if out.resid is not None else None
    return jac, rows


def newton_step(jac, rows, values=None, names=()):
    """(decrement, step) of :func:`newton_decrement`: the decrement in noise variances and
    the Gauss-Newton step of every parameter (0 for the constants held at their bound; None
    where the decrement is 0 or infinite)."""
    J = np.asarray(jac, dtype=float)
    r = np.asarray(rows, dtype=float)
    if J.ndim != 2 or not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        return math.inf, None
    n, p = J.shape
    s2 = float(r @ r) / max(n - p, 1)
    if not s2 > 0:
        return 0.0, None
    keep = np.ones(p, dtype=bool)
    vals = np.asarray(values if values is not None else np.zeros(p), dtype=float)
    for _ in range(p):
        Jk = J[:, keep]
        # the residuals are model - data: the step that lowers the cost is -J^+ r
        step = -np.linalg.lstsq(Jk, r, rcond=None)[0]
        full = np.zeros(p)
        full[keep] = step
        out = [k for k in range(p) if keep[k] and k < len(names)
               and names[k] in ("mu", "b", "D") and vals[k] + full[k] < 0.0]
        if not out:
            g = Jk.T @ r
            return float(-(g @ step)) / s2, full
        keep[out] = False
        if not keep.any():
            return 0.0, None
    return 0.0, None


def null_directions(jac, names) -> list:
    """The exact degeneracies of a fit: the parameters whose effects on the trace cancel.

    The columns of the Jacobian (physical parameters, data rows) are scaled to unit norm;
    singular values below numpy's rank tolerance (largest singular value times max(n, p)
    times the machine epsilon, as ``numpy.linalg.matrix_rank``) span directions the data
    cannot see at all. Columns that are zero (a constant at its bound that the model does not
    feel) are left out: they have no standard error already.

    Arguments:
        jac: the Jacobian (n x p) or None; names: the parameters of its columns.

    Returns:
        A list with, for each null direction, the names of the parameters that take part
        in it (|component| above 0.1 of the unit vector), largest first; empty when the
        Jacobian has full rank (or is missing or not finite).
    """
    if jac is None:
        return []
    J = np.asarray(jac, dtype=float)
    if J.ndim != 2 or J.shape[1] != len(names) or not np.all(np.isfinite(J)):
        return []
    norm = np.sqrt(np.sum(J * J, axis=0))
    live = np.flatnonzero(norm > 0)
    if live.size < 2:
        return []
    Jn = J[:, live] / norm[live]
    _, s, vt = np.linalg.svd(Jn, full_matrices=False)
    tol = s[0] * max(Jn.shape) * np.finfo(float).eps
    out = []
    for k in np.flatnonzero(s <= tol):
        v = np.abs(vt[k])
        order = [int(i) for i in np.argsort(-v) if v[i] > 0.1]
        out.append([names[int(live[i])] for i in order])
    return out
