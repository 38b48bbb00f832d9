"""Where the block halts, for every fit of the exact model: the motion of a fit's parameters,
its turning points and the thresholds of mu (or mu_s) that halt it there; the pipeline's
search of the motions that halt at a neighbouring turning point (:func:`search_other_halts`,
:func:`other_halt_check`) and the checks of a fit at a given mu_s (:func:`with_static_halt`,
:func:`above_mu_s`). The search of mu_s itself (``fit(free=(..., "mu_s"))``) is
``_static.fit_mu_s``, above the pipeline.

With static friction mu_s >= mu the block sticks at the first turning point x_j where
|k x_j + k3 x_j^3| <= mu_s m g (``Oscillator.mu_s``); with mu_s = mu where that holds for mu.
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np

from .._oscillator import Oscillator
from .._solve import default_swings, prepare_reference, solve
from ._core import FIT_MODELS, FIT_RESULTS
from ._params import varied_names
from ._problem import SETTLE, predicted_start
from ._profile import LR_Z
from ._starts import REACHED_RTOL
from ._text import lower_cost

#: step budget of the search's fits with mu held past a threshold: the cost jumps where the
#: halt moves, so a held fit that has not converged in this many steps sits on that jump
#: (measured on issue 36's family: such fits ran the whole default budget of 256 steps, 4 of
#: the 5 seconds of a fit); its cost then bounds the held optimum's from above
HALT_STEPS = 64
#: a held fit that ran out of its HALT_STEPS is continued where its cost is within this many
#: noise variances of the optimum's: the check fails below LR_CHI2 (6.63) times the
#: intervals' variance ratio (sd/stderr)^2, up to about 10 for correlated residuals
NEAR_RISE = 100.0
#: a fit of the search whose cost after ``_lm.GIVE_UP_AFTER`` (16) steps lies more than this
#: many noise variances above the optimum's stops there (:func:`_far`): on the calibration
#: family (benchmarks/halt_steps.py, 1341 held fits) the held fits that end within
#: NEAR_RISE lay at most 385 NEAR_RISE up after 16 steps, 26 times below this bound; about
#: one held fit in thirteen lies above it and sits on a jump of the halt (the example's three
#: lie 4e5 NEAR_RISE up); after ``_lm.GIVE_UP_EARLY`` (8) steps, one above 10 times it stops
GIVE_UP_RISE = 1e4 * NEAR_RISE


def _motion_start(p: dict, t, m: float, g: float, k3: float, mu_s=None):
    """(oscillator, x0, v0, span) of a fit's motion: parameters ``p`` over the window ``t``."""
    osc = Oscillator(m=m, k=m * p["w0"] ** 2, mu=p["mu"], b=p["b"], D=p["D"], g=g, k3=k3,
                     mu_s=None if mu_s is None else max(float(mu_s), float(p["mu"])))
    return osc, p["x0"], p["v0"], float(t[-1] - t[0])


def _motion_swings(osc, x0, v0, span: float) -> int | None:
    """The swing budget of a fit's motion over twice its window: from the window and the
    frequency only (``default_swings(..., until_halt=False)``), so that the motions of every
    mu, b and D of a fit and its searches share one compiled program (the budget from the
    halt's bound gave each its own: two more programs, 1.3 s of a cold fit on its critical
    path); None (the solve's own budget) beyond ``MAX_SWINGS``."""
    try:
        return default_swings(osc, x0, v0, 2.0 * span, until_halt=False)
    except ValueError:
        return None


def _motion(res, m: float, g: float, k3: float, mu_s=None):
    """The reference solution of a fit's motion from its start over twice its window (one
    compiled program for every call of a search: :func:`_motion_swings`), and the window's
    span."""
    osc, x0, v0, span = _motion_start(res.params, res.t, m, g, k3, mu_s)
    return solve(osc, x0, v0, method="reference", t_end=2.0 * span,
                 max_swings=_motion_swings(osc, x0, v0, span)), span


