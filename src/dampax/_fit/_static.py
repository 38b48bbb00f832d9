"""``fit(free=(..., "mu_s"))``: the static friction coefficient, searched by the halt it gives
(the motion's turning points and thresholds, and the checks every reference fit makes of
where it halts, are ``_halts``, below the pipeline).

With static friction mu_s >= mu the block sticks at the first turning point x_j where
|k x_j + k3 x_j^3| <= mu_s m g (``Oscillator.mu_s``). The motion before that turning point does
not depend on mu_s, so x(t) depends on mu_s only through which turning point is the halt: it is
a step function of mu_s, constant on [th_j, th_(j-1)) with th_j = |k x_j + k3 x_j^3| / (m g)
(its derivative is zero almost everywhere, and a gradient-based optimizer cannot move it).

The search (:func:`fit_mu_s`):

1. the fit with mu_s = mu (the sliding-friction fit, with the caller's starts);
2. a screen at that fit's parameters: the curve that halts at turning point j is the sliding
   curve up to t_j and x_j after it, so the residual sum of squares of every candidate halt
   (every turning point the sliding motion passes inside the window) costs one integration;
3. fits at fixed mu_s (the middle of [th_j, th_(j-1))) of the ``REFINE`` candidates that screen
   lowest, each started from the sliding fit's optimum with the reference model directly;
4. the screen again at the best fit's parameters: a candidate not yet fitted that screens
   below the best cost is fitted too (at most ``MAX_FITS`` fits in all).

The result is the fit of the lowest cost; mu_s is reported as the middle of the interval of
values that give its halt, the interval itself as its ``conf_interval``
(``profiled["mu_s"]``), and as its standard error the interval's width / sqrt(12).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._halts import thresholds, turning_points
from ._params import PARAMS
from ._pipeline import DIRECT, DIRECT_INNER, INNER, run

#: fits at fixed mu_s of the best-screening candidates, and the most fits at fixed mu_s in all
REFINE = 2
MAX_FITS = 5


def _interval(th: np.ndarray, j: int) -> tuple[float, float]:
    """The values of mu_s that halt the motion at turning point j (0-based):
    [th_j, min(th_0 .. th_(j-1))); [th_0, inf) for the first."""
    return float(th[j]), (math.inf if j == 0 else float(np.min(th[:j])))


def _candidate(th: np.ndarray, j: int) -> float:
    """mu_s in the middle of the values that halt at turning point j (1.25 th_0 for the
    first)."""
    lo, hi = _interval(th, j)
    return 1.25 * lo if not math.isfinite(hi) else 0.5 * (lo + hi)


def screen(res, m: float, g: float, k3: float) -> list[tuple[float, int, float]]:
    """The residual sum of squares of every candidate halt at the fit's parameters.

    The curve that halts at turning point j is the fit's curve (mu_s = mu) up to t_j and
    offset + x_j after it (the motion before the halt does not depend on mu_s).

    Returns:
        [(cost, j, mu_s)] for every turning point j inside the window that the motion passes
        (th_j > mu), lowest cost first; mu_s is the middle of the values that halt there.
    """
    tau_j, x_j, th, halts = turning_points(res, m, g, k3)
    mu = float(res.params["mu"])
    tau = np.asarray(res.t, dtype=float) - float(res.t[0])
    data = np.asarray(res.x, dtype=float)
    curve = np.asarray(res.model_x, dtype=float)
    offset = float(res.params["offset"])
    last = len(th) - (1 if halts else 0)  # the sliding halt itself is the fit's own motion
    out = []
    for j in range(last):
        if th[j] <= mu or (j > 0 and th[j] >= np.min(th[:j])):
            continue  # not passed, or no value of mu_s halts here first
        model = np.where(tau < tau_j[j], curve, offset + x_j[j])
        out.append((float(np.sum((data - model) ** 2)), j, max(_candidate(th, j), mu)))
    return sorted(out)


def _cost(res) -> float:
    return float(res.chisqr) if res is not None and np.isfinite(res.chisqr) else math.inf


def _at(problem, value, start, inner: bool = True):
    """A fit at fixed mu_s from another fit's optimum with the reference model directly (one
    start: the caller's starts were spent on the sliding fit); None where an inner one is
    refused."""
    try:
        held = problem.with_consts(mu_s=value).starting_at(
            {n: float(start.params[n]) for n in PARAMS}, starts=1)
        return run(held, DIRECT_INNER if inner else DIRECT)
    except ValueError:
        if not inner:
            raise
        return None


def _search(problem, base):
    """Steps 2-4 of the module's search: (the best fit, its mu_s or None, fits made)."""
    m, g, k3 = problem.consts.motion
    best, best_value, done = base, None, {}
    for _, j, value in screen(base, m, g, k3)[:REFINE]:
        res = done[j] = _at(problem, value, base)
        if _cost(res) < _cost(best):
            best, best_value = res, value
    fits = len(done)
    if best_value is not None:
        # the screen at the best fit's parameters: a halt not yet fitted that screens below it
        tried = {best_value}
        for c, _, value in screen(best, m, g, k3):
            if fits >= MAX_FITS or c >= _cost(best):
                break
            if any(abs(value - v) <= 1e-12 * max(1.0, abs(v)) for v in tried):
                continue
            tried.add(value)
            res = _at(problem, value, base)
            fits += 1
            if _cost(res) < _cost(best):
                best, best_value = res, value
    return best, best_value, fits


