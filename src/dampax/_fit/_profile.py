"""The intervals of a fit against its cost (used by ``_assess.assess`` and the k3 profile):
the profile of each parameter on either side of its interval (:func:`profile_ratios`,
followed out where it is far from a quadratic: :func:`profile_side`) and the likelihood-ratio
test of each damping constant at the bound 0 (:func:`bound_tests`, from a batch of starts
around :func:`transferred_start`). Each takes the fit's ``profile(name, value, ...)``: the
chi-square with that parameter held and the rest refitted."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

from ._params import DAMPING, d_per_unit, start_amplitude

#: with a parameter held 2 interval sd from its value and the others refitted, the cost rises
#: c times what the intervals assume (c = 1 where the model is linear in its parameters): the
#: bound of the interval on that side lies at 1/sqrt(c) of the reported distance, and for
#: c < 1 ``conf_interval`` widens that side by 1/sqrt(c) (c > 1: conservative, kept). Below
#: c = 1/4 (the bound beyond twice the reported one) one profile point no longer measures it:
#: the side is followed out (:func:`profile_side`) to where the cost rises as much as the
#: interval assumes, at most PROFILE_REACH times the reported distance (PROFILE_EVALS fits); a
#: side whose bound lies farther (a flat cost: the data do not bound it there) fails the fit,
#: its c PROFILE_FAIL
PROFILE_MEASURE, PROFILE_REACH, PROFILE_EVALS = 0.25, 8.0, 4
PROFILE_FAIL = 1.0 / PROFILE_REACH ** 2

#: the Wald test of a damping constant = 0 and the likelihood-ratio test must agree at this
#: level: z = 2.576 and chi2(1) = 6.63 (1 %)
LR_LEVEL = 0.01
LR_Z = 2.5758293035489004
LR_CHI2 = LR_Z * LR_Z
#: a damping constant whose 90 % interval excludes 0 (value / sd above this, 5 % one-sided) is
#: held at 0 too (:func:`bound_tests`): where its 99 % interval reaches 0 a rise below
#: LR_CHI2 is what the interval says, but the held fit can move the others beyond theirs
#: (seed 22 draw 38: b at z = 2.5, a decay that friction halting the block explains at a chi2
#: of 5.7, mu 8 interval sd up behind a rise of 6.8 at 4 sd)
BOUND_Z = 1.6448536269514722
#: no batch at the bound for a constant beyond this Wald z whose held fit from the fit's values
#: rose by QUADRATIC_SHARE z^2 or more: a batch matters only below a rise of LR_CHI2 (a valley)
#: or 0 (a local optimum), z^2 / 1,500 at z = 100: in 562 batches (benchmarks/README.md, issue
#: 36, 37th session) it did at z = 2.2, 3.0 and 11, never below 0.16 z^2 beyond z = 20
BATCH_Z, QUADRATIC_SHARE = 100.0, 0.1
#: a point of the cost at a likelihood-ratio chi2 below this widens the intervals as if it
#: lay at this rise (:func:`widening_toward`: the quadratic extrapolation beyond a nearly
#: flat rise reaches nowhere); the widened intervals' coverage is measured only on
#: fit_calibration.py's generated family (benchmarks/README.md, issue 36, thirteenth session)
WIDEN_FLOOR = 1.0


class Optimum(NamedTuple):
    """The fit whose intervals are held against its cost (:func:`profile_ratios`,
    :func:`bound_tests`).

    Attributes:
        params: the fitted values by name.
        stderr: their delta-method standard errors.
        sd: their interval sd (allowing for correlated noise).
        chisqr: the fit's chi-square.
        s2: the noise variance of its residuals (chisqr over the degrees of freedom).
    """

    params: dict
    stderr: dict
    sd: dict
    chisqr: float
    s2: float


#: which power of the amplitude each damping constant's decay rate carries (eq. 21: the
#: envelope falls as dA/dt = -(d0 + d1 A + d2 A^2))
_POWER = {"mu": 0, "b": 1, "D": 2}


def transferred_start(name: str, params: dict, others, d_scale: dict, amplitude: float):
    """A start for the fit with ``name`` held at 0: its decay rate handed to the other damping
    constants. At the motion's mean amplitude A/2 the held term's rate d_i (A/2)^i is split
    equally among the other terms j (d_j += d_i (A/2)^(i-j) / their number): where the others
    explain the same decay, which a refit from the fit's own values (where they may lie near
    0, far in the optimizer's log-coordinates) does not reach.

    Arguments:
        d_scale: d per unit of each constant at the fitted w0 (eq. 21).
        amplitude: the fitted initial amplitude A.
    Returns:
        {constant: start}, or None where nothing can take the decay over.
    """
    others = [o for o in others if o != name and d_scale.get(o, 0.0) > 0.0]
    if not others or not (amplitude > 0.0 and math.isfinite(amplitude)):
        return None
    a = 0.5 * amplitude
    rate = params[name] * d_scale[name] * a ** _POWER[name] / len(others)
    return {o: params[o] + rate / (a ** _POWER[o] * d_scale[o]) for o in others}


#: a damping constant below this fraction of its share of the decay sits at its bound for a
#: batch of starts around the fit: the batch's jitter (factors exp(1.5 z), exp(4.5) = 90 at
#: 3 sigma) does not reach its share from there (:func:`shared_start`)
AT_BOUND_SHARE = 1e-3


def shared_start(params, free, consts):
    """The centre of a batch of starts around a fit (``params``, TraceParams; ``consts``: its
    Constants) with each free damping constant that sits at its bound 0 (below
    :data:`AT_BOUND_SHARE` of its share) moved to an equal share of the decay rate that all of
    them give at the mean amplitude A/2 (the reverse of :func:`transferred_start`): a jitter
    around the fit's own values (factors of exp(1.5 z)) never leaves the bound in the
    optimizer's log coordinates (fit_calibration.py seed 22 draw 84: b at 4e-9 with D large, 67
    noise variances above the truth's cost)."""
    p = {k: float(v) for k, v in params._asdict().items()}
    a, scale = 0.5 * start_amplitude(p), d_per_unit(p["w0"], consts.m, consts.g)
    names = [n for n in free if n in DAMPING and scale[n] > 0.0]
    if len(names) < 2 or not (a > 0.0 and math.isfinite(a)):
        return params
    rate = sum(p[n] * scale[n] * a ** _POWER[n] for n in names) / len(names)
    share = {n: rate / (scale[n] * a ** _POWER[n]) for n in names}
    return params._replace(**{n: share[n] for n in names if p[n] < AT_BOUND_SHARE * share[n]})


