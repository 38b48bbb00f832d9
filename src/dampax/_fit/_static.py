"""Where the block halts, in fits: ``fit(free=(..., "mu_s"))`` (the static friction coefficient,
searched by the halt it gives) and, for every reference fit with mu free, the search of the
motions that halt at a neighbouring turning point (:func:`search_other_halts`,
:func:`other_halt_check`).

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

from .._oscillator import Oscillator
from .._solve import solve
from ._params import PARAMS, oscillator_values
from ._profile import LR_CHI2, LR_Z

#: fits at fixed mu_s of the best-screening candidates, and the most fits at fixed mu_s in all
REFINE = 2
MAX_FITS = 5


def _constants(options) -> tuple[float, float, float]:
    """(m, g, k3) of the fit's oscillator (unit mass and g = 9.81 without one)."""
    vals = oscillator_values(options["oscillator"])
    k3 = options.get("k3")
    return vals["m"], vals["g"], 0.0 if k3 is None else float(k3)


def _motion(res, m: float, g: float, k3: float, mu_s=None):
    """The reference solution of a fit's motion from its start over twice its window (one
    compiled program for every call of a search), and the window's span."""

    p = res.params
    osc = Oscillator(m=m, k=m * p["w0"] ** 2, mu=p["mu"], b=p["b"], D=p["D"], g=g, k3=k3,
                     mu_s=None if mu_s is None else max(float(mu_s), float(p["mu"])))
    span = float(res.t[-1] - res.t[0])
    return solve(osc, p["x0"], p["v0"], method="reference", t_end=2.0 * span), span


def turning_points(res, m: float, g: float, k3: float, mu_s=None):
    """The turning points of a fit's motion inside its window.

    Arguments:
        res: a trace fit of the reference model.
        m, g, k3: the fit's constants.
        mu_s: the static friction of the motion (None: mu_s = mu); with a value the list
            ends at the halt it gives.

    Returns:
        (tau_j, x_j, th_j, halts): the times after the fit start, the positions (about the
        offset), the static-friction thresholds th_j = |k x_j + k3 x_j^3| / (m g) in time
        order, and whether the motion halts inside the window (its last turning point is
        then the halt).
    """
    sol, span = _motion(res, m, g, k3, mu_s)
    k = m * float(res.params["w0"]) ** 2
    ts = np.asarray(sol.swing_times, dtype=float)
    xs = np.asarray(sol.turning_x, dtype=float)
    ok = np.isfinite(ts) & (ts > 0.0) & (ts <= span)
    ts, xs = ts[ok], xs[ok]
    th = np.abs(k * xs + k3 * xs ** 3) / (m * g)
    halt = float(sol.halt_time)
    return ts, xs, th, bool(np.asarray(sol.halted)) and math.isfinite(halt) and halt <= span


def thresholds(res, m: float, g: float, k3: float, mu_s=None) -> tuple[np.ndarray, bool]:
    """(th_j, halts) of :func:`turning_points`."""
    _, _, th, halts = turning_points(res, m, g, k3, mu_s)
    return th, halts


def other_halts(params, t, m: float, g: float, k3: float) -> tuple[float, float]:
    """The thresholds of mu at which a fit's motion would halt one turning point earlier or
    later (sliding friction, mu_s = mu; the check of ``fit`` for another optimum).

    Where the block sticks is a step function of mu: the motion halts at the first turning
    point j with th_j = |k x_j + k3 x_j^3| / (m g) <= mu. A fit that halts at turning point h
    (th_h <= mu < th_(h-1)) has neighbours that halt at h - 1 (mu >= th_(h-1)) and h + 1
    (mu < th_h), a jump in the cost that no gradient crosses; over two or three swings their
    optimum can fit as well.

    Arguments:
        params: the fit's parameters (dict or TraceParams: mu, b, D, w0, x0, v0).
        t: the window's times.
        m, g, k3: the fit's constants.

    Returns:
        (th_(h-1), th_h): NaN for a neighbour that does not exist (h = 0: no earlier turning
        point). A motion that does not halt inside the window has one neighbour: the motion
        that halts at the window's last turning point (th_(h-1) = its threshold, th_h NaN);
        none without a turning point inside the window.
    """
    from types import SimpleNamespace

    p = params if isinstance(params, dict) else params._asdict()
    ns = SimpleNamespace(params={k: float(v) for k, v in p.items()}, t=np.asarray(t))
    th, halts = thresholds(ns, m, g, k3)
    if th.size == 0:
        return math.nan, math.nan
    if not halts:  # it halts after the window: the neighbour halts at its last turning point
        return float(th[-1]), math.nan
    h = th.size - 1
    return (float(th[h - 1]) if h >= 1 else math.nan), float(th[h])


