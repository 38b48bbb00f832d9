"""Checks of fits (numpy): degenerate input before a fit, named failures and the adequacy of
the model after it (issue 11, item 3).

Before a fit, :func:`check_trace` turns input that has no free decay in it into a ValueError
that says why: constant time, a constant trace, no oscillation above the noise, fewer than two
periods, an amplitude that grows (growing or time-reversed data).

After a fit, :func:`assess` returns the failures (``success = False`` with a one-line reason)
and, separately, whether the model describes the data (``adequate``):

failures
    the optimizer did not converge; no measurable decay (every fitted damping constant
    within two standard errors of zero); a parameter ran to absurd values (d0/(w0 A), d1/w0 or
    d2 A/w0 above :data:`ABSURD`, or an amplitude far beyond the data); the fitted w0 differs
    from the data's zero-crossing frequency by more than :data:`W0_TOLERANCE`; the model stops
    moving well before the data do, or the reverse (:func:`motion_end`); a standard error of a
    fitted parameter is not finite.
adequacy
    the residuals are far above the noise level estimated from the data (rms above
    :data:`RMS_NOISE` noise and above :data:`RMS_AMPLITUDE` of the amplitude), a systematic
    phase drift between data and model (:func:`phase_drift` above :data:`PHASE_DRIFT` rad), or
    a fitted halt far from where the data stop moving. A smaller phase drift (above
    :data:`PHASE_NOTE`) is reported as a note: the residuals are correlated.
"""

from __future__ import annotations

import math

import numpy as np

from ._guess import Analysis, despike

#: a damping ratio above this is absurd for a trace that oscillates (d0/(w0 A), d1/w0, d2 A/w0)
ABSURD = 10.0
#: largest relative difference between the fitted w0 and the zero-crossing frequency
W0_TOLERANCE = 0.02
#: the model is inadequate when its rms exceeds this many noise sigmas ...
RMS_NOISE = 5.0
#: ... and this fraction of the first amplitude
RMS_AMPLITUDE = 0.05
#: the model is inadequate when its phase drifts from the data's by more than this [rad]
#: (a quarter period: the model swings at the wrong place)
PHASE_DRIFT = 1.5
#: a phase drift above this [rad] is noted: the residuals are correlated, the delta-method
#: stderr understate the uncertainty (use conf_interval)
PHASE_NOTE = 0.25
#: the motion ends of data and model may differ by this many periods (or a tenth of the window)
END_PERIODS = 4.0


def check_sampling(t: np.ndarray, x: np.ndarray) -> None:
    """ValueError for constant time, mostly repeated time stamps or a constant trace (the
    checks that must come before any analysis)."""
    span = float(t[-1] - t[0])
    if not span > 0.0:
        raise ValueError("t: all sample times are equal (constant time): nothing to fit")
    distinct = np.unique(t).size
    if distinct < 0.5 * t.size:
        raise ValueError(f"t: only {distinct} distinct times among {t.size} samples; "
                         "rebuild time from the sample rate (load_trace(rate=...), "
                         "dampax fit --rate)")
    ptp = float(np.ptp(x))
    if not ptp > 1e-12 * max(float(np.max(np.abs(x))), 1e-300):
        raise ValueError("x: the trace is constant: nothing oscillates")