def prepare_motion(params, t, m: float, g: float, k3: float) -> None:
    """Start compiling, in the background, the program of :func:`other_halts`'s motion for a
    fit near ``params`` (a TraceParams, the guess) over the window ``t``
    (``_solve.prepare_reference``)."""
    p = {k: float(v) for k, v in params._asdict().items()}
    osc, x0, v0, span = _motion_start(p, np.asarray(t), m, g, k3)
    prepare_reference(osc, x0, v0, t_end=2.0 * span,
                      max_swings=_motion_swings(osc, x0, v0, span))


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


def _thresholds_of(params, t, m: float, g: float, k3: float) -> tuple[np.ndarray, bool]:
    """:func:`thresholds` of a fit's parameters (dict or TraceParams) over the window ``t``;
    none where the motion cannot be integrated over twice the window."""
    p = params if isinstance(params, dict) else params._asdict()
    ns = SimpleNamespace(params={k: float(v) for k, v in p.items()}, t=np.asarray(t))
    try:
        return thresholds(ns, m, g, k3)
    except ValueError:  # the motion fails past the data (a softening spring that lets go):
        return np.zeros(0), False  # no neighbour to search (it raised out of fit before)


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
        point; both where the motion cannot be integrated over twice the window). A motion
        that does not halt inside the window has one neighbour: the motion that halts at the
        window's last turning point (th_(h-1) = its threshold, th_h NaN); none without a
        turning point inside the window.
    """
    return _neighbours(*_thresholds_of(params, t, m, g, k3))


def _neighbours(th: np.ndarray, halts: bool) -> tuple[float, float]:
    """(th_(h-1), th_h) of :func:`other_halts` from the motion's thresholds."""
    if th.size == 0:
        return math.nan, math.nan
    if not halts:  # it halts after the window: the neighbour halts at its last turning point
        return float(th[-1]), math.nan
    h = th.size - 1
    return (float(th[h - 1]) if h >= 1 else math.nan), float(th[h])