def search_other_halts(out, run, t, vary, fs, name, stages, constants):
    """The search of ``fit`` for a better optimum where the block halts at a neighbouring
    turning point (``_static.other_halts``), for the exact model with mu free.

    With the thresholds th_(h-1) (halt one turning point earlier) and th_h (one later): mu
    held just past each threshold (by a quarter of its standard error), at 1.05 and 1.25
    th_(h-1) and at 0.95 and 0.8 th_h, the rest refitted; and free fits started at 1.05
    th_(h-1) and 0.95 th_h (where to look, not thresholds: the verdict is the likelihood
    ratio of :func:`other_halt_check`). A lower cost is taken (a held fit's by freeing mu
    from it: the optimizer only goes downhill, so it stays in that basin) and the search
    repeated once around it.

    Returns:
        (the fit, {held mu: its cost}) for :func:`other_halt_check`: the held fits of both
        rounds and the optimum a lower cost replaced.
    """
    held = vary._replace(mu=False)
    others = {}  # every held fit of the search, and an optimum it left (a basin it saw)
    for _ in range(2):
        prev, last = other_halts(out.params, t, *constants)
        se = float(out.stderr.mu) if math.isfinite(float(out.stderr.mu)) else 0.0
        points = [prev * (1.0 + 1e-3) + 0.25 * se, 1.05 * prev, 1.25 * prev,
                  last * (1.0 - 1e-3) - 0.25 * se, 0.95 * last, 0.8 * last]
        fits = []
        for mu_alt in points:
            if math.isfinite(mu_alt) and mu_alt > 0.0:
                fit_alt = run(out.params._replace(mu=mu_alt), name, fs, mask=held)
                others[mu_alt] = float(fit_alt.chisqr)
                fits.append(fit_alt)
        lower = [f for f in fits if float(f.chisqr) < float(out.chisqr)]
        starts = [min(lower, key=lambda f: float(f.chisqr)).params] if lower else []
        starts += [out.params._replace(mu=v) for v in (1.05 * prev, 0.95 * last)
                   if math.isfinite(v) and v > 0.0]
        better = None
        for p in starts:
            cand = run(p, name, fs)
            if float(cand.chisqr) < float(out.chisqr if better is None else better.chisqr):
                better = cand
        if better is None:
            break
        stages.append(f"a motion that halts at another turning point fits better (cost "
                      f"{0.5 * float(better.chisqr):.4g} < {0.5 * float(out.chisqr):.4g})")
        others[float(out.params.mu)] = float(out.chisqr)  # the basin left: nearly as good?
        out = better
    return out, others


def other_halt_check(res, others: dict):
    """Fail a fit when a motion that halts at a neighbouring turning point fits nearly as well
    with mu outside its interval (``_static.other_halts``): with mu held at each value of
    ``others`` and the rest refitted (its cost the value), the likelihood-ratio chi2 against
    the fit,
    in the intervals' own noise variance (s2 (sd/stderr)^2, as ``_profile.bound_tests``),
    below :data:`~dampax._fit._profile.LR_CHI2` (1 %) while mu differs by more than
    :data:`~dampax._fit._profile.LR_Z` interval sd: the data hold two answers, and the
    interval of one of them is no interval."""

    sd, se = res.hac_stderr.get("mu", math.nan), res.stderr.get("mu", math.nan)
    if not (math.isfinite(sd) and sd > 0 and math.isfinite(se) and se > 0):
        return res
    s2 = float(res.chisqr) / max(res.ndata - res.nvarys, 1)
    mu = float(res.params["mu"])
    for mu_alt, cost in others.items():
        if not abs(mu_alt - mu) > LR_Z * sd:
            continue
        rise = (cost - float(res.chisqr)) / (s2 * (sd / se) ** 2)
        if rise < LR_CHI2:
            reason = (f"two motions fit nearly as well: this one and one that halts at another "
                      f"turning point with mu = {mu_alt:.4g} ({abs(mu_alt - mu) / sd:.0f} "
                      f"interval sd away; likelihood-ratio chi2 {rise:.2g} < {LR_CHI2:.2f}): "
                      "where the block sticks does not settle mu; fit a longer record or fix "
                      "the offset")
            return dataclasses.replace(res, success=False, reason=reason,
                                       diagnostics={**res.diagnostics,
                                                    "other_halt_mu": mu_alt,
                                                    "other_halt_chi2": rise})
    return res


