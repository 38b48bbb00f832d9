"""The assessment of a finished fit as a table of checks (issue 33): each check a function of
what the fit shows (:class:`Inputs`) and of what the checks before it found, returning a
:class:`Finding`; :func:`assess` runs :data:`FIRST`, then :data:`CHECKS` on the residuals'
:class:`Measures`, in the order listed there, and builds the verdict from their findings
(failures, inadequacies, the numbers measured). The statistics behind each are described in
``_checks`` (tests whose null distribution is known, no tuned thresholds).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from ._analysis import Analysis
from ._checks import (
    END_P,
    STRUCTURE_P,
    end_mismatch,
    interval_sd,
    model_end,
    newton_step,
    null_directions,
    phase_drift,
)
from ._dist import chi2_isf, norm_ppf
from ._intervals import ar1_coefficient
from ._measures import (
    SETTLE_RTOL,
    Finding,
    Measures,
    Verdict,
    gross_ends,
    level_text,
    measures,
    settled_starts,
    settles,
    structure_text,
    worst_swing,
)
from ._params import start_amplitude
from ._profile import (
    PROFILE_FAIL,
    PROFILE_REACH,
    Optimum,
    bound_tests,
    bound_verdict,
    profile_ratios,
)
from ._text import NO_FREQUENCY, time_span

#: a damping ratio above this is absurd for a trace that oscillates (d0/(w0 A), d1/w0, d2 A/w0)
ABSURD = 10.0
#: the model is inadequate when its residuals hold structure (:data:`STRUCTURE_P`) and their
#: rms exceeds this fraction of the first amplitude (a tolerance of the description, not a
#: test: the residuals of a model that misses 5 % of the swing are seen by eye)
RMS_AMPLITUDE = 0.05
#: a gross mismatch of the motion ends whatever the noise: the swings above a fiftieth of the
#: amplitude end this many periods (or a tenth of the window) apart
END_PERIODS = 4.0
#: a fit that ran out of optimizer steps counts as converged when one more Gauss-Newton step
#: would move no parameter by more than sqrt(this) = 0.3 sd of its interval (for a trace; of
#: its delta-method standard error otherwise, where the decrement in noise variances bounds
#: it), which keeps a 90 % interval's coverage above 87.7 %
NEWTON_TOL = 0.09


class Inputs(NamedTuple):
    """What a finished fit shows (``_result.build_result`` makes it).

    Attributes:
        t, x, curve: the fitted window and the model on it.
        params, stderr, varied, derived: of the fit (``derived`` holds d0, d1, d2, A).
        an: the ``Analysis`` of the window (noise, turning points, where the data stop).
        converged: the optimizer converged; ``message``: its message; ``capped``: it stopped
            at its step budget (not on a failure).
        kind, model: "trace" (every check) or "envelope"; the fit model ("reference": eq. 3).
        jac, rows: the Jacobian (physical parameters) and residuals of the data rows.
        profile: ``profile(name, value, start=None, batch=False)`` -> the chi-square of the
            fit with that parameter held at that value (None: skipped); ``chisqr``: the fit's.
        d_scale: d per unit of mu, b, D at the fitted w0 (eq. 21; the tests at the bound).
        search: the batch of starts whose costs tell a local optimum from a model that lacks
            something (``_starts.Starts``; None: none ran).
        exact: the residuals are eq. 3's (an approximate model that answers for the exact
            one, ``_answer``): structure in them is judged as the exact model's.
    """

    t: np.ndarray
    x: np.ndarray
    curve: np.ndarray
    params: dict
    stderr: dict
    varied: tuple
    derived: dict
    an: Analysis
    converged: bool
    message: str
    kind: str = "trace"
    model: str = "ansatz"
    jac: object = None
    rows: object = None
    capped: bool = False
    profile: Callable | None = None
    chisqr: float = math.nan
    d_scale: dict | None = None
    search: object = None
    exact: bool = False


def _damping(a: Inputs) -> tuple[list, list]:
    """(the fitted damping constants, the held ones that are > 0)."""
    damping = [n for n in ("mu", "b", "D") if n in a.varied]
    held = [n for n in ("mu", "b", "D") if n not in a.varied and a.params.get(n, 0.0) > 0.0]
    return damping, held


def step_budget(a: Inputs, v: Verdict) -> Finding:
    """A fit that ran out of steps on a flat valley counts as converged: one more Gauss-Newton
    step would move no parameter by more than sqrt(:data:`NEWTON_TOL`) interval sd."""
    if a.converged or not a.capped or a.jac is None or a.rows is None:
        return Finding()
    names = list(a.varied)
    dec, step = newton_step(a.jac, a.rows, [a.params[n] for n in names], names)
    diag = {"newton_decrement": dec}
    # how far the parameters would still move: sqrt(decrement) bounds it in delta-method
    # standard errors; for a trace, in the sd of the intervals themselves (HAC: what
    # conf_interval reports, and what the coverage depends on)
    move, unit = math.sqrt(max(dec, 0.0)), "standard errors"
    sd_move = interval_sd(a.jac, a.rows, a.params, a.t) if a.kind == "trace" else None
    if step is not None and sd_move is not None and np.all(sd_move > 0):
        move, unit = float(np.max(np.abs(step) / sd_move)), "interval sd"
        diag["newton_move_sd"] = move
    if move * move <= NEWTON_TOL:
        diag["note_steps"] = (f"the step budget ran out on a flat valley: one more "
                              f"Gauss-Newton step would lower the cost by {dec:.2g} noise "
                              "variances (the parameters would move by less than "
                              f"{move:.2g} {unit})")
    return Finding(diag=diag)


def convergence(a: Inputs, v: Verdict) -> Finding:
    """The optimizer converged (or the step budget's note says it as good as did)."""
    if a.converged or v.converged:
        return Finding()
    return Finding(fails=(f"the optimizer did not converge ({a.message})",))


def finite(a: Inputs, v: Verdict) -> Finding:
    """Finite fitted parameters and a finite model on the window; else nothing more can be
    judged."""
    if not all(math.isfinite(a.params.get(n, math.nan)) for n in a.varied):
        fails = ("the fitted parameters are not finite",) if a.converged or v.converged else ()
        return Finding(fails=fails, bad=("the fit produced no finite model",), stop=True)
    if a.curve is not None and not np.all(np.isfinite(np.asarray(a.curve, dtype=float))):
        return Finding(fails=("the model is not finite on the window at the fitted values (the "
                              "integration failed there)",),
                       bad=("the fit produced no finite model",), stop=True)
    return Finding()


def degeneracy(a: Inputs, v: Verdict) -> Finding:
    """Exact degeneracies (:func:`null_directions`): the split is not determined."""
    null = null_directions(a.jac, list(a.varied))
    if not null:
        return Finding()
    diag = {"null_space": null}
    group = [n for n in ("mu", "b", "D", "w0") if n in null[0]]
    others = [n for n in null[0] if n not in group]
    if others:  # the offset first: what Coulomb friction trades with over one swing
        group.append("offset" if "offset" in others else others[0])
    if len(group) >= 2:
        turns = a.an.n_turns
        diag["unidentifiable"] = (
            f"{', '.join(group[:-1])} and {group[-1]} are not separately identifiable "
            f"from this window ({turns} turning point{'s' if turns != 1 else ''}"
            "): the Jacobian of the fit is singular, their effects on the trace cancel "
            "exactly (over a single swing Coulomb friction only moves its centre); fix all "
            "but one of them (damping constants in the oscillator, the offset with "
            "offset=False and p0={'offset': ...}) or fit a longer record")
    return Finding(diag=diag)


def standard_errors(a: Inputs, v: Verdict) -> Finding:
    """Finite standard errors of every varied parameter and intervals of positive width (a
    variance <= 0, clipped to 0, is a numerically singular Jacobian's, not a parameter the data
    pin down: a quarter-swing window had zero-width intervals, fit_calibration.py seed 2); w0's
    99 % interval above 0 (wide seed 11 draw 54, 1.7 half swings: w0 1.99 +- 45 rad/s against
    7.0, mu 16 sd off, was a success: the others' intervals, linear over w0's, do not hold)."""
    bad = [n for n in a.varied if not math.isfinite(a.stderr.get(n, math.nan))]
    sd = interval_sd(a.jac, a.rows, a.params, a.t) if not bad and a.kind == "trace" and \
        a.jac is not None and a.rows is not None else None
    sd = {} if sd is None else dict(zip(a.varied, sd, strict=True))
    w0, reach = a.params.get("w0", math.nan), norm_ppf(0.995) * sd.get("w0", 0.0)
    return Finding(fails=tuple(f"the {what} of {', '.join(names)} {why}" for what, names, why in (
        ("standard error", bad, "is not finite (not determined by the data)"),
        ("interval", [n for n, s in sd.items() if not s > 0], "has no width: the Jacobian is "
         "numerically singular (not determined by the data)"),
        ("99 % interval", [f"w0 = {w0:.4g} +- {reach:.2g} rad/s"] if w0 <= reach else [],
         f"reaches 0: {NO_FREQUENCY}, and the other constants' "
         "intervals do not hold either; give the stiffness (the oscillator's k) or fit a "
         "record with more swings")) if names))


def envelope_decay(a: Inputs, v: Verdict) -> Finding:
    """An envelope fit's decay note; its checks end here."""
    if a.kind == "trace":
        return Finding()
    damping, held = _damping(a)
    diag = {}
    if damping and not held and \
            all(not a.params[n] > 2.0 * a.stderr.get(n, math.nan) for n in damping):
        # (a decay that held constants explain is measured by them; a note, not a failure:
        # the values and their intervals, which reach 0, are the right answer)
        diag["note_decay"] = (f"no measurable decay: every fitted damping constant "
                              f"({', '.join(damping)}) is consistent with zero (the intervals "
                              "are upper bounds)")
    return Finding(diag=diag, stop=True)


def amplitude(a: Inputs, v: Verdict) -> Finding:
    """A positive finite amplitude and frequency; else nothing more can be judged."""
    A, w0 = a.derived.get("A", math.nan), a.params["w0"]
    if math.isfinite(A) and A > 0 and math.isfinite(w0) and w0 > 0:
        return Finding()
    return Finding(fails=("the fitted amplitude or frequency is not a positive finite number",),
                   stop=True)


def _motion_amplitude(a: Inputs) -> float:
    """The exact model's start's own amplitude, hypot(x0, v0/w0), else the model's A."""
    exact = a.model == "reference" and math.isfinite(a.params.get("v0", math.nan))
    return start_amplitude(a.params) if exact else a.derived["A"]


def absurd(a: Inputs, v: Verdict) -> Finding:
    """Damping ratios above :data:`ABSURD`, or an amplitude far beyond the data's range, of
    :func:`_motion_amplitude`: the ansatz matched to a start under strong drag has one many
    times the motion's (14.6x on a wide draw, d2 A0/w0 = 1.1: it failed, the truth inside)."""
    w0, A = a.params["w0"], _motion_amplitude(a)
    d = a.derived
    ratios = {"d0/(w0 A)": d["d0"] / (w0 * A), "d1/w0": d["d1"] / w0, "d2 A/w0": d["d2"] * A / w0}
    span_x = float(np.ptp(a.x))
    bad = [f"{k} = {x:.3g}" for k, x in ratios.items() if not x <= ABSURD]
    if bad or A > 100.0 * span_x:
        what = ", ".join(bad) if bad else f"A = {A:.3g} vs data range {span_x:.3g}"
        return Finding(fails=(f"a parameter ran to absurd values ({what})",), diag=ratios)
    return Finding(diag=ratios)


def residual_size(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """The residuals' rms against the noise and the amplitude (numbers only)."""
    noise, A = a.an.noise, a.derived["A"]
    diag = {"noise": noise, "rms": m.rms, "rms/noise": m.rms / noise if noise > 0 else math.inf,
            "rms/A": m.rms / A}
    if math.isfinite(a.an.omega) and a.an.omega > 0:
        diag["w0/turning - 1"] = a.params["w0"] / a.an.omega - 1.0
    return Finding(diag=diag)


def _wald(a: Inputs, m: Measures, group: list) -> float:
    """Wald chi2 of ``group`` against 0, x^T pinv(C) x >= 0; NaN without a finite C."""
    idx = [list(a.varied).index(n) for n in group]
    if m.cov is None or not np.all(np.isfinite(cov := m.cov[np.ix_(idx, idx)])):
        return math.nan
    x = np.array([a.params[n] for n in group])
    return max(float(x @ np.linalg.pinv(cov) @ x), 0.0)


def decay(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """No measurable decay: the fitted damping constants together consistent with zero (the
    Wald test with the intervals' covariance does not reject at 5 %): a note."""
    damping, held = _damping(a)
    if not damping or held:
        return Finding()
    wald = _wald(a, m, damping)
    if math.isnan(wald):  # no covariance: the standard errors alone
        x, se = (np.array([d.get(n, math.nan) for n in damping]) for d in (a.params, a.stderr))
        wald = float(np.sum((x / se) ** 2)) if np.all(se > 0) else math.nan
    diag = {"decay_wald": wald}
    if not wald > chi2_isf(0.05, len(damping)):
        # a note: the data bound the decay (intervals that reach 0), they do not fail
        diag["note_decay"] = (f"no measurable decay: the fitted damping constants "
                              f"({', '.join(damping)}) are together consistent with zero "
                              f"(Wald chi2 = {wald:.3g}, {len(damping)} dof; the "
                              "intervals are upper bounds)")
    return Finding(diag=diag)


def split(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """The split between the damping terms: a group measured together (Wald at 1 %) of which
    none is measured alone (each within 1.96 sd of zero) is not identifiable."""
    damping, _ = _damping(a)
    if m.cov is None or len(damping) < 2 or not np.all(np.isfinite(m.cov)):
        return Finding()
    weak = [n for n in damping if m.sd.get(n, 0.0) > 0 and abs(a.params[n] / m.sd[n]) < 1.96]
    if len(weak) < 2:
        return Finding()
    diag = {"split_wald": (wald := _wald(a, m, weak))}
    if wald > chi2_isf(0.01, len(weak)):
        turns = a.an.n_turns
        diag["unidentifiable"] = (
            f"{', '.join(weak[:-1])} and {weak[-1]} are not separately identifiable "
            f"from this window ({turns} turning point{'s' if turns != 1 else ''}): "
            f"together they are measured (Wald chi2 = {wald:.3g}), none of them alone "
            "(each within 1.96 sd of zero); fix all but one of them (pass their "
            "values in the oscillator) or fit a longer record" + level_text(a, m))
    return Finding(diag=diag)


def structure(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """The residuals against AR(1) noise (numbers; the verdicts follow)."""
    return Finding(diag={"residual_phi": m.st["phi"], "residual_p": m.st["p"],
                         "residual_blocks": m.st["blocks"]})


#: residuals correlated over more than this many periods (AR(1) phi about their mean) and
#: above WANDER_SHARE of the motion's amplitude wander (a random walk was adequate: AR(1) of
#: phi 0.996 took it); the families' noise stays 5x below (benchmarks/README.md)
WANDER_PERIODS, WANDER_SHARE = 1.0, 0.5


def wander(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """Residuals that wander slowly and as large as the motion: inadequate, named."""
    phi = ar1_coefficient(m.r - np.mean(m.r), clip=(-0.99, 1.0))  # (the test clips at 0.99)
    dt, A = float(np.median(np.diff(a.t))), _motion_amplitude(a)
    periods = -dt / math.log(phi) / m.period if 0.0 < phi < 1.0 else math.inf  # (phi 1: inf)
    if not (phi > 0.0 and periods > WANDER_PERIODS and m.rms > WANDER_SHARE * A):
        return Finding()
    return Finding(bad=(f"the residuals wander: correlated over {periods:.3g} periods (AR(1) "
                        f"phi = {phi:.4f}) with an rms of {m.rms:.3g}, {100 * m.rms / A:.0f} % "
                        "of the fitted motion's amplitude: a moving level or a motion the "
                        "model lacks (a random walk?), not noise",))


def _gross_end(a: Inputs, m: Measures) -> Finding:
    """A gross mismatch of the motion ends whatever the noise (``_measures.gross_ends``): the
    model's halt and the end of the data's swings above max(6 noise, A/50) are
    :data:`END_PERIODS` periods or a tenth of the window apart."""
    gross_m, gross_d, tol = gross_ends(a.t, a.x, a.curve, m.r, m.period, (
        a.an.noise, a.derived["A"], m.st["p"] < STRUCTURE_P), END_PERIODS)
    if gross_m < gross_d - tol:
        msg = (f"the model stops moving at t = {gross_m:.5g} s, well before the data "
               f"(t = {gross_d:.5g} s)")
    elif gross_m > gross_d + tol:
        msg = (f"the model still moves at t = {gross_m:.5g} s, well after the data stop "
               f"(t = {gross_d:.5g} s)")
    else:
        return Finding()
    return Finding(fails=(msg,), bad=(msg,))


def _stands(a: Inputs, m: Measures) -> bool:
    """Eq. 3's structured residuals at an optimum its search of starts settled on: no start
    found a lower cost, so the residuals hold what eq. 3 lacks (issue 36, item 4)."""
    return bool(m.st["p"] < STRUCTURE_P and (a.model == "reference" or a.exact) and
                settles(a.search))


def motion_ends(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """Where the model halts against where the data stop: the residuals between the two ends
    against those elsewhere (:func:`end_mismatch`), else a gross mismatch. Where eq. 3's
    optimum stands (:func:`_stands`), a mismatch is what it lacks: inadequate, not failed
    (the 100 deg torsion release, whose frequency follows its amplitude)."""
    end_m = model_end(a.t, a.curve)
    end_d = a.an.end_t if a.an.halted else float(a.t[-1])
    p_end = end_mismatch(a.t, m.r, end_m, end_d, m.st["phi"])
    diag = {"end_model": end_m, "end_data": end_d, "end_p": p_end}
    found = Finding(diag=diag)
    if p_end < END_P:
        msg = (f"the model stops moving at t = {end_m:.5g} s, before the data (t = {end_d:.5g} "
               "s)" if end_m < end_d else
               f"the model still moves at t = {end_m:.5g} s, after the data stop "
               f"(t = {end_d:.5g} s)")
        found = Finding(fails=(msg + f": the residuals between are beyond the noise "
                               f"(p = {p_end:.1g})",), bad=(msg,), diag=diag)
    elif end_m < float(a.t[-1]) - 0.5 * m.period:
        found = _gross_end(a, m)._replace(diag=diag)
    if found.fails and _stands(a, m):
        return found._replace(fails=(), bad=tuple(
            f"{b} (the optimum stands: the exact model's starts found no lower cost)"
            for b in found.bad))
    return found


def exact_structure(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """Eq. 3 integrated exactly: structure the noise cannot produce is a local optimum or
    physics that eq. 3 lacks. The fit's own search of the exact model's starts (``a.search``,
    run where the first exact fit looked stuck) tells them apart: where its starts found no
    lower cost and settled on this optimum (:func:`settled_starts`), the optimum stands (a
    success) and the model is inadequate, the structure named; where no search ran, or it did
    not settle (its starts spread over other costs), the fit fails as a possible local
    optimum."""
    if not (m.st["p"] < STRUCTURE_P and (a.model == "reference" or a.exact)):
        return Finding()
    where = structure_text(a, m)
    search = a.search
    settled = 0 if search is None else settled_starts(search.costs)
    if _stands(a, m):
        return Finding(bad=(f"the residuals hold structure that eq. 3 with these terms lacks "
                            f"({where}): {search.n} starts found no lower cost, {settled} "
                            f"settled within {100 * SETTLE_RTOL:g} % of it",))
    why = ("no search of the exact model ran (starts=1)" if search is None else
           f"of {search.n} starts of the exact model {settled} settled within "
           f"{100 * SETTLE_RTOL:g} % of the best cost")
    return Finding(fails=(f"the residuals are not noise ({where}): a local optimum, or the data "
                          f"hold what eq. 3 lacks; {why}",),
                   bad=(f"the residuals hold structure beyond the noise ({where})",))


def size(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """An approximate model's structured residuals above :data:`RMS_AMPLITUDE` of the
    amplitude: inadequate, with the half swing where they are largest (the exact model's
    structure is :func:`exact_structure`'s)."""
    A, noise = a.derived["A"], a.an.noise
    if not (m.st["p"] < STRUCTURE_P and m.rms > RMS_AMPLITUDE * A) or a.model == "reference" \
            or a.exact:
        return Finding()
    lo, hi, rms = worst_swing(a, m)
    return Finding(bad=(f"the residuals (rms {m.rms:.3g}) are {v.diag['rms/noise']:.0f} times "
                        f"the noise level of the data ({noise:.3g}) and "
                        f"{100 * m.rms / A:.1f} % of the amplitude (largest in the swing at "
                        f"t = {time_span(lo, hi)}: rms {rms:.3g})",))


def drift(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """The phase drift; with structured residuals of an approximate model, a note."""
    A, noise = a.derived["A"], a.an.noise
    value = phase_drift(a.t, a.x, a.curve, a.params["w0"], a.params.get("offset", 0.0),
                        max(6.0 * noise, 0.02 * A))
    diag = {"phase_drift": value}
    if m.st["p"] < STRUCTURE_P and a.model != "reference":
        diag["note"] = (f"the residuals hold structure beyond the noise (p = {m.st['p']:.1g}; "
                        f"phase drift {value:.2f} rad, rms {v.diag['rms/noise']:.0f} times the "
                        "noise): the delta-method stderr understate the uncertainty; use "
                        "conf_interval(), which allows for it")
    return Finding(diag=diag)


def intervals(a: Inputs, m: Measures, v: Verdict) -> Finding:
    """The intervals against the cost, where the residuals are noise and nothing failed:
    profiles of the damping constants (and w0), then the tests at the bound."""
    if a.profile is None or not m.sd or v.fails or m.st["p"] < STRUCTURE_P or \
            "unidentifiable" in v.diag or not math.isfinite(a.chisqr):
        return Finding()
    names, (damping, _) = list(a.varied), _damping(a)
    fitted = Optimum(a.params, a.stderr, m.sd, a.chisqr,
                     a.chisqr / max(m.r.size - len(names), 1))
    which = damping + (["w0"] if "w0" in names else [])
    prof = profile_ratios(a.profile, fitted, which)
    flat = [(k, c) for k, cs in prof.items() for c in cs if math.isfinite(c)
            and c < PROFILE_FAIL]
    vals = [c for cs in prof.values() for c in cs if math.isfinite(c)]
    diag = {"profile_min": float(min(vals)), "profile_max": float(max(vals))} if vals else {}
    if flat:
        k, c = min(flat, key=lambda kc: kc[1])
        return Finding(diag=diag, fails=(
            f"the intervals do not hold: with {k} held from 2 to {2 * PROFILE_REACH:.0f} sd "
            "from its value and the rest refitted the cost rises less than the intervals "
            "assume (the data pin the parameters down less than their linearisation says)",))
    # each side of an interval where the cost rises less than assumed is widened
    diag["interval_scale"] = {k: tuple(1.0 / math.sqrt(c) if math.isfinite(c) and c < 1.0
                                       else 1.0 for c in cs) for k, cs in prof.items()}
    lr = bound_tests(a.profile, fitted, damping, d_scale=a.d_scale,
                     amplitude=float(a.derived.get("A", math.nan)))
    diag.update({f"lr_zero_{k}": x[1] for k, x in lr.items()})
    fail, note = bound_verdict(lr, fitted, diag["interval_scale"])
    if note:
        diag["note_bound"] = note
    return Finding(diag=diag, fails=(fail,) if fail else ())


#: the checks before the residuals are measured (a ``stop`` ends the assessment), then those
#: of a trace fit on its measures, in order
FIRST = (step_budget, convergence, finite, degeneracy, standard_errors, envelope_decay,
         amplitude, absurd)
CHECKS = (residual_size, decay, split, structure, wander, motion_ends, exact_structure, size,
          drift, intervals)


def assess(a: Inputs):
    """Failures and adequacy of a finished fit: :data:`FIRST`, then :data:`CHECKS` on the
    fit's :class:`Measures`, each finding added to the verdict.

    Returns:
        (failures, inadequacies, diagnostics): two lists of one-line reasons and a dict of the
        measured numbers. ``diagnostics["unidentifiable"]``, when present, is the true reason
        to refuse the fit (the decay is measured, its split between the damping terms is not).
    """
    v = Verdict((), (), {})
    for check in FIRST:
        f = check(a, v)
        v = v.add(f)
        if f.stop:
            return list(v.fails), list(v.bad), v.diag
    m = measures(a)
    for check in CHECKS:
        v = v.add(check(a, m, v))
    return list(v.fails), list(v.bad), v.diag