def search_other_halts(problem, best, last):
    """The search of a fit for a better optimum where the block halts at a neighbouring
    turning point (:func:`other_halts`), for the exact model with mu free.

    With the thresholds th_(h-1) (halt one turning point earlier) and th_h (one later): mu
    held just past each threshold (by a quarter of its standard error), at 1.05 and 1.25
    th_(h-1) and at 0.95 and 0.8 th_h, the rest refitted; and free fits started at 1.05
    th_(h-1) and 0.95 th_h (where to look, not thresholds: the verdict is the likelihood
    ratio of :func:`other_halt_check`; :func:`_free_fit`: continued past HALT_STEPS only
    near the optimum's cost). A lower cost is taken (a held fit's by freeing mu
    from it: the optimizer only goes downhill, so it stays in that basin) and the search
    repeated once around it.

    Arguments:
        problem: the fit's ``_problem.Problem``.
        best: the fit's optimum (the core's output).
        last: the fit's last solve (``_problem.Solved``: its model, scale and options).

    Returns:
        (the optimum, the last solve, {held mu: (its cost, whether its motion halts at its
        first turning point with the offset free: :func:`first_halt`, {name: value} of its
        varied parameters)}, the stages' notes): the held fits of both rounds and the
        optimum a lower cost replaced, for :func:`other_halt_check`.
    """
    held, full = _holding_mu(problem)
    constants = problem.consts.motion
    name, fs = last.model, last.fs
    # first halts: mu ~ offset (exactly without k3; with k3 nearly, its cubic force the only
    # thing that tells mu from the offset over one swing: wide draw 41, 12 half-widths off)
    flat = bool(problem.vary.offset)
    others, notes = {}, ()  # every held fit of the search, and an optimum it left
    for _ in range(2):
        motion = _thresholds_of(best.params, problem.data.t, *constants)  # (th, halts)
        prev, nxt = _neighbours(*motion)
        mu = float(best.params.mu)
        se = float(best.stderr.mu) if math.isfinite(float(best.stderr.mu)) else 0.0
        points = [prev * (1.0 + 1e-3) + 0.25 * se, 1.05 * prev, 1.25 * prev,
                  nxt * (1.0 - 1e-3) - 0.25 * se, 0.95 * nxt, 0.8 * nxt]
        fits = []
        for mu_alt in points:
            if math.isfinite(mu_alt) and mu_alt > 0.0:
                # above mu a motion that halts at its first turning point keeps the fit's
                # first swing (wide draw 41: the optimum on that threshold, the linearised
                # start 94 noise variances up at 1.05 mu, the first swing's 1.0)
                swing = first_halt_start(best.params, problem.data.t, constants, motion,
                                         mu=mu_alt) if flat and mu_alt > mu else None
                last = _held_fit(held, full, best, mu_alt, last, swing)
                others[mu_alt] = (float(last.out.chisqr),
                                  flat and first_halt(last.out.params, problem.data.t, constants),
                                  _values(last.out, problem))
                fits.append(last.out)
        first = first_halt_start(best.params, problem.data.t, constants, motion) \
            if flat else None
        if first is not None:  # the basin where the profile of mu is flat (held: no jumps)
            last = _free_fit(full, best, first, name, fs)
            others[float(first.mu)] = (float(last.out.chisqr), first_halt(
                last.out.params, problem.data.t, constants), _values(last.out, problem))
        lower = [f for f in fits if float(f.chisqr) < float(best.chisqr)]
        starts = [min(lower, key=lambda f: float(f.chisqr)).params] if lower else []
        starts += [best.params._replace(mu=v) for v in (1.05 * prev, 0.95 * nxt)
                   if math.isfinite(v) and v > 0.0]
        better = None
        for p in starts:
            last = _free_fit(problem, best, p, name, fs)
            if float(last.out.chisqr) < float(best.chisqr if better is None else better.chisqr):
                better = last.out
        if better is None:
            break
        # a cost lower by less than the starts' "reached" share is the same optimum polished
        # again: it replaces the optimum without a note (one claimed another halt "fits
        # better" by 2.7e-12 %)
        if float(better.chisqr) < float(best.chisqr) * (1.0 - REACHED_RTOL):
            notes += (f"a motion that halts at another turning point fits better (cost "
                      f"{lower_cost(0.5 * float(better.chisqr), 0.5 * float(best.chisqr))})",)
        others[float(best.params.mu)] = (  # the basin left: nearly as good? (first_halt)
            float(best.chisqr), flat and math.isnan(prev) and math.isfinite(nxt),
            _values(best, problem))
        best = better
    return best, last, others, notes


def _holding_mu(problem):
    """(the problem with mu held and :data:`HALT_STEPS` steps, with mu held and the whole
    budget): the held fits' problems of :func:`_held_fit`."""
    full = problem.holding("mu")
    return dataclasses.replace(full, settings=full.settings._replace(
        max_steps=min(full.steps, HALT_STEPS))), full


def mu_profile(problem, best, last):
    """mu's profile past the neighbouring halts, for ``_profile.other_halt_check`` to follow
    out: a function of mu that fits with mu held there and the rest refitted
    (:func:`_held_fit`, as the search's held fits), each from the last one's solve.

    Arguments:
        problem, best, last: the fit's problem, optimum and last solve, as for
            :func:`search_other_halts`.

    Returns:
        (mu, near) -> (its cost, whether its motion halts at its first turning point with the
        offset free: :func:`first_halt`, {name: value} of its varied parameters); ``near``
        ({name: value} of a held fit nearer mu, or None) is a second start, the lower cost
        kept: the linearised start of the search's held fits reaches another valley far out
        (seed 0 draw 134: 216 noise variances up at 14 interval sd, where the profile lies at
        4).
    """
    held, full = _holding_mu(problem)
    flat, constants, solved = bool(problem.vary.offset), problem.consts.motion, [last]

    def at(mu: float, near: dict | None = None):
        solved[0] = _held_fit(held, full, best, mu, solved[0])
        if near:  # and from a held fit's values nearer mu (the profile continued)
            other = _free_fit(full, best, best.params._replace(**{**near, "mu": mu}),
                              solved[0].model, solved[0].fs, like=solved[0])
            if float(other.out.chisqr) < float(solved[0].out.chisqr):
                solved[0] = other
        out = solved[0].out
        return (float(out.chisqr), flat and first_halt(out.params, problem.data.t, constants),
                _values(out, problem))
    return at