def fit_mu_s(problem):
    """The fit of ``problem`` with the static friction coefficient mu_s searched (see the
    module's text).

    Arguments:
        problem: the prepared problem (``_problem.prepare``; model "reference", ``free``
            without "mu_s").

    Returns:
        The :class:`FitResult` of the lowest cost, with "mu_s" in ``params``, ``stderr``,
        ``free`` and ``conf_interval`` (the interval of values that give its halt), and
        ``profiled["mu_s"]``: value, interval, the fitted value used, the halt's turning point
        (1-based), the fits made, and the rms and the model's position at the window's end
        of the sliding-friction fit (mu_s = mu).
    """
    m, g, k3 = problem.consts.motion
    # the search's fits are inner fits (no refusal, no profile of the intervals): the chosen
    # one is fitted again at the end with every check of a plain fit
    base = run(problem, INNER)
    best, best_value, fits = _search(problem, base)
    # the chosen fit again as a plain fit (its checks, and a refusal with the true reason)
    best = _at(problem, best_value, best, inner=False)
    return _reported(best, base, best_value, fits, (m, g, k3))


def _reported(best, base, best_value, fits, constants):
    """The chosen fit with mu_s reported: the middle of the values that give its halt."""
    m, g, k3 = constants
    mu_best = float(best.params["mu"])
    used = mu_best if best_value is None else best_value
    # the halt that the chosen fit makes (its parameters moved from the candidate's), and the
    # values of mu_s that give the same one: [th_h, th_(h-1)), h the halt's turning point
    th_f, halts_f = thresholds(best, m, g, k3, mu_s=best_value)
    if halts_f and th_f.size:
        h = th_f.size - 1
        lo, hi = _interval(th_f, h)
        lo = max(lo, mu_best)
        halt = h + 1
    else:  # no halt inside the window: any value below the window's last threshold
        lo, hi = mu_best, float(np.min(th_f)) if th_f.size else math.inf
        halt = None
    value = 0.5 * (lo + hi) if math.isfinite(hi) else used
    sd = (hi - lo) / math.sqrt(12.0) if math.isfinite(hi) else math.inf
    w0 = float(best.params["w0"])
    profile = {"mu_s": {"value": value, "stderr": sd, "interval": (lo, hi),
                        "fitted_at": used, "halt_turn": halt, "evaluations": fits + 1,
                        "rms_sliding": base.rms,
                        "end_sliding": float(np.asarray(base.model_x)[-1])}}
    return dataclasses.replace(
        best, params={**best.params, "mu_s": value}, stderr={**best.stderr, "mu_s": sd},
        init={**base.init}, fixed={k: v for k, v in best.fixed.items() if k != "mu_s"},
        free=tuple(best.free) + ("mu_s",), profiled={**best.profiled, **profile},
        derived={**best.derived, "x_static": value * g / w0 ** 2,
                 "rms_mu_s_eq_mu": base.rms})
