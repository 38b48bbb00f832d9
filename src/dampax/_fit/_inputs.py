"""Checks of a fit's input (numpy), before any analysis: a time axis that is one trace's,
positions within float64's range, no stray time stamp, a trace that is not constant; and the
notes about the data against the settings (a frequency or a level the settings contradict).

Each check raises a ValueError that names the argument and the reason; the notes are strings
that ``_problem.prepare`` emits as warnings, once.
"""

from __future__ import annotations

import math

import numpy as np

from ._analysis import Analysis
from ._params import DAMPING, PARAMS

#: the largest |time| [s] a fit takes (about 3e7 years; beyond it the time axis is not one of
#: a free decay, and times near 1e300 overflowed the fit's sums)
MAX_TIME = 1e15
#: the smallest median time step [s] a fit takes (a sampling rate of 1 THz: the squares of the
#: frequencies of finer steps overflowed)
MIN_STEP = 1e-12
#: the median time step must exceed this many float64 spacings of the largest |time|: else
#: the stamps are quantised by the float format itself (subtract the first stamp first)
MIN_STEPS_PER_SPACING = 1e3
#: one gap between samples longer than this share of the span (and this many median steps)
#: is a stray time stamp, not a pause of the logger
MAX_GAP_SHARE, MAX_GAP_STEPS = 0.5, 100.0


#: more steps back than these (a count, a share of the samples) are unsorted samples, not a
#: clock that resets: a reset or a few runs put end to end go back a few times
UNSORTED_STEPS, UNSORTED_SHARE = 10, 0.01


