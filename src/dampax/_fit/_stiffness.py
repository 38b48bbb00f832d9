"""``fit(free=(..., "k3"))``: the cubic stiffness k3, profiled around the linear-spring fit.

The fit at fixed k3 is a plain least-squares fit (k3 a constant of its model); S(k3), its
residual sum of squares, is minimised over k3 by Brent's method and k3's interval comes from
the curvature of S (docs/cubic_stiffness.md; issue 14, issue 25 for the profile check).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from .._oscillator import Oscillator
from .._solve import solve
from ._core import FIT_MODELS
from ._dist import norm_ppf
from ._halts import first_halt
from ._intervals import ar1_coefficient
from ._params import PARAMS, start_amplitude
from ._pipeline import DIRECT_INNER, FULL, INNER, finished, fitted, run
from ._profile import PROFILE_FAIL, PROFILE_REACH, other_halt_check, profile_side
from ._text import NO_FREQUENCY

#: the reach of k3's search: e = k3 A^2/(m w0^2) within +- this (docs/cubic_stiffness.md)
K3_REACH = 0.3
#: points of the coarse scan of S(e) over [-K3_REACH, K3_REACH] that looks for a lower basin
#: than the one Brent's method found from 0 (a step of 0.075 in e)
K3_GRID = 9


class Profile(NamedTuple):
    """k3's profile: S(e) minimised over e = k3 A^2/(m w0^2) (e = k3 / scale)."""

    base: object  # the linear-spring fit
    at: Callable  # e -> the fit at fixed k3 = e * scale (memoised)
    cost: Callable  # e -> its residual sum of squares (1e300 where not finite)
    evaluations: Callable  # () -> the fits made so far
    scale: float
    e_best: float
    h: float  # the step of the central differences
    s0: float  # S(e_best)
    sigma2: float  # the noise variance, inflated for the residuals' AR(1) correlation
    sd_e: float  # e's standard error
    rho: float


def profile_k3(problem, base) -> Profile:
    """After the linear-spring fit ``base`` (the plain plan), S(e) minimised by Brent's method from
    fits at fixed k3 started at its optimum and from it with w0 less the rise k3 gives
    (:func:`hardening_shift`), the lower kept (no batch of starts: the global starts were spent
    on the linear fit; the exact model's directly, without its approximate start), and e's
    standard error from the curvature of S at the minimum."""
    from scipy.optimize import minimize_scalar

    w0 = float(base.params["w0"])
    amp = start_amplitude(base.params)
    scale = problem.consts.m * w0 * w0 / (amp * amp)  # k3 of e = k3 A^2/(m w0^2) = 1
    start = {name: float(base.params[name]) for name in PARAMS}
    # the exact model's fits start from the linear spring's exact optimum, not from the
    # approximate model's (the ansatz's k3 phase integral costs some 26 evaluations per sample
    # and step: 34 s of a 35 s fit of 15,274 samples, 1,010 s for the whole profile)
    plan = _fixed_k3_plan(problem)
    cache, results = {}, {}
    shift = hardening_shift(problem, amp) if "w0" in base.varied else 0.0

    def fit(e):
        # from the linear spring's w0 and from it less the rise this k3 gives: the lower;
        # assessed only where its result is asked for (``at``: 3 of some 20-50 fits)
        if e not in cache:
            w0s = (w0,) if shift * e == 0.0 else (w0, w0 / (1.0 + shift * e))
            fits = [(p, fitted(p, plan)[1]) for p in (
                problem.starting_at({**start, "w0": w}, starts=1).with_consts(k3=e * scale)
                for w in w0s)]
            cache[e] = min(fits, key=lambda f: _finite_cost(f[1].best.chisqr))
        return cache[e]

    def at(e):
        e = float(e)
        if e not in results:
            problem_e, state = fit(e)
            results[e] = finished(problem_e, plan, state, {})
        return results[e]

    def cost(e):
        return _finite_cost(float(fit(float(e))[1].best.chisqr))

    opt = minimize_scalar(cost, bracket=(-0.01, 0.01), bounds=None, method="brent",
                          options={"xtol": 1e-4, "maxiter": 40})
    e_best = float(np.clip(opt.x, -K3_REACH, K3_REACH))
    e_best = _lower_basin(cost, e_best)
    best = at(e_best)
    h = max(0.02 * abs(e_best), 2e-3)
    s0, sp, sm = cost(e_best), cost(e_best + h), cost(e_best - h)
    curv = (sp + sm - 2.0 * s0) / (h * h)
    r = np.asarray(best.residuals, dtype=float)
    n, p = r.size, best.nvarys + 1
    rho = ar1_coefficient(r, clip=(0.0, 0.99), pearson=True)
    sigma2 = s0 / max(n - p, 1) * (1.0 + rho) / (1.0 - rho)
    sd_e = math.sqrt(2.0 * sigma2 / curv) if curv > 0 else math.inf
    return Profile(base, at, cost, lambda: len(cache), scale, e_best, h, s0, sigma2, sd_e,
                   rho)