def check_trace(t: np.ndarray, x: np.ndarray, an: Analysis) -> None:
    """ValueError when the (sorted, finite) trace holds no free decay to fit.

    Arguments:
        t, x: the fit window.
        an: its :class:`~dampax._fit._guess.Analysis`.

    Raises:
        ValueError: constant time, constant trace, no oscillation above the noise, fewer than
            two periods, or an amplitude that grows (growing or time-reversed data).
    """
    check_sampling(t, x)
    span = float(t[-1] - t[0])
    if an.n_cross < 4 or an.ext_x.size < 3:
        raise ValueError(f"x: only {an.n_cross} zero crossings above the noise "
                         f"(sigma = {an.noise:.3g}): no free oscillation to fit (pure noise, "
                         "or fewer than two periods)")
    periods = span * an.omega / (2.0 * math.pi)
    if periods < 2.0:
        raise ValueError(f"the fit window holds {periods:.2f} periods; a fit needs at least two")
    E = np.abs(an.ext_x)
    if E.size >= 4 and an.noise > 0 and float(np.median(E[:4])) < 10.0 * an.noise:
        raise ValueError(f"x: the swings ({float(np.median(E[:4])):.3g}) are within 10 noise "
                         f"sigmas ({an.noise:.3g}): no free oscillation above the noise")
    # growing (or time-reversed) data: the swings of the second half exceed the first half's
    n = E.size
    if n >= 4:
        first, last = float(np.median(E[: n // 2])), float(np.median(E[n - n // 2:]))
        slope = np.polyfit(an.ext_t - an.ext_t[0], np.log(np.maximum(E, 1e-300)), 1)[0]
        if last > 1.05 * first and slope > 0:
            raise ValueError(f"x: the amplitude grows ({first:.3g} -> {last:.3g}): not a free "
                             "decay (time-reversed or driven data?)")


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
    k = np.floor((t - t[0]) / period).astype(int)
    phases = []
    rot = np.exp(-1j * w0 * (t - t[0]))
    for j in range(int(k[-1])):  # whole periods only
        sel = k == j
        if np.sum(sel) < 8:
            continue
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


def assess(*, t, x, curve, params: dict, stderr: dict, varied, derived: dict, an: Analysis,
           converged: bool, message: str, kind: str = "trace"):
    """Failures and adequacy of a finished fit.

    Arguments:
        t, x, curve: the fitted window and the model on it.
        params, stderr, varied, derived: of the fit (``derived`` holds d0, d1, d2, A).
        an: the :class:`Analysis` of the window (noise, zero-crossing frequency).
        converged: the optimizer converged; ``message``: its message.
        kind: "trace" (every check) or "envelope" (the optimizer and the standard errors).

    Returns:
        (failures, inadequacies, diagnostics): two lists of one-line reasons and a dict of the
        measured numbers (noise, rms / noise, w0 / crossing frequency - 1, motion ends,
        phase drift).
    """
    fails, bad, diag = [], [], {}
    if not converged:
        fails.append(f"the optimizer did not converge ({message})")
    if not all(math.isfinite(params.get(n, math.nan)) for n in varied):
        if converged:
            fails.append("the fitted parameters are not finite")
        return fails, ["the fit produced no finite model"], diag
    nonfinite = [n for n in varied if not math.isfinite(stderr.get(n, math.nan))]
    if nonfinite:
        fails.append(f"the standard error of {', '.join(nonfinite)} is not finite (the data do "
                     "not determine it)")
    damping = [n for n in ("mu", "b", "D") if n in varied]
    if damping and all(not params[n] > 2.0 * stderr.get(n, math.nan) for n in damping):
        fails.append(f"no measurable decay: every fitted damping constant "
                     f"({', '.join(damping)}) is consistent with zero")
    if kind != "trace":
        return fails, bad, diag
    w0 = params["w0"]
    A = derived.get("A", math.nan)
    d0, d1, d2 = derived["d0"], derived["d1"], derived["d2"]
    span_x = float(np.ptp(x))
    if not (math.isfinite(A) and A > 0 and math.isfinite(w0) and w0 > 0):
        fails.append("the fitted amplitude or frequency is not a positive finite number")
        return fails, bad, diag
    ratios = {"d0/(w0 A)": d0 / (w0 * A), "d1/w0": d1 / w0, "d2 A/w0": d2 * A / w0}
    diag.update(ratios)
    absurd = [f"{k} = {v:.3g}" for k, v in ratios.items() if not v <= ABSURD]
    if absurd or A > 100.0 * span_x:
        what = ", ".join(absurd) if absurd else f"A = {A:.3g} vs data range {span_x:.3g}"
        fails.append(f"a parameter ran to absurd values ({what})")
    rel = w0 / an.omega - 1.0
    diag["w0/crossing - 1"] = rel
    if abs(rel) > W0_TOLERANCE:
        fails.append(f"the fitted w0 = {w0:.5g} rad/s differs by {100 * rel:+.1f} % from the "
                     f"data's zero-crossing frequency {an.omega:.5g} rad/s")
    period = 2.0 * math.pi / w0
    noise = an.noise
    level = max(6.0 * noise, 0.02 * A)
    end_data = motion_end(t, x, period, level)
    end_model = motion_end(t, curve, period, level)
    diag.update(noise=noise, end_data=end_data, end_model=end_model)
    tol = max(END_PERIODS * period, 0.1 * float(t[-1] - t[0]))
    if end_model < end_data - tol:
        msg = (f"the model stops moving at t = {end_model:.5g} s, well before the data "
               f"(t = {end_data:.5g} s)")
        fails.append(msg)
        bad.append(msg)
    elif end_model > end_data + tol:
        msg = (f"the model still moves at t = {end_model:.5g} s, well after the data stop "
               f"(t = {end_data:.5g} s)")
        fails.append(msg)
        bad.append(msg)
    r = x - curve
    rms = float(np.sqrt(np.mean(r * r)))
    diag["rms/noise"] = rms / noise if noise > 0 else math.inf
    diag["rms/A"] = rms / A
    if rms > RMS_NOISE * noise and rms > RMS_AMPLITUDE * A:
        bad.append(f"the residuals (rms {rms:.3g}) are {diag['rms/noise']:.0f} times the noise "
                   f"level of the data ({noise:.3g}) and {100 * rms / A:.1f} % of the amplitude")
    drift = phase_drift(t, x, curve, w0, params.get("offset", 0.0), level)
    diag["phase_drift"] = drift
    if drift > PHASE_DRIFT:
        bad.append(f"systematic phase drift: the data's phase wanders {drift:.2f} rad from the "
                   "model's (the frequency changes with the amplitude?)")
    elif drift > PHASE_NOTE:
        diag["note"] = (f"the data's phase drifts {drift:.2f} rad from the model's and the "
                        f"residuals are {diag['rms/noise']:.0f} times the noise: they are "
                        "correlated, so the delta-method stderr understate the uncertainty; "
                        "use conf_interval()")
    return fails, bad, diag