def check_time_axis(t: np.ndarray) -> None:
    """ValueError naming ``t`` for a time axis that is not one trace's: times that go back
    (a clock that resets, runs put end to end; unsorted samples, told apart by how often),
    times beyond :data:`MAX_TIME`, steps below :data:`MIN_STEP` or the float format's
    resolution, or mostly repeated stamps (every sample twice). One gap over most of the
    window is :func:`check_gaps`'s (on the window: ``Window.end`` can leave it out).

    Arguments:
        t: the finite sample times, in the order given (not sorted).
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return
    top = float(np.max(np.abs(t)))
    if top > MAX_TIME:  # first: times near 1e300 are also equal in float64
        raise ValueError(f"t: times up to {top:.3g} s, beyond the {MAX_TIME:g} s a trace's "
                         "clock can hold; give the times in seconds from the start")
    if float(np.ptp(t)) == 0.0:  # constant time: check_sampling says so
        return
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size > max(UNSORTED_STEPS, UNSORTED_SHARE * t.size):
        raise ValueError(f"t: the times are not in order ({back.size} of {t.size - 1} steps go "
                         "back, as in shuffled or unsorted samples): sort the samples by time "
                         "first (order = np.argsort(t); t, x = t[order], x[order])")
    if back.size:
        i = int(back[0])
        raise ValueError(f"t: the time column goes back {back.size} time(s), first after sample "
                         f"{i} ({t[i]:g} s -> {t[i + 1]:g} s): a clock that resets or runs put "
                         "end to end; fit each run alone (dp.fit([run1, run2, ...]) fits them "
                         "jointly) or rebuild time from the sample rate (load_trace(rate=...), "
                         "dampax fit --rate)")
    steps = np.diff(t)
    step = float(np.median(steps))
    if not step > 0.0:
        raise ValueError(f"t: at least half of the {t.size} time stamps repeat the one before "
                         "(samples written twice, or buffered stamps); rebuild time from the "
                         "sample rate (load_trace(rate=...), dampax fit --rate) or drop the "
                         "repeated rows")
    if step < MIN_STEP:
        raise ValueError(f"t: the median time step ({step:.3g} s) is below {MIN_STEP:g} s (a "
                         "sampling rate above 1 THz); give the times in seconds")
    if step < MIN_STEPS_PER_SPACING * float(np.spacing(top)):
        raise ValueError(f"t: the median time step ({step:.3g} s) is within "
                         f"{MIN_STEPS_PER_SPACING:g} float64 spacings of the times ({top:.3g} "
                         "s): the stamps are rounded by the number format; subtract the first "
                         "time stamp before storing them")


#: the range of the largest |position| a fit takes: beyond it the sums of squares of the
#: residuals leave float64's range (positions of 1e200 or 1e-150 stopped the linear algebra
#: with "SVD did not converge")
POSITION_RANGE = (1e-100, 1e100)


def check_positions(x: np.ndarray) -> None:
    """ValueError naming ``x`` when the largest |position| lies outside
    :data:`POSITION_RANGE` (all zero is left to :func:`check_sampling`: a constant trace).

    Arguments:
        x: the finite positions.
    """
    top = float(np.max(np.abs(x))) if np.size(x) else 0.0
    low, high = POSITION_RANGE
    if top != 0.0 and not low <= top <= high:
        raise ValueError(f"x: positions up to {top:.3g}, outside the [{low:g}, {high:g}] a fit "
                         "takes (its sums of squares leave float64's range); rescale them "
                         "(load_trace(scale=...), dampax fit --scale) and name the unit "
                         "(Window(units=...))")


def check_gaps(t: np.ndarray) -> None:
    """ValueError naming ``t`` when one gap between the (sorted) samples of a fit window covers
    more than :data:`MAX_GAP_SHARE` of its span and :data:`MAX_GAP_STEPS` median steps: a stray
    time stamp, not a pause of the logger.

    Arguments:
        t: the window's sorted sample times.
    """
    t = np.asarray(t, dtype=float)
    if t.size < 3:
        return
    steps = np.diff(t)
    step = float(np.median(steps))
    span = float(t[-1] - t[0])
    i = int(np.argmax(steps))
    gap = float(steps[i])
    if span > 0 and gap > MAX_GAP_SHARE * span and gap > MAX_GAP_STEPS * step:
        raise ValueError(f"t: one gap of {gap:.3g} s between samples {i} and {i + 1} "
                         f"({t[i]:g} s -> {t[i + 1]:g} s) covers {100 * gap / span:.0f} % of "
                         f"the trace's span (median step {step:.3g} s): a stray time stamp? "
                         "Drop it, or end the window before it (Window(end=...), --end)")


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


def omega_warning(an: Analysis, osc: dict, fit_omega0: bool) -> list:
    """A note when the data's turning points disagree with sqrt(k/m) (w0 not fitted)."""
    if not fit_omega0 and an.n_turns >= 5 and \
            abs(an.omega / osc["w0"] - 1.0) > 0.03 + 2.0 * an.omega_spread:
        # the turning points (not the zero crossings, which friction moves) keep the clock
        return [f"the data's turning points are {math.pi / an.omega:.5g} s apart, "
                f"half a period of {an.omega:.5g} rad/s, but sqrt(k/m) = "
                f"{osc['w0']:.5g} rad/s: pass fit_omega0=True or the right m and k"]
    return []


#: a held offset this share of the swings' amplitude (the largest turning point) away from
#: the centre of the data's half swings is noted (a description: the fit runs as asked)
HELD_OFFSET_SHARE = 0.05


def held_offset_warning(an: Analysis, held: float, fitted: bool) -> list:
    """A note when the offset is held (``offset=False``) away from the data's centre.

    The centre is the mean of the half swings' centres (``Analysis.offset``; friction's +-mu g
    / w0^2 cancels between them, to a quarter of it after 5 turning points). Held 0.06 away on
    swings of 0.1 the exact model stuck at the level after one swing (mu 1.04 for 0.002) and
    the fit was refused as "mu and D not separately identifiable", naming neither.
    """
    size = float(np.max(np.abs(an.ext_x))) if an.n_turns else 0.0
    away = an.offset - held
    if fitted or an.n_turns < 5 or not abs(away) > HELD_OFFSET_SHARE * size:
        return []
    return [f"the data swing about {an.offset:.4g}, {100 * abs(away) / size:.0f} % of their "
            f"amplitude from the offset held at {held:.4g} (offset=False): pass offset=True, "
            "or hold the right value (p0={'offset': ...})"]