def _fixed_k3_plan(problem):
    """The plan of a fit at fixed k3 with one start: the exact model directly (without its
    approximate start) where it integrates."""
    return DIRECT_INNER if FIT_MODELS[problem.settings.model].integrates else INNER


def _finite_cost(chisqr) -> float:
    return float(chisqr) if np.isfinite(chisqr) else 1e300


def hardening_shift(problem, amp: float) -> float:
    """c of the cubic spring's frequency w0 (1 + c e) at e = k3 A^2/(m w0^2) (A = ``amp``),
    averaged as a least-squares fit of the linear spring weighs it: the frequency at amplitude
    a is w0 (1 + 3/8 e (a/A)^2) to first order (docs/cubic_stiffness.md's Lindstedt series),
    each half swing's phase weighted by its amplitude squared, c = 3/8 <a^4>/(<a^2> A^2) over
    the window's turning points (3/8 without them). A linear spring's w0 takes up the
    hardening's mean rise; the fits at fixed k3 start from it and from it less this rise, and
    keep the lower cost: from the first alone they stayed in its basin (fit_calibration.py seed
    21, draw 156: w0 9 sd high at every k3, k3 a twelfth of the truth), from the second alone
    draw 160 (k3 A^2/(m w0^2) = 0.076, ten swings of Coulomb friction) fell into another (536
    noise variances above the truth's cost)."""
    a = np.asarray(problem.data.analysis.ext_x, dtype=float)
    a2 = np.mean(a * a) if a.size else 0.0
    if not (a2 > 0 and amp > 0):
        return 3.0 / 8.0
    return 3.0 / 8.0 * float(np.mean(a ** 4) / (a2 * amp * amp))


def _lower_basin(cost, e_best: float) -> float:
    """e of the lowest S: Brent's minimum ``e_best``, unless a coarse scan of S over k3's
    search (:data:`K3_GRID` points) finds a point lower, whose neighbourhood is then searched
    (bounded Brent within one grid step). S can have two basins where w0 is fitted: a
    hardening spring's rising frequency taken up by a higher w0 with k3 near 0 (fit_calibration
    .py seed 21, draw 192: k3 a fifth of the truth, w0 7 sd high, 103 noise variances above the
    truth's cost, reported as a success). Where the fits at every k3 sit in the other basin
    (draw 156: S one valley, w0 9 sd high at each k3) the scan cannot help: their second start
    (:func:`hardening_shift`) does."""
    from scipy.optimize import minimize_scalar

    grid = np.linspace(-K3_REACH, K3_REACH, K3_GRID)
    lowest = float(min(grid, key=cost))
    if not cost(lowest) < cost(e_best):
        return e_best
    step = float(grid[1] - grid[0])
    opt = minimize_scalar(cost, bounds=(max(lowest - step, -K3_REACH),
                                        min(lowest + step, K3_REACH)),
                          method="bounded", options={"xatol": 1e-4, "maxiter": 40})
    return float(opt.x) if cost(float(opt.x)) < cost(lowest) else lowest


def carried_covariance(pr: Profile):
    """What k3's uncertainty adds to the others' covariance (issue 25): g g^T sd_e^2 with g
    the change of each optimum with e (central differences of the profile's fits); None
    where not finite."""
    best, plus, minus = pr.at(pr.e_best), pr.at(pr.e_best + pr.h), pr.at(pr.e_best - pr.h)
    g = np.array([(plus.params[n] - minus.params[n]) / (2.0 * pr.h) for n in best.varied])
    if np.all(np.isfinite(g)) and math.isfinite(pr.sd_e):
        return np.outer(g, g) * pr.sd_e * pr.sd_e
    return None