def bound_tests(profile, fitted: Optimum, names, *, d_scale: dict | None = None,
                amplitude: float = math.nan) -> dict:
    """Wald against likelihood ratio at the bound: each damping constant of ``names`` whose
    interval excludes 0 at 10 % (value / sd > :data:`BOUND_Z`) is held at 0 and the others are
    fitted again (``profile(name, 0)``, from the fit's values, and where that rises beyond the
    test's point ``profile(name, 0, start, batch=True)``: a batch of starts around
    :func:`transferred_start`, as the fit's own, unless z > :data:`BATCH_Z` and the rise is
    near the quadratic's, :data:`QUADRATIC_SHARE` z^2 or more; the lower cost kept); the rise
    of the cost, in long-run noise variances (s2 (sd / stderr)^2: the intervals' own variance,
    which allows for correlated noise), is the likelihood-ratio chi2(1) of the same hypothesis.
    Where the model is linear in its parameters both tests agree (chi2 = z^2); a rise below
    chi2(1)'s 1 % point while the Wald z is beyond it means a valley in the cost: the others
    explain the constant's decay nearly as well, far outside the intervals
    (:func:`widening_toward` widens them to that point).

    Arguments:
        profile: ``profile(name, value, start=None, batch=False, values=False)`` -> the
            chi-square of the fit with that parameter held at that value (``values``: and
            {name: value} of that fit's varied parameters).
        fitted: the fit (its values, errors, interval sd, chi-square and s2).
        names: the damping constants to test.
        d_scale: d per unit of each constant at the fitted w0 (eq. 21; the transferred starts).
        amplitude: the fitted initial amplitude A.

    Returns:
        {name: (Wald z, likelihood-ratio chi2, {name: value} of the held fit)} for the
        constants tested.
    """
    params, stderr, sd, chisqr, s2 = fitted
    out = {}
    for name in names:
        v, s, se = params[name], sd.get(name, math.nan), stderr.get(name, math.nan)
        if not (math.isfinite(s) and s > 0 and math.isfinite(se) and se > 0):
            continue
        z = v / s
        if not z > BOUND_Z:
            continue
        unit = s2 * (s / se) ** 2
        c, point = profile(name, 0.0, values=True)
        start = transferred_start(name, params, names, d_scale or {}, amplitude)
        quadratic = z > BATCH_Z and (c - chisqr) / unit >= QUADRATIC_SHARE * z * z
        if start is not None and not (c - chisqr) / unit < LR_CHI2 and not quadratic:
            other, there = profile(name, 0.0, start, batch=True, values=True)
            if math.isfinite(other) and not other >= c:
                c, point = other, there
        if math.isfinite(c):
            out[name] = (z, (c - chisqr) / unit, point)
    return out