def above_mu_s(res, mu_s: float):
    """A fit at a given mu_s whose fitted mu exceeds it, failed with the reason (issue 37):
    the model's rule is mu_s >= mu, and a traced mu_s below mu acts as mu, so such a fit
    described a motion without the given static friction and reported it as a success.

    Arguments:
        res: the fit's FitResult.
        mu_s: the given static friction coefficient.

    Returns:
        ``res`` unchanged when mu <= mu_s (to 1e-9 relative) or mu was not fitted, else a
        copy with ``success = False`` and the reason.
    """
    mu = res.params.get("mu")
    if mu is None or not float(mu) > float(mu_s) * (1.0 + 1e-9):
        return res
    reason = (f"the fitted mu = {float(mu):.4g} exceeds the given mu_s = {float(mu_s):.4g}, "
              "against the model's rule mu_s >= mu (the motion was that of mu_s = mu): the "
              "data's sliding friction is larger than the static friction given; fit mu_s as "
              "well (free=(..., 'mu_s')) or give mu_s >= mu")
    return dataclasses.replace(res, success=False,
                               reason="; ".join(r for r in (res.reason, reason) if r))


def with_static_halt(res, m: float, g: float, k3: float, mu_s: float):
    """A fit at fixed mu_s with ``fixed["mu_s"]`` and ``derived["halt_time"]`` of its own
    motion (the reference with mu_s, where it halts within twice the window; otherwise the
    value stays the ansatz's estimate for mu_s = mu, which is later)."""
    res = dataclasses.replace(res, fixed={**res.fixed, "mu_s": float(mu_s)})
    sol, _ = _motion(res, m, g, k3, mu_s)
    halt = float(sol.halt_time)
    if not (bool(np.asarray(sol.halted)) and math.isfinite(halt)):
        return res
    return dataclasses.replace(res, derived={**res.derived,
                                             "halt_time": float(res.t[0]) + halt})


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
        (1-based), the fits made, and the rms and the model's position at the window's end
        of the sliding-friction fit (mu_s = mu).
    """
    m, g, k3 = _constants(options)
    # the search's fits are inner fits (no refusal, no profile of the intervals): the chosen
    # one is fitted again at the end with every check of a plain fit
    base = fit(trace_or_t, x, free=free, _inner=True, **options)

    def cost(res):
        return float(res.chisqr) if res is not None and np.isfinite(res.chisqr) else math.inf

    def run(value, start=base, inner=True):
        # a fit at fixed mu_s from another fit's optimum with the reference model directly
        # (one start: the caller's starts were spent on the sliding fit)
        kw = {**options, "starts": 1, "p0": {n: float(start.params[n]) for n in PARAMS}}
        try:
            return fit(trace_or_t, x, free=free, mu_s=value, _inner=inner, _direct=True, **kw)
        except ValueError:
            if not inner:
                raise
            return None

    done: dict[int, object] = {}  # candidate halt j (of the sliding fit's screen) -> fit

    best, best_value = base, None
    for _, j, value in screen(base, m, g, k3)[:REFINE]:
        res = done[j] = run(value)
        if cost(res) < cost(best):
            best, best_value = res, value
    fits = len(done)
    if best_value is not None:
        # the screen at the best fit's parameters: a halt not yet fitted that screens below it
        tried = {best_value}
        for c, _, value in screen(best, m, g, k3):
            if fits >= MAX_FITS or c >= cost(best):
                break
            if any(abs(value - v) <= 1e-12 * max(1.0, abs(v)) for v in tried):
                continue
            tried.add(value)
            res = run(value)
            fits += 1
            if cost(res) < cost(best):
                best, best_value = res, value
    # the chosen fit again as a plain fit (its checks, and a refusal with the true reason)
    best = run(best_value, start=best, inner=False)
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