def k3_sides(pr: Profile, entry: dict) -> str:
    """k3's interval against the cost itself (as ``_profile.profile_ratios`` for the others):
    S at e -+ 2 sd_e must rise by about the 4 sigma^2 the interval assumes; a side where it
    rises c < 1 times that is widened by 1/sqrt(c) (followed out where c < 1/4:
    ``_profile.profile_side``); where its bound lies beyond the reach (S is flat: where the
    block sticks moves with k3 and changes the cost by steps) the interval does not hold.
    Fills ``entry`` (the profile's report) and returns the failure's reason, or ""."""
    rises = []
    for sgn in (-1, 1):
        def rise(d, sgn=sgn):
            return (pr.cost(pr.e_best + sgn * d) - pr.s0) / (4.0 * pr.sigma2)

        rises.append(profile_side(rise, 2.0 * pr.sd_e, rise(2.0 * pr.sd_e)))
    entry["profile"] = rises
    entry["scale"] = tuple(1.0 / math.sqrt(c) if math.isfinite(c) and PROFILE_FAIL <= c < 1.0
                           else 1.0 for c in rises)
    if any(math.isfinite(c) and c < PROFILE_FAIL for c in rises):
        return (f"the intervals do not hold: with k3 held from 2 to "
                f"{2 * PROFILE_REACH:.0f} sd from its value and the rest refitted the cost "
                "rises less than its interval assumes (the cost is not quadratic in k3 "
                "over its interval)")
    return ""


def undetermined_reason(pr: Profile) -> str:
    """The failure's reason where the window does not determine k3, or "": S does not curve
    upward at its lowest point (k3's interval unbounded; at the edge of the search, where
    Brent's method stopped, or inside it). The other constants were fitted at that k3, and
    their intervals carry k3's uncertainty only through a finite standard error
    (:func:`carried_covariance`): wide draw 7 of seed 11 (1.4 half swings of a viscous decay,
    w0 fitted, k3 at the edge with no interval) reported w0 11 standard errors off the truth
    as a success. A finite interval that reaches past the edge is carried over and holds
    (wide seed 9 draws 13 and 18: k3 at -0.3, every interval covering the truth)."""
    if math.isfinite(pr.sd_e) and pr.sd_e > 0:
        return ""
    edge = (f" at the edge of k3's search (k3 A^2/(m w0^2) = {pr.e_best:+.2g})"
            if abs(pr.e_best) >= K3_REACH else "")
    return (f"k3 is not determined by this window: the cost does not curve upward around its "
            f"lowest point{edge}, so k3's interval is unbounded, and the other constants' "
            "intervals do not allow for it: hold k3 (k3=...) or fit a record with more swings")


def bias_reason(problem, pr: Profile, bias: dict) -> str:
    """The failure's reason where the approximate model's own error for this cubic spring
    moves a constant beyond 1.96 standard errors (issue 37), or ""."""
    worst = max(bias, key=lambda n: bias[n]["z"], default=None)
    if worst is None or not bias[worst]["z"] > norm_ppf(0.975):
        return ""
    shown = ", ".join(f"{n} by {b['shift']:+.3g} ({b['z']:.1f} standard errors)"
                      for n, b in bias.items() if b["z"] > 1.0)
    return (f"the {problem.settings.model} model's own error for this cubic spring biases "
            f"the fit beyond its intervals: fitted to the exact motion (the reference) of its "
            f"own constants, it moves {shown}; fit with model='reference', exact for a cubic "
            "spring")