def _values(out, problem) -> dict:
    """{name: value} of a fit's varied parameters."""
    return {k: float(getattr(out.params, k)) for k in varied_names(problem.vary)}


def first_halt(params, t, constants) -> bool:
    """Whether a fit's motion halts at its first turning point inside the window (:func:
    `other_halts`: no earlier threshold, a later one). Over that one swing Coulomb friction
    only moves the centre of the motion, by mu g / w0^2, and the block halts at the turning
    point for every mu above its threshold: with the offset free (and no k3), every larger mu
    fits exactly as well, its centre taken up by the offset."""
    prev, nxt = other_halts(params, t, *constants)
    return math.isnan(prev) and math.isfinite(nxt)


def first_halt_start(params, t, constants, motion=None, mu=None):
    """A start in the basin of the motions that halt at their first turning point, for a fit
    that halts at its first or second one (None otherwise): mu at ``mu``, by default twice
    the larger of its value and the first turning point's threshold (eq. 3: the block halts
    there for every mu above it), the centre of the first swing, -sign(v) mu g / w0^2, moved
    by x0 and taken back by the offset, so that the first swing is the fit's own
    (:func:`first_halt`). ``motion``: the fit's (thresholds, halts) where already computed."""
    th, halts = motion if motion is not None else _thresholds_of(params, t, *constants)
    p = params._asdict()
    if not (halts and th.size in (1, 2)):
        return None
    mu = 2.0 * max(float(th[0]), float(p["mu"])) if mu is None else float(mu)
    w0, v0, x0 = float(p["w0"]), float(p["v0"]), float(p["x0"])
    sign = math.copysign(1.0, v0) if v0 != 0.0 else -math.copysign(1.0, x0)
    shift = -sign * (mu - float(p["mu"])) * constants[1] / (w0 * w0)
    return params._replace(mu=mu, x0=x0 + shift, offset=float(p["offset"]) - shift)


def held_mu_starts(problem, best, model: str, value, own: bool = True) -> list:
    """The starts of a fit of mu's profile besides the linearised one (``_problem.
    predicted_start``), with mu held at ``value``:

    - above the optimum's mu, for the exact model with the offset free and a motion that
      halts at its first or second turning point, the motion that halts at the first, with
      the fit's own first swing (:func:`first_halt_start`). Over that swing friction moves only
      the centre, which the offset takes up, so mu's profile above a halt's threshold is flat
      or nearly (exactly without k3); the linearised start follows the optimum's side of that
      threshold and stops far up (wide draw 41: the profile's fit at 1.05 mu 94 noise
      variances up, from this start 1.0, the truth 31 interval sd away);
    - (``own``) the fit's own values, mu moved: where the block sticks sets basins apart, and
      the linearised start can end in another one (calibrated seed 34 draw 36: 3.2 noise
      variances up at 2 sd from there, 0.5 from here; the linearised one said the intervals
      hold, and the truth lay 3.5 half-widths outside mu's 99 % interval of a success).
    """
    out = []
    if problem.vary.offset and FIT_MODELS[model].integrates and float(value) > float(best.mu):
        out.append(first_halt_start(best, problem.data.t, problem.consts.motion,
                                    mu=float(value)))
    return [q for q in out + ([best._replace(mu=float(value))] if own else []) if q is not None]


def noise_variance(problem, best) -> float:
    """The noise variance of the optimum's residuals (its chi-square per degree of freedom)."""
    return float(best.chisqr) / max(problem.n - int(sum(bool(v) for v in problem.vary)), 1)


def _near(out, best, problem) -> bool:
    """Whether a fit's cost is within :data:`NEAR_RISE` noise variances of the optimum's."""
    return float(out.chisqr) - float(best.chisqr) < NEAR_RISE * noise_variance(problem, best)