def widening_toward(fitted: Optimum, point: dict, chi2: float) -> dict:
    """The sides of the intervals widened to reach a point of the cost: ``point`` (a fit with
    one parameter held, the rest refitted) lies at likelihood-ratio ``chi2`` above the fit,
    so each of its values is inside that parameter's profile-likelihood interval at every
    level beyond chi2 (the profile is the lowest cost at that value: at most the point's).
    The normal interval value +- z sd reaches a value d away at level chi2 = z^2 only when
    |d| <= sqrt(chi2) sd; a side that falls short is widened by |d| / (sd sqrt(chi2)) (chi2
    at least :data:`WIDEN_FLOOR`): the rise taken as quadratic from the fit to the point, as
    :func:`profile_ratios` does for its sides. Where the cost is quadratic (the model linear
    in its parameters) no side is widened: the held fit's values then lie at |rho| sqrt(chi2)
    sd or less.

    Arguments:
        fitted: the fit (its values and interval sd).
        point: {name: value} of the held fit's parameters.
        chi2: its likelihood-ratio chi2 against the fit, in the intervals' noise variance.

    Returns:
        {name: (below, above)} factors of the sides widened (those above 1 only).
    """
    params, _, sd, _, _ = fitted
    out = {}
    for name, value in point.items():
        s = sd.get(name, math.nan)
        if not (name in params and math.isfinite(s) and s > 0 and math.isfinite(value)):
            continue
        d = value - params[name]
        w = abs(d) / (s * math.sqrt(max(chi2, WIDEN_FLOOR)))
        if w > 1.0 + 1e-9:  # (the held parameter itself on a quadratic cost: 1 to rounding)
            out[name] = (w, 1.0) if d < 0 else (1.0, w)
    return out


def widen(scale: dict, fitted: Optimum, points) -> None:
    """``scale`` ({name: (below, above)}, updated in place) widened to reach each of
    ``points`` ((likelihood-ratio chi2, {name: value}) of held fits: :func:`widening_toward`),
    the larger factor of each side kept."""
    for chi2, point in points:
        for name, w in widening_toward(fitted, point, chi2).items():
            old = scale.get(name, (1.0, 1.0))
            scale[name] = (max(old[0], w[0]), max(old[1], w[1]))