def checked_consts(k3, mu_s, free, osc, *, against_mu: bool = True):
    """(k3, mu_s) as floats (or None), checked: finite, mu_s >= 0 and (``against_mu``) >= a
    held mu."""
    if mu_s is not None:
        mu_s = float(mu_s)
        if not (math.isfinite(mu_s) and mu_s >= 0.0):
            raise ValueError(f"mu_s must be a finite number >= 0, got {mu_s!r}")
        if against_mu and "mu" not in free and mu_s < osc["mu"]:
            raise ValueError(f"mu_s must be >= mu (static friction is at least the sliding "
                             f"friction), got mu_s={mu_s!r} and mu={osc['mu']!r}")
    if k3 is not None:
        k3 = float(k3)
        if not math.isfinite(k3):
            raise ValueError(f"k3 must be a finite number, got {k3!r}")
    return k3, mu_s


def held_constants(oscillator, names, k3, mu_s) -> tuple:
    """(k3, mu_s) that a fit holds: the keywords ``k3`` and ``mu_s``, else the oscillator's
    own (its ``k3`` where not 0, its ``mu_s`` where set), unless the constant is fitted (in
    ``names``: ``free``, and a joint fit's ``shared``). Before, a fit left an oscillator's
    k3 and mu_s out without a word: ``dp.fit(..., oscillator=dp.Oscillator(m, k, k3=...))``
    fitted a linear spring.

    Raises:
        ValueError: a keyword and the oscillator hold different values of one constant.
    """
    if oscillator is None:
        return k3, mu_s
    get = oscillator.get if isinstance(oscillator, dict) else \
        (lambda name, default: getattr(oscillator, name, default))
    held = {"k3": k3, "mu_s": mu_s}
    for name, unset in (("k3", 0.0), ("mu_s", None)):
        own = get(name, unset)
        if own is None or name in names or np.shape(own) != ():  # (a batch: refused later)
            continue
        own = float(own)
        if own == unset:
            continue
        if held[name] is not None and float(held[name]) != own:
            raise ValueError(f"{name}: the oscillator holds {name}={own!r} and the fit was "
                             f"given {name}={held[name]!r}: give it once")
        held[name] = own
    return held["k3"], held["mu_s"]


def check_p0_fitted(p0, free, fit_omega0: bool) -> None:
    """ValueError for an entry of ``p0`` that the fit holds: a damping constant not in
    ``free``, or w0 without ``fit_omega0`` (they were held at p0's values, overriding the
    oscillator's, unsaid). The offset with ``offset=False`` is held at p0's value, as
    documented. Unknown names are a ValueError too."""
    unknown = set(p0) - set(PARAMS)
    if unknown:
        raise ValueError(f"p0: unknown parameters {sorted(unknown)}; use {PARAMS}")
    held = [k for k in p0 if (k in DAMPING and k not in free) or (k == "w0" and not fit_omega0)]
    if held:
        raise ValueError(f"p0: {', '.join(held)} not fitted here (a damping constant not in "
                         "free, w0 without fit_omega0): its value is the oscillator's; set it "
                         "there, or fit it")


def check_fitted_on(res, t_all: np.ndarray, x_all: np.ndarray, name: str) -> None:
    """ValueError naming ``name`` where the fit ``res`` is not of the data (t_all, x_all):
    the samples of its window must be a run of theirs (``start_fit`` of a posterior,
    ``fitted`` of a ranking were used whatever data came with them)."""
    n = len(res.t)
    i = int(np.searchsorted(t_all, res.t[0])) if n else 0
    if not (n and i + n <= len(t_all) and np.array_equal(t_all[i:i + n], res.t)
            and np.array_equal(x_all[i:i + n], res.x)):
        raise ValueError(f"{name}: a fit of other data (its {n} samples are not a run of the "
                         f"{len(t_all)} given); fit these data, or pass the data it fitted")


def as_times(t) -> np.ndarray:
    """``t`` as float64 seconds: a timedelta64 array (pandas' elapsed times) in seconds (it
    was read as a count of its own unit, ns: w0 1e9 times small); datetimes and what is not
    a number are a ValueError naming ``t``."""
    arr = np.asarray(t)
    if np.issubdtype(arr.dtype, np.timedelta64):
        return arr / np.timedelta64(1, "s")
    if np.issubdtype(arr.dtype, np.datetime64):
        raise ValueError("t: datetimes; pass the elapsed seconds, (t - t[0]) / "
                         "np.timedelta64(1, 's')")
    try:
        return np.asarray(arr, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"t: not numbers (an array of {arr.dtype})") from None
