"""``fit(free=(..., "mu_s"))``: the static friction coefficient, searched by the halt it gives.

With static friction mu_s >= mu the block sticks at the first turning point x_j where
|k x_j + k3 x_j^3| <= mu_s m g (``Oscillator.mu_s``). The motion before that turning point does
not depend on mu_s, so x(t) depends on mu_s only through which turning point is the halt: it is
a step function of mu_s, constant on [th_j, th_(j-1)) with th_j = |k x_j + k3 x_j^3| / (m g)
(its derivative is zero almost everywhere, and a gradient-based optimizer cannot move it).

The search (:func:`fit_mu_s`): the fit with mu_s = mu (the sliding-friction fit), then fits at
fixed mu_s, one per candidate halt j (mu_s at the middle of [th_j, th_(j-1)), from the previous
fit's turning points), from the last turning point of the window backwards while the residual
sum of squares falls; the candidates beside the best are tried again with the turning points
of the best fit. The result is the fit of the lowest cost; mu_s is reported as the middle of
the interval of values that give its halt, the interval itself as its ``conf_interval``
(``profiled["mu_s"]``), and as its standard error the interval's width / sqrt(12).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._oscillator import Oscillator
from ._params import PARAMS, oscillator_values

#: the most fits at fixed mu_s in the backward search, and how many rises of the cost end it
MAX_CANDIDATES = 10
PATIENCE = 3


def _constants(options) -> tuple[float, float, float]:
    """(m, g, k3) of the fit's oscillator (unit mass and g = 9.81 without one)."""
    vals = oscillator_values(options["oscillator"])
    k3 = options.get("k3")
    return vals["m"], vals["g"], 0.0 if k3 is None else float(k3)


def thresholds(res, m: float, g: float, k3: float, mu_s=None) -> tuple[np.ndarray, bool]:
    """The static-friction thresholds th_j = |k x_j + k3 x_j^3| / (m g) of the fit's turning
    points with mu_s = mu (in time order, inside the window), and whether that motion halts
    inside the window (its last turning point is then the halt).

    Arguments:
        res: a trace fit of the reference model.
        m, g, k3: the fit's constants.
        mu_s: the static friction of the motion (None: mu_s = mu); with a value the list
            ends at the halt it gives.
    """
    from .._solve import solve

    p = res.params
    k = m * p["w0"] ** 2
    osc = Oscillator(m=m, k=k, mu=p["mu"], b=p["b"], D=p["D"], g=g, k3=k3,
                     mu_s=None if mu_s is None else max(float(mu_s), float(p["mu"])))
    span = float(res.t[-1] - res.t[0])
    sol = solve(osc, p["x0"], p["v0"], method="reference", t_end=span)
    ts = np.asarray(sol.swing_times, dtype=float)
    xs = np.asarray(sol.turning_x, dtype=float)
    ok = np.isfinite(ts) & (ts > 0.0) & (ts <= span)
    xs = xs[ok]
    return np.abs(k * xs + k3 * xs ** 3) / (m * g), bool(np.asarray(sol.halted))


def _candidate(th: np.ndarray, j: int) -> float:
    """mu_s in the middle of the values that halt at turning point j (0-based):
    [th_j, th_(j-1)); above th_0 for the first."""
    return float(1.25 * th[0]) if j == 0 else float(0.5 * (th[j] + th[j - 1]))


def fit_mu_s(fit, trace_or_t, x, *, free, options):
    """``fit`` with the static friction coefficient mu_s searched (see the module's text).

    Arguments:
        fit: :func:`dampax.fit` (passed in: this module does not import ``_api``).
        trace_or_t, x: the data, as for ``fit``.
        free: the other free constants.
        options: the other keyword arguments of ``fit`` (model "reference").

    Returns:
        The :class:`FitResult` of the lowest cost, with "mu_s" in ``params``, ``stderr``,
        ``free`` and ``conf_interval`` (the interval of values that give its halt), and
        ``profiled["mu_s"]``: value, interval, the fitted value used, the halt's turning point
        (1-based), the fits evaluated and the rms of the sliding-friction fit.
    """
    m, g, k3 = _constants(options)
    base = fit(trace_or_t, x, free=free, **options)
    inner = {**options, "starts": 1,
             "p0": {name: float(base.params[name]) for name in PARAMS}}
    cache: dict[float, object] = {}

    def run(value):
        if value not in cache:
            try:
                cache[value] = fit(trace_or_t, x, free=free, mu_s=value, _inner=True, **inner)
            except ValueError:
                cache[value] = None
        return cache[value]

    def cost(res):
        return float(res.chisqr) if res is not None and np.isfinite(res.chisqr) else math.inf

    best, best_value, best_j = base, None, None
    th, halts = thresholds(base, m, g, k3)
    mu = float(base.params["mu"])
    # candidate halts: turning points the sliding-friction motion passes (th_j > mu), last first
    last = len(th) - (2 if halts else 1)
    rises, tried = 0, 0
    for j in range(last, -1, -1):
        if th[j] <= mu or tried >= MAX_CANDIDATES:
            continue
        value = max(_candidate(th, j), mu)
        res = run(value)
        tried += 1
        if cost(res) < cost(best):
            best, best_value, best_j, rises = res, value, j, 0
        else:
            rises += 1
            if rises >= PATIENCE:
                break
    if best_j is not None:  # the neighbours again, with the best fit's turning points
        th2, _ = thresholds(best, m, g, k3)
        for j in (best_j - 1, best_j, best_j + 1):
            if 0 <= j < len(th2) and th2[j] > float(best.params["mu"]):
                value = max(_candidate(th2, j), float(best.params["mu"]))
                res = run(value)
                if cost(res) < cost(best):
                    best, best_value, best_j = res, value, j
    mu_best = float(best.params["mu"])
    used = mu_best if best_value is None else best_value
    # the halt that the chosen fit makes (its parameters moved from the candidate's), and the
    # values of mu_s that give the same one: [th_h, th_(h-1)), h the halt's turning point
    th_f, halts_f = thresholds(best, m, g, k3, mu_s=best_value)
    if halts_f and th_f.size:
        h = th_f.size - 1
        lo = max(float(th_f[h]), mu_best)
        hi = float(th_f[h - 1]) if h >= 1 else math.inf
        best_j = h
    else:  # no halt inside the window: any value below the window's last threshold
        lo, hi = mu_best, float(th_f[-1]) if th_f.size else math.inf
        best_j = None
    value = 0.5 * (lo + hi) if math.isfinite(hi) else used
    sd = (hi - lo) / math.sqrt(12.0) if math.isfinite(hi) else math.inf
    w0 = float(best.params["w0"])
    profile = {"mu_s": {"value": value, "stderr": sd, "interval": (lo, hi),
                        "fitted_at": used,
                        "halt_turn": None if best_j is None else best_j + 1,
                        "evaluations": len(cache) + 1, "rms_sliding": base.rms}}
    return dataclasses.replace(
        best, params={**best.params, "mu_s": value}, stderr={**best.stderr, "mu_s": sd},
        free=tuple(best.free) + ("mu_s",), profiled={**best.profiled, **profile},
        derived={**best.derived, "x_static": value * g / w0 ** 2,
                 "rms_mu_s_eq_mu": base.rms})