def bound_verdict(lr: dict, fitted: Optimum, scale: dict) -> tuple[str, str]:
    """The tests at the bound (:func:`bound_tests`' ``lr``) read: a held fit with a lower
    cost than the fit's is a local optimum (the failure); one whose cost rises by less than
    :data:`LR_CHI2` is a valley toward the bound, and every interval is widened to reach its
    values (:func:`widening_toward`, into ``scale``: {name: (below, above)}, updated in
    place) with a note.

    Returns:
        (failure, note): one-line texts, "" where none.
    """
    weak = sorted((c, k, z, p) for k, (z, c, p) in lr.items() if c < LR_CHI2)
    if not weak:
        return "", ""
    c, k, z, _ = weak[0]
    if not c > 0.0:
        return (f"a local optimum: with {k} held at 0 and the rest refitted the cost is lower "
                f"(likelihood-ratio chi2 {c:.2g})"), ""
    before = dict(scale)
    widen(scale, fitted, [(chi2, point) for chi2, _, _, point in weak])
    if not any(w[2] > LR_Z for w in weak):  # each 99 % interval reaches 0: no valley there
        return "", "" if scale == before else (
            f"with {k} held at 0 (inside its 99 % interval) and the rest refitted the others "
            f"move beyond their intervals at a likelihood-ratio chi2 of {c:.2g}; the intervals "
            "are widened to reach that fit's values (profile likelihood)")
    c, k, z, _ = next(w for w in weak if w[2] > LR_Z)
    return "", (f"{k} is weakly separated from the other damping terms: its normal interval "
                f"excluded 0 by {z:.2g} sd, but with {k} held at 0 and the rest refitted the "
                f"cost rises by a likelihood-ratio chi2 of only {c:.2g} (< {LR_CHI2:.2f}, 1 %); "
                "the intervals are widened to reach that fit's values (profile likelihood)")


def profile_side(rise, d0: float, c0: float, *, limit: float = math.inf) -> float:
    """Where a side of an interval ends, for a cost that is not near a quadratic: ``rise(d)``
    is the profile's rise at distance d from the value over the rise the interval assumes
    (c0 = rise(d0)); from c0 < :data:`PROFILE_MEASURE` the side is followed out to the point
    where the rise reaches 1: each next distance from the power law through the last two
    points (a quadratic from the first), at most :data:`PROFILE_REACH` d0, and once the point
    is bracketed, interpolated by that power law (at most :data:`PROFILE_EVALS` profile fits;
    exact for rise = c d^p).

    Arguments:
        limit: the distance to the parameter's bound (0 for a damping constant): a side whose
            rise stays below 1 up to there reaches the bound.
    Returns:
        the effective c = (d0 / d_bound)^2 of the side (1/c^(1/2) is its widening);
        c0 where c0 >= PROFILE_MEASURE; 0 where the bound lies beyond the reach.
    """
    if not (math.isfinite(c0) and c0 < PROFILE_MEASURE):
        return c0
    reach = min(PROFILE_REACH * d0, limit)
    lo, hi = (d0, c0), None  # the farthest point below 1, the nearest at or above 1

    def power_law(p1, p2, target=1.0):  # the d where the power law through both is target
        (d1, c1), (d2, c2) = p1, p2
        if c1 > 0 and c2 > 0 and c1 != c2 and d1 != d2:
            p = min(max(math.log(c2 / c1) / math.log(d2 / d1), 0.5), 4.0)
            return d2 * (target / c2) ** (1.0 / p)
        return None

    prev = None
    for _ in range(PROFILE_EVALS):
        if hi is not None:
            d = power_law(lo, hi)
            d = 0.5 * (lo[0] + hi[0]) if d is None or not lo[0] < d < hi[0] else d
        else:
            d = power_law(prev, lo) if prev is not None else None
            if d is None:
                d = lo[0] / math.sqrt(lo[1]) if lo[1] > 0 else 4.0 * lo[0]
            d = min(max(d, 1.25 * lo[0]), reach)
        c = rise(d)
        if not math.isfinite(c):
            break
        if abs(c - 1.0) < 0.05:
            return (d0 / d) ** 2
        if c >= 1.0:
            hi = (d, c)
        else:
            prev, lo = lo, (d, c)
            if d >= reach and hi is None:
                break
    if hi is not None:  # the bracket's power-law point
        d = power_law(lo, hi)
        d = 0.5 * (lo[0] + hi[0]) if d is None or not lo[0] <= d <= hi[0] else d
        return (d0 / d) ** 2
    if lo[0] >= limit:  # the side reaches the parameter's bound (its interval is clipped)
        return (d0 / limit) ** 2
    return 0.0