def fit_k3(problem):
    """The fit of ``problem`` with the cubic stiffness k3 profiled (see ``fit``'s ``free``):
    every fit at fixed k3 is ``problem.with_consts(k3=...)``, the data prepared once.

    S(k3), the residual sum of squares of the fit at fixed k3, is minimised by Brent's method
    in e = k3 A^2/(m w0^2) on [-K3_REACH, K3_REACH]; the interval of k3 comes from the
    curvature of S at the minimum (central differences), sigma^2 = S/(n - p) and the factor
    (1 + rho)/(1 - rho) of the residuals' lag-1 autocorrelation rho. The fit fails where the
    window does not determine k3 (:func:`undetermined_reason`). Returns the fit at the best
    k3 with "k3" in ``params``, ``stderr``, ``free`` and ``conf_interval``.
    """
    base = run(problem, FULL)
    if not base.success and NO_FREQUENCY in base.reason:
        return _unsearched(base)
    pr = profile_k3(problem, base)
    (best, others), k3, sd = searched(problem, pr.at(pr.e_best), pr.e_best * pr.scale), \
        pr.e_best * pr.scale, pr.sd_e * pr.scale
    entry = {"value": k3, "stderr": sd, "ratio": pr.e_best, "ratio_scale": pr.scale,
             "rho": pr.rho, "evaluations": pr.evaluations(), "rms_linear": pr.base.rms,
             "at_bound": abs(pr.e_best) >= K3_REACH}
    extra = carried_covariance(pr)
    success, reason = best.success, best.reason
    if math.isfinite(pr.sd_e) and pr.sd_e > 0 and best.success:
        reason = k3_sides(pr, entry) or reason
        success = success and reason == best.reason
    if success:
        reason = undetermined_reason(pr) or reason
        success = reason == best.reason
    if success and not FIT_MODELS[problem.settings.model].integrates and \
            math.isfinite(pr.sd_e):
        # the approximate model's own error for a cubic spring, against the fit's standard
        # errors (issue 37: D 43 standard errors off the truth, reported as a success)
        bias = model_bias(problem, best, (pr.e_best, pr.scale, pr.h, pr.sd_e), extra)
        reason = bias_reason(problem, pr, bias) or reason
        success = success and reason == best.reason
        entry["model_bias"] = bias
    res = dataclasses.replace(
        best, success=success, reason=reason,
        params={**best.params, "k3": k3}, stderr={**best.stderr, "k3": sd},
        free=tuple(best.free) + ("k3",), profiled={"k3": entry}, extra_cov=extra,
        derived={**best.derived, "k3_ratio": pr.e_best, "rms_linear_spring": pr.base.rms,
                 "k3_z": norm_ppf(0.975)})
    # the neighbouring halts weighed against intervals that carry k3's uncertainty (at fixed
    # k3 they are narrower: wide draw 31, a false failure 3 of those sd away)
    return other_halt_check(res, others, held_mu(problem.with_consts(k3=k3), best)) \
        if success and others else res


def _unsearched(base):
    """The linear-spring fit ``base``, failed because the window does not determine w0, with
    k3 unsearched (NaN, no interval): a free k3 only adds to what the window leaves open.
    Its search fitted 20-50 motions of that undetermined frequency, each to the end of its
    step budget, for the same failure (wide seed 46 draw 80: 1.7 half swings, mu, b, D, w0
    and k3 free; 105-125 s, 1.5 s warm without the search)."""
    nan = math.nan
    return dataclasses.replace(
        base, reason=f"{base.reason}; k3 was not searched (a free k3 leaves the frequency "
        "more open still)", params={**base.params, "k3": nan},
        stderr={**base.stderr, "k3": nan}, free=tuple(base.free) + ("k3",),
        profiled={"k3": {"value": nan, "stderr": nan, "evaluations": 0}})


def held_mu(problem, best):
    """mu's profile at the fit's k3, for ``_profile.other_halt_check`` to follow out past a
    neighbouring halt: mu -> the fit with mu held there and k3 at ``problem``'s, one start
    from the fit's values and one from a held fit's nearer mu (``near``), the lower kept. k3
    stays at the profile's optimum (a profile over k3 too would take some 20 fits per point):
    each cost bounds mu's profile from above, so the profile may be bounded sooner than with
    k3 free (seed 23 draw 70, seed 24 draw 99: the check failed them with the truth inside).

    Returns:
        (mu, near) -> (its cost, whether its motion halts at its first turning point with
        the offset free: ``_halts.first_halt``, {name: value} of its parameters).
    """
    plan = _fixed_k3_plan(problem)
    start = {name: float(best.params[name]) for name in PARAMS if name in best.params}
    flat = bool(problem.vary.offset)

    def at(mu: float, near: dict | None = None):  # (only costs and values: not assessed)
        fits = [fitted(problem.starting_at({**s, "mu": mu}, starts=1).holding("mu"), plan)[1]
                .best for s in ((start, {**start, **near}) if near else (start,))]
        r = min(fits, key=lambda f: _finite_cost(f.chisqr))
        values = {k: float(getattr(r.params, k)) for k in start}
        return (_finite_cost(r.chisqr), flat and first_halt(values, problem.data.t,
                                                            problem.consts.motion), values)
    return at