def _far(problem, best) -> float:
    """The chi-square above which a fit of the search gives up after ``_lm.GIVE_UP_AFTER``
    steps: :data:`GIVE_UP_RISE` noise variances above the optimum's."""
    return float(best.chisqr) + GIVE_UP_RISE * noise_variance(problem, best)


def _unfinished(out) -> bool:
    """Whether a fit stopped without converging (its step budget ran out, or it failed)."""
    return int(np.asarray(out.code._value)) != int(FIT_RESULTS.successful._value)


def _free_fit(problem, best, start, name: str, fs: float, like=None):
    """A free fit of the search from ``start``: :data:`HALT_STEPS` steps (16 where it is then
    more than :data:`GIVE_UP_RISE` noise variances up: :func:`_far`), continued with the
    whole budget only where its cost is then within :data:`NEAR_RISE` noise variances of the
    optimum's (the rule of :func:`_held_fit`: a fit still far above after that many steps is
    crossing the jumps of the halt, and the optimizer only goes downhill). On the example
    trace such a start ran all 256 steps to a cost 9,000 times the optimum's. ``like``: a
    solve whose integrator options it keeps (None: the options of the start's w0).

    Returns:
        The last solve (``_problem.Solved``).
    """
    last = problem.solve(start, name, fs, like=like, budget=min(problem.steps, HALT_STEPS),
                         give_up=_far(problem, best))
    if _unfinished(last.out) and _near(last.out, best, problem):
        last = problem.solve(last.out.params, name, fs, like=last, settle=SETTLE)
    return last


def _held_fit(held, full, best, mu_alt: float, last, swing=None):
    """The fit with mu held at ``mu_alt``: :data:`HALT_STEPS` steps (``held``; 16 where it is
    then more than :data:`GIVE_UP_RISE` noise variances up: :func:`_far`) from the
    linearised profile, and where that is not near the optimum's cost, from ``swing`` too
    (a start that keeps the fit's first swing: :func:`first_halt_start`; the linearised
    profile follows the optimum's side of a halt's threshold, not the motion beyond it), the
    lower cost kept. Where its cost is within :data:`NEAR_RISE` noise variances of the
    optimum's, the held optimum may fit nearly as well: a fit that ran out of steps is
    continued with the whole budget (``full``), and a motion that :func:`other_halt_check`
    weighs (mu more than LR_Z standard errors away) is also fitted from the optimum's own
    values with mu replaced, the lower cost kept (draw 134 of fit_calibration.py was a
    confident wrong answer without it).

    Returns:
        The last solve (``_problem.Solved``).
    """
    name, fs = last.model, last.fs
    last = held.solve(predicted_start(best, "mu", mu_alt), name, fs, like=last,
                      give_up=_far(full, best))
    if swing is not None and not _near(last.out, best, full):
        other = held.solve(swing, name, fs, like=last, give_up=_far(full, best))
        if float(other.out.chisqr) < float(last.out.chisqr):
            last = other
    out = last.out
    if not _near(out, best, full):
        return last
    if _unfinished(out):
        last = full.solve(out.params, name, fs, like=last, settle=SETTLE)
    se = float(best.stderr.mu)
    if math.isfinite(se) and abs(mu_alt - float(best.params.mu)) > LR_Z * se:
        # a motion the check weighs: the linearised start may have led into another valley
        # (draw 134: a held cost 75 noise variances up, 4.7 from the optimum's own start)
        plain = full.solve(best.params._replace(mu=mu_alt), name, fs, like=last,
                           settle=SETTLE)
        if float(plain.out.chisqr) < float(last.out.chisqr):
            last = plain
    return last


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
    try:
        sol, _ = _motion(res, m, g, k3, mu_s)
    except ValueError:  # the motion fails past the data: the estimate stays
        return res
    halt = float(sol.halt_time)
    if not (bool(np.asarray(sol.halted)) and math.isfinite(halt)):
        return res
    return dataclasses.replace(res, derived={**res.derived,
                                             "halt_time": float(res.t[0]) + halt})