def profile_ratios(profile, fitted: Optimum, names, z: float = 2.0) -> dict:
    """The intervals against the cost itself: each parameter of ``names`` is held at its
    value -+ z interval sd and the others are fitted again (``profile(name, value)`` returns
    that fit's chi-square); the rise of the cost over the rise the intervals assume (z^2
    times (sd / stderr)^2 noise variances) is 1 where the model is linear in its parameters.
    A side that rises less than :data:`PROFILE_MEASURE` is followed out
    (:func:`profile_side`): its value is then the effective ratio of where it ends.

    Arguments:
        profile: ``profile(name, value)`` -> the chi-square of the fit with that parameter held
            at that value.
        fitted: the fit (its values, errors, interval sd, chi-square and s2).
        names: the parameters to profile.
        z: the distance of the profile's points, in interval sd.

    Returns:
        {name: (ratio below, ratio above)} (NaN where a side leaves the allowed range).
    """
    params, stderr, sd, chisqr, s2 = fitted
    out = {}
    for name in names:
        v, s, se = params[name], sd.get(name, math.nan), stderr.get(name, math.nan)
        if not (math.isfinite(s) and s > 0 and math.isfinite(se) and se > 0):
            continue
        pred = z * z * (s / se) ** 2 * s2
        sides = []
        for sgn in (-1.0, 1.0):
            limit = v if (sgn < 0 and name in ("mu", "b", "D", "w0")) else math.inf

            def rise(d, sgn=sgn, limit=limit, name=name, v=v, pred=pred):
                c = profile(name, v + sgn * d) if d < limit else profile(name, 0.0)
                return (c - chisqr) / pred if math.isfinite(c) else math.nan

            if z * s >= limit:
                sides.append(math.nan)
                continue
            sides.append(profile_side(rise, z * s, rise(z * s), limit=limit))
        out[name] = tuple(sides)
    return out


#: held fits at most spent following mu's profile out past a motion that halts at another
#: turning point and fits nearly as well (:func:`followed_out`), each FOLLOW_GROWTH times
#: farther from the fit's mu than the farthest one below the 1 % point
FOLLOW_EVALS, FOLLOW_GROWTH = 4, 1.5