def searched(problem, best, k3: float):
    """The exact model's fit at the profile's k3 again with the fit's global starts (the
    profile's fits have one start each): where its residuals hold structure, its verdict
    needs the search of its own starts (``_assess.exact_structure``: spring run 1 with k3
    free failed "no search of the exact model ran"), and the search of the neighbouring
    halts (``_halts.search_other_halts``). Kept where its cost is not higher; ``best`` as it
    is for a closed-form model or one start.

    Returns:
        (the fit, the held fits for ``_halts.other_halt_check``: {mu: (cost, first halt,
        values)}, made by the caller against intervals that carry k3's uncertainty).
    """
    if not FIT_MODELS[problem.settings.model].integrates or problem.settings.starts <= 1:
        return best, {}
    # with the search of the motions that halt at a neighbouring turning point (wide draws
    # 23, 24: one swing, mu 4.4 and 4.7 half-widths off, reported as successes)
    again = run(problem.starting_at({name: float(best.params[name]) for name in PARAMS})
                .with_consts(k3=k3), INNER._replace(neighbouring_halts=True, halt_check=False,
                                                    profile_checks=True))
    if float(again.chisqr) <= float(best.chisqr) * (1.0 + 1e-6):
        return again, again.other_halts
    # the search's own optimum, a little higher, is one of the held fits: where its mu lies
    # outside the fit's interval at a likelihood ratio below the 1 % point the data hold two
    # answers (wide draw 23 with D fixed: mu 2.99 +- 0.16 and the search's 7.68 0.3 noise
    # variances up, the truth 4.78)
    others = {**again.other_halts}
    if "mu" in again.params:
        others[float(again.params["mu"])] = (float(again.chisqr), False, {})
    return best, others


def model_bias(problem, best, profile: tuple, extra=None) -> dict:
    """The bias of an approximate model's k3 fit from its own error: the exact motion of the
    fit's constants (the reference, k3 included) is fitted again as data, noise-free, with the
    same model: where the model were exact the fit would return its constants; what it moves
    them by is the bias its approximation puts into them (to first order the same at the
    truth). k3's own shift comes from the minimum of a parabola through the refits' costs at
    e_best and e_best -+ h (three fits at fixed k3, from the fit's optimum).

    Arguments:
        problem: the fit's prepared problem (its settings: the same fit of other data).
        best: the fit at the best k3.
        profile: (e_best, scale, h, sd_e): k3 = e_best * scale; the profile's step and k3's
            sd in e.
        extra: the covariance that k3's uncertainty adds to the others (over
            ``best.varied``), or None.

    Returns:
        {name: {"shift": model's shift of the parameter, "z": |shift| / its standard error}}
        for the fitted damping constants and k3 (empty where the exact motion cannot be
        computed).
    """
    e_best, scale, h, sd_e = profile
    p = best.params
    m, g = problem.consts.m, problem.consts.g
    t = np.asarray(best.t, dtype=float)
    tau = t - t[0]
    try:
        osc = Oscillator(m=m, k=m * p["w0"] ** 2, mu=p["mu"], b=p["b"], D=p["D"], g=g,
                         k3=e_best * scale)
        sol = solve(osc, p["x0"], p["v0"], method="reference", t_end=float(tau[-1]) * 1.001
                    + 1e-9, ts=tau)
        exact = np.asarray(sol.x(tau), dtype=float) + p["offset"]
    except ValueError:
        return {}
    # the same window and mask on the exact motion, started at the fit (no new analysis)
    exact_problem = problem.with_positions(exact).starting_at(
        {name: float(p[name]) for name in PARAMS}, starts=1)
    refits = {}
    try:
        for e in (e_best - h, e_best, e_best + h):
            refits[e] = run(exact_problem.with_consts(k3=e * scale), INNER)
    except ValueError:
        return {}
    costs = np.array([float(r.chisqr) for r in refits.values()])
    if not np.all(np.isfinite(costs)):
        return {}
    curv = (costs[0] + costs[2] - 2.0 * costs[1]) / (h * h)
    shift_e = -(costs[2] - costs[0]) / (2.0 * h * curv) if curv > 0 else 0.0
    shift_e = float(np.clip(shift_e, -h * 4.0, h * 4.0))
    lo, mid, hi = refits.values()
    out = {}
    for name in best.free:
        slope = (float(hi.params[name]) - float(lo.params[name])) / (2.0 * h)
        shift = float(mid.params[name]) - float(p[name]) + slope * shift_e
        se2 = float(best.stderr.get(name, math.nan)) ** 2
        if extra is not None and name in best.varied:
            i = list(best.varied).index(name)
            se2 += float(extra[i, i])
        se = math.sqrt(se2)
        out[name] = {"shift": shift, "z": abs(shift) / se if se > 0 else math.inf}
    out["k3"] = {"shift": shift_e * scale, "z": abs(shift_e) / sd_e if sd_e > 0 else math.inf}
    return out