def other_halt_check(res, others: dict, follow=None):
    """Weigh the motions that halt at a neighbouring turning point against a fit's intervals
    (``_halts.search_other_halts``): with mu held at each value of ``others`` and the rest
    refitted (its cost, whether that motion halts at its first turning point:
    ``_halts.first_halt``, and its values), the likelihood-ratio chi2 against the fit, in the
    intervals' own noise variance (s2 (sd/stderr)^2, as :func:`bound_tests`). One below
    :data:`LR_CHI2` (1 %) with mu more than :data:`LR_Z` interval sd away lies inside mu's
    99 % profile-likelihood set but outside the linearised interval: where ``follow`` (mu ->
    a held fit: ``_halts.mu_profile``) is given, the profile is followed out past it
    (:func:`followed_out`) and, where a held fit beyond rises above the 1 % point (or mu
    reaches 0), the intervals are widened to reach every held fit below it (profile
    likelihood, :func:`widening_toward`; a success with a note). Otherwise (no ``follow``,
    a lower cost, a profile still below the 1 % point after :data:`FOLLOW_EVALS` held fits,
    or a first halt above mu: every larger mu fits as well) the data hold two answers and
    the fit fails. (Widening to the other motion alone was tried: the cost jumps from one
    halt to the next, so the rise up to it says nothing of the motions beyond; on
    fit_calibration.py it made draw 134 of seed 0 and draw 30 of seed 22 confident wrong
    answers.) Where the first-halt side's held fits rise by more (no halt changes between
    the fit and them), the intervals are widened to the nearest
    (:func:`widened_to_first_halts`)."""

    sd, se = res.hac_stderr.get("mu", math.nan), res.stderr.get("mu", math.nan)
    if not (math.isfinite(sd) and sd > 0 and math.isfinite(se) and se > 0):
        return res
    unit = float(res.chisqr) / max(res.ndata - res.nvarys, 1) * (sd / se) ** 2
    mu = float(res.params["mu"])
    rises = {m: ((cost - float(res.chisqr)) / unit, first, point)
             for m, (cost, first, point) in others.items()}

    def held(m: float, near: dict):  # a held fit's (chi2, first halt, values)
        cost, first, point = follow(m, near)
        return (cost - float(res.chisqr)) / unit, first, point

    bounded = follow is not None and followed_out(rises, mu, sd, held)
    flat = []  # the first-halt side: (rise, the held fit's values)
    for mu_alt, (rise, first, point) in rises.items():
        unbounded = first and mu_alt > mu  # every mu above fits as well (first_halt)
        if not (unbounded or abs(mu_alt - mu) > LR_Z * sd):
            continue
        if unbounded and rise >= LR_CHI2:
            flat.append((mu_alt, rise, point))
        if rise < LR_CHI2 and not bounded:
            reason = (f"two motions fit nearly as well: this one and one that halts at another "
                      f"turning point with mu = {mu_alt:.4g} ({abs(mu_alt - mu) / sd:.0f} "
                      f"interval sd away; likelihood-ratio chi2 {rise:.2g} < {LR_CHI2:.2f}): "
                      "where the block sticks does not settle mu; fit a longer record or fix "
                      "the offset")
            if unbounded:
                reason = (f"the data bound mu only from below: a motion that halts at its first "
                          f"turning point with mu = {mu_alt:.4g} fits nearly as well "
                          f"(likelihood-ratio chi2 {rise:.2g} < {LR_CHI2:.2f}), and so does "
                          "every larger mu (over one swing friction only moves the centre, "
                          "which the offset takes up); fix the offset or fit a record with "
                          "more swings")
            return dataclasses.replace(res, success=False, reason=reason,
                                       diagnostics={**res.diagnostics,
                                                    "other_halt_mu": mu_alt,
                                                    "other_halt_chi2": rise})
    if bounded:
        res = widened_to_profile(res, rises)
    return widened_to_first_halts(res, [p[1:] for p in sorted(flat)[:1]])


def followed_out(rises: dict, mu: float, sd: float, follow) -> bool:
    """mu's profile followed out past the held fits of :func:`other_halt_check` below the 1 %
    point with mu more than :data:`LR_Z` interval sd away: on each such side, a held fit
    FOLLOW_GROWTH times farther than the farthest one below :data:`LR_CHI2` (started from its
    values too), until one of them beyond it rises above (or mu reaches 0, its bound). On
    the calibration family's false failures of the check the profile rises smoothly through
    the neighbouring halt (seed 23 draw 70: chi2 1.9, 4.1, 7.3 at 2.7, 3.6, 4.5 sd, the halt
    at 4.0) or stays flat far beyond it (seed 22 draw 88: 0.2 from 0.5 to 6.4 sd, the truth
    at 4.9).

    Arguments:
        rises: {mu: (likelihood-ratio chi2, first halt, values)}; the followed fits are added.
        mu, sd: the fit's mu and its interval sd.
        follow: (mu, values of a held fit to start from) -> (chi2, first halt, values) of a
            fit with mu held there.

    Returns:
        Whether every such side is bounded within :data:`FOLLOW_EVALS` held fits, with no
        held fit below the fit's cost and no first halt above mu among those below the 1 %
        point (then the data hold two answers: False).
    """
    def below(r, m):
        return r[0] < LR_CHI2 and not (r[0] < 0.0 or (r[1] and m > mu))

    near = [m for m, r in rises.items() if r[0] < LR_CHI2 and abs(m - mu) > LR_Z * sd]
    if not near or not all(below(rises[m], m) for m in near):
        return False
    followed = set()  # the held fits that bound a side (a fit of the search above the 1 %
    # point bounds the profile only from above: seed 0 draw 134's at 14 sd, 216 up, the
    # profile there 4)
    for side in {math.copysign(1.0, m - mu) for m in near}:
        while True:
            on = {m: r for m, r in rises.items() if (m - mu) * side > 0.0}
            far = max((m for m, r in on.items() if r[0] < LR_CHI2), key=lambda m: abs(m - mu))
            if far <= 0.0 or any(abs(m - mu) > abs(far - mu) and on[m][0] >= LR_CHI2
                                 for m in followed & set(on)):
                break
            if len(followed) == FOLLOW_EVALS:
                return False
            nxt = max(mu + (far - mu) * FOLLOW_GROWTH, 0.0)
            rises[nxt] = follow(nxt, rises[far][2])
            followed.add(nxt)
            if rises[nxt][0] < LR_CHI2 and not below(rises[nxt], nxt):
                return False
    return True


def widened_to_profile(res, rises: dict):
    """The intervals widened to reach every held fit of mu's followed profile below the 1 %
    point (:func:`followed_out`; :func:`widening_toward` at each one's chi2), with a note (a
    held fit below it more than LR_Z sd away always widens mu's side)."""
    reach = [m for m, r in rises.items() if r[0] < LR_CHI2]
    return _widened(res, [(rises[m][0], rises[m][2]) for m in reach], "note_other_halt", (
        f"a motion that halts at another turning point fits nearly as well: mu's profile was "
        f"followed past it (held fits from mu = {min(reach):.4g} to {max(reach):.4g} lie below "
        "the 1 % point, one beyond rises above it), and the intervals are widened to reach "
        "them (profile likelihood)"))


def widened_to_first_halts(res, points):
    """The intervals widened to reach the held fits of the first-halt side of mu
    (``points``: (likelihood-ratio chi2, {name: value})), as ``_profile.bound_verdict`` does
    for a valley toward the bound (``_profile.widen``): above the threshold of the
    first halt the motion and its halt stay the same, so mu's profile is continuous there and
    flat or nearly (the offset takes up the centre that friction moves; only k3 or the motion
    before the first turning point tells them apart), far from the quadratic of the
    linearised intervals (wide draw 41 at 2,000 samples: the truth 26 interval sd above
    mu at a rise below 6; the held fit at 1.05 mu 6.8). Each held fit's values lie inside the
    profile-likelihood intervals at every level beyond its chi2; the nearest one is taken
    (the profile between the fit and it interpolated as a quadratic, as in
    ``_profile.profile_ratios``: a farther one, at a larger chi2, speaks of levels beyond
    it, and the profile up to it is not quadratic)."""
    return _widened(res, points, "note_first_halt", (
        "the motion halts at or near its first turning point, where friction only moves the "
        "centre (taken up by the offset): mu's profile above is nearly flat, and the intervals "
        "are widened to reach the fits with mu held there (profile likelihood)"))


def _widened(res, points, key: str, note: str):
    """``res`` with its intervals widened to reach ``points`` ((likelihood-ratio chi2,
    {name: value}) of held fits: :func:`widen`) and ``note`` under ``diagnostics[key]``;
    ``res`` itself where no side widens."""
    fitted = Optimum(res.params, res.stderr, res.hac_stderr, float(res.chisqr), math.nan)
    scale = {k: tuple(v) for k, v in res.diagnostics.get("interval_scale", {}).items()}
    widen(scale, fitted, points)
    if scale == res.diagnostics.get("interval_scale", {}):
        return res
    return dataclasses.replace(res, diagnostics={**res.diagnostics, "interval_scale": scale,
                                                 key: note})
