"""The fit of a prepared problem as a plan of stages (issue 33): each stage a function of the
problem and the fit so far (a :class:`Fit` value), the plan a value that says which stages run.

Stages, in order (:func:`run`):

1. **global starts**: a batch of jittered starts of the first model (the approximate one, the
   ansatz, unless the plan starts with the exact model), the best one polished;
2. **robust restart**: with ``loss="soft_l1"``, again from the linear-loss optimum with the
   scale from its residuals (1.4826 MAD);
2b. **the approximation answers?** (plan :data:`DEFAULT`, ``dp.fit``'s default): where the
   exact model's one-step correction of the approximate optimum is negligible against the
   intervals (``_answer.approximation_bias``), the approximate fit is assessed and, if it
   succeeds, is the answer; the report says which model answered and why;
3. **exact model**: a model with ``start_from`` (the reference) from the approximate optimum,
   and, where its residuals are not noise (``_checks.looks_stuck``), a batch of its own starts;
4. **continue**: where the default step budget ran out, one more round from there;
5. **neighbouring halts**: for the exact model with mu free, the motions that halt at the
   neighbouring turning points (``_halts.search_other_halts``);
6. **assess**: the result and its checks (``_result.build_result``), with the profile refits
   of the intervals' checks (:func:`profile_refit`) where the plan asks for them;
6b. **from the bound**: where a test at the bound (a constant held at 0) or a profile's point
   cost less, the fit again from there (:func:`from_the_bound`), its neighbouring halts
   searched again; :func:`finished` runs 6-7 on :func:`fitted`'s;
6c. **search on**: where the fit failed with structured residuals, each free damping constant
   held at 0, then a batch of the exact model's starts around the optimum, the neighbouring
   halts of a lower cost searched again (:func:`search_on`);
7. **static halt**: with a given mu_s, the halt of that motion and the rule mu_s >= mu.

:data:`FULL` is ``dp.fit``'s plan; :data:`INNER` the plan of the fits inside a search (k3's
profile, mu_s's screen: no neighbouring-halt search, no profile checks, no refusal, no static
halt; the search checks its chosen fit); :data:`DIRECT` and :data:`DIRECT_INNER` start with
the exact model (the fits at fixed mu_s or k3, from another fit's optimum).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import numpy as np

from ._answer import approximation_bias
from ._assess import NEWTON_TOL
from ._checks import STRUCTURE_P, data_rows, looks_stuck, newton_step
from ._context import prepare_envelope
from ._core import FIT_MODELS, FIT_RESULTS, is_code
from ._curves import prepare_amplitude_phase
from ._halts import (
    above_mu_s,
    held_mu_starts,
    mu_profile,
    noise_variance,
    prepare_motion,
    search_other_halts,
    with_static_halt,
)
from ._measures import k3_hint
from ._params import DAMPING, varied_names
from ._problem import SETTLE, Problem, Solved, predicted_start, robust_scale
from ._profile import other_halt_check, shared_start
from ._result import FitContext, FitResult, build_result
from ._starts import prepare_starts, run_starts
from ._text import lower_cost


class Plan(NamedTuple):
    """Which stages of :func:`run` a fit makes (see the module docstring)."""

    approximate_first: bool = True  # the approximate model first (else the exact one)
    neighbouring_halts: bool = True  # stage 5
    profile_checks: bool = True  # the intervals' profile refits in stage 6
    refuse_unidentifiable: bool = True  # a ValueError where the split is not determined
    static_halt: bool = True  # stage 7
    halt_check: bool = True  # stage 5's check (else its held fits kept in ``other_halts``)
    approximation_may_answer: bool = False  # stage 2b


#: starts of the batch of a held refit (the tests at the bound): it searches one region, the
#: valley where the other damping terms take over the held one's decay (around
#: ``_profile.transferred_start``), not the whole space of the fit's own batch; 8 jittered
#: starts of spread 4.5x per sigma reach it (benchmarks/README.md, issue 36's calibration)
HELD_STARTS = 8

FULL = Plan()
INNER = Plan(neighbouring_halts=False, profile_checks=False, refuse_unidentifiable=False,
             static_halt=False)
DIRECT = FULL._replace(approximate_first=False)
DIRECT_INNER = INNER._replace(approximate_first=False)
#: dp.fit's default (model "auto"): the exact model, answered by the approximation where the
#: two provably agree
DEFAULT = FULL._replace(approximation_may_answer=True)


class Fit(NamedTuple):
    """The fit so far: the current optimum, the last solve (whose model, scale and options a
    held refit uses), the batch of starts, the stages' notes."""

    best: object
    last: Solved
    starts: object = None
    notes: tuple = ()
    search: object = None  # the exact model's own batch, where it ran


def first_model(problem: Problem, plan: Plan) -> str:
    """The model of stages 1-2: the approximate one unless the plan starts with the exact."""
    spec = FIT_MODELS[problem.settings.model]
    return (spec.start_from or spec.name) if plan.approximate_first else spec.name


def batch_of_starts(problem: Problem, plan: Plan) -> bool:
    """Whether stage 1 runs a batch of starts (a closed-form first model, several starts)."""
    return problem.settings.starts > 1 and \
        not FIT_MODELS[first_model(problem, plan)].integrates


def global_starts(problem: Problem, plan: Plan) -> Fit:
    """Stage 1: the batch of starts (closed-form first models), then a solve from the best."""
    first, s = first_model(problem, plan), problem.settings
    found, start = None, problem.guess
    if batch_of_starts(problem, plan):
        found = run_starts(problem, problem.guess, first, math.inf, seed=int(s.seed))
        start = found.params
    last = problem.solve(start, first, math.inf, settle=SETTLE)  # (one-round models)
    return Fit(last.out, last, found)


def robust_restart(problem: Problem, state: Fit) -> Fit:
    """Stage 2: soft_l1 from the linear-loss optimum, f_scale = 1.4826 MAD of its residuals."""
    if problem.settings.loss != "soft_l1":
        return state
    r = problem.data.x - np.asarray(state.best.curve)[:problem.n]
    fs = robust_scale(r)
    fs = fs if fs > 0 else float(np.std(r)) or 1.0
    last = problem.solve(state.best.params, state.last.model, fs)
    return Fit(last.out, last, state.starts,
               state.notes + (f"soft_l1 started from the linear-loss fit, f_scale = {fs:.4g}",))


def exact_model(problem: Problem, plan: Plan, state: Fit) -> Fit:
    """Stage 3: the exact model from the approximate optimum; where its residuals are not
    noise, a batch of its own starts around the guess (both optima among them), the lower
    cost kept (the approximate optimum can lie in another basin of the exact model)."""
    spec = FIT_MODELS[problem.settings.model]
    if not (spec.start_from and plan.approximate_first):
        return state
    first, fs = state.last.model, state.last.fs
    text = f"started from the {first} fit ({int(state.best.steps)} steps)"
    approx = state.best.params
    last = problem.solve(approx, spec.name, fs, settle=SETTLE)
    out, found, s, data = last.out, state.starts, problem.settings, problem.data
    if s.starts > 1 and looks_stuck(data.t, data.x, np.asarray(out.curve)[:problem.n],
                                    data.analysis, float(out.params.w0), _code(problem, out)):
        opts = problem.reference_options(spec.name, problem.guess.w0)
        found = run_starts(problem, problem.guess, spec.name, fs, seed=int(s.seed) + 1,
                              extra=(approx, out.params), opts=opts)
        last = problem.solve(found.params, spec.name, fs)
        c0, c1 = float(out.chisqr), float(last.out.chisqr)
        text += (f"; its residuals were not noise: {int(s.starts) - 2} jittered starts of "
                 f"the {spec.name} model")
        if math.isfinite(c1) and (c1 < c0 or not math.isfinite(c0)):
            out = last.out
            text += f" found a lower cost ({lower_cost(0.5 * c1, 0.5 * c0)})"
        else:
            text += " found no lower cost"
    search = found if found is not state.starts else None
    return Fit(out, last, found, state.notes + (text,), search)


def _code(problem: Problem, out):
    """The exact fit's result code as :func:`exact_model` reads it: where a free damping
    constant is not told from 0 (within ``AT_ZERO`` standard errors) and the step budget ran
    out on a flat valley (one more Gauss-Newton step would lower the cost by less than
    ``NEWTON_TOL`` noise variances: :func:`_descending`), it crept along eq. 3's kink at that
    constant's 0, which the assessment accepts: no sign of a local optimum (undamped traces:
    a batch of starts found nothing in 3 of 3, 2-5 s; b free on a trace without it, 15,000
    samples: 13 s that found nothing). Elsewhere a capped fit keeps its search (a valley far
    from 0 can hide a lower optimum: test_fit.py)."""
    p, se = out.params, out.stderr
    if is_code(out.code, FIT_RESULTS.max_steps_reached) and any(
            float(getattr(p, n)) < AT_ZERO * float(getattr(se, n))
            for n in problem.settings.free if n in ("mu", "b", "D")) and \
            not _descending(problem, out):
        return FIT_RESULTS.successful
    return out.code


#: rounds of the default step budget that stage 4 adds, each while the last ran out of steps
#: with a Gauss-Newton step that would still lower the cost by more than
#: ``_assess.NEWTON_TOL`` noise variances (wide seed 9 draw 4: one heavily damped swing at
#: correlation 0.9992, converged in the second round; one failed it, the truth inside). A
#: smaller step: a flat valley the assessment accepts, leading on to absurd constants
#: (other noise: 0.013, then d0/(w0 A) = 100 three rounds on)
CONTINUE_ROUNDS = 3


def _descending(problem: Problem, out) -> bool:
    """Whether one more Gauss-Newton step from the fit ``out`` (a CoreResult) would lower its
    cost by more than NEWTON_TOL noise variances (``_checks.newton_step``, as the
    assessment's step-budget check)."""
    jac, rows = data_rows(out, problem.vary, problem.n)
    if jac is None or rows is None:
        return True
    names, params = varied_names(problem.vary), out.params._asdict()
    dec, _ = newton_step(jac, rows, [float(params[n]) for n in names], names)
    return dec > NEWTON_TOL


def continue_budget(problem: Problem, state: Fit) -> Fit:
    """Stage 4: where the default step budget ran out, more rounds (at most
    :data:`CONTINUE_ROUNDS`, see there), each kept if lower (a budget the caller set is
    honoured)."""
    if problem.settings.max_steps is not None:
        return state
    steps = 0
    for _ in range(CONTINUE_ROUNDS):
        out = state.best
        if not is_code(out.code, FIT_RESULTS.max_steps_reached) or \
                not _descending(problem, out):
            break
        last = problem.solve(out.params, problem.settings.model, state.last.fs)
        if not float(last.out.chisqr) < float(out.chisqr):
            state = state._replace(last=last)
            break
        steps += int(last.out.steps)
        state = Fit(last.out, last, state.starts, state.notes, state.search)
    if not steps:
        return state
    note = f"the step budget ran out: continued ({steps} more steps)"
    return state._replace(notes=state.notes + (note,))


def neighbouring_halts(problem: Problem, plan: Plan, state: Fit) -> tuple[Fit, dict]:
    """Stage 5: the search of the motions that halt at a neighbouring turning point (the
    exact model, mu free, mu_s = mu, the linear loss); (the fit, {held mu: its cost})."""
    s = problem.settings
    if not (plan.neighbouring_halts and FIT_MODELS[s.model].integrates and problem.vary.mu
            and problem.consts.mu_s is None and s.loss == "linear"):
        return state, {}
    best, last, others, notes = search_other_halts(problem, state.best, state.last)
    return Fit(best, last, state.starts, state.notes + notes, state.search), others


def profile_refit(problem: Problem, state: Fit, first: str, name: str, value, start=None,
                  batch: bool = False, values: bool = False):
    """The cost of the fit with ``name`` held at ``value`` (the intervals' checks): the lowest
    of the held fits from the linearised start (``start``: the fit's values with its values in
    place) and, for mu, from ``_halts.held_mu_starts`` (the fit's own values, past the first
    halt's threshold); ``batch``: from a batch of jittered starts around there (the first
    model's batch program), the best one polished; ``values``: (the cost, {name: value} of the
    held fit's varied parameters)."""
    held = {name: float(value), **{k: float(v) for k, v in (start or {}).items()}}
    best = state.best.params
    p = best._replace(**held) if start else predicted_start(state.best, name, value)
    if batch and problem.settings.starts > 1:
        local = problem.starting_at(starts=min(problem.settings.starts, HELD_STARTS))
        p = run_starts(local, p, first, state.last.fs, seed=int(problem.settings.seed) + 2,
                       held=name, extra=(p,)).params
        # its damping constants (the approximate model's state and frequency can lie far from
        # the exact model's where the block halts early)
        p = p._replace(**{k: float(getattr(p, k)) for k in problem.settings.free if k != name},
                       **{k: getattr(best, k) for k in ("w0", "offset", "x0", "v0")})
        p = p._replace(**{name: float(value)})
    starts = [p] + (held_mu_starts(problem, best, state.last.model, value, own=not start)
                    if name == "mu" and not batch else [])
    out = min((problem.holding(name).solve(q, state.last.model, state.last.fs, like=state.last,
                                           settle=SETTLE).out for q in starts),
              key=lambda o: float(o.chisqr))
    if not values:
        return float(out.chisqr)
    return float(out.chisqr), {k: float(getattr(out.params, k))
                               for k in varied_names(problem.vary)}


#: a free damping constant within this many standard errors of 0 is not told from its bound
#: by the data: there the ansatz and eq. 3 coincide (no friction or drag to approximate), so
#: the one-step check of their agreement passes wherever the ansatz's optimum is, also in a
#: wrong basin: draw 165 of fit_calibration.py seed 0 (mu 1.4e-10 against a truth of 0.106)
#: and draw 3 of seed 2 (mu at 0.07 sd against a truth 13 sd away: within half a swing eq. 3's
#: friction is an offset, the ansatz's is not), both confident wrong answers. In the 11 other
#: answers of the ansatz in seed 0's 200 draws every free constant lay 1.1 sd or more from 0
#: (the exact model, answering instead, costs only time)
AT_ZERO = 1.0


def approximation_answers(problem: Problem, plan: Plan,
                          state: Fit) -> tuple[FitResult | None, Fit]:
    """Stage 2b: the approximate fit, assessed, where the exact model's one-step correction
    of its optimum is negligible (``_answer``) and its checks pass; else None (the exact
    model answers, and the note says why)."""
    spec = FIT_MODELS[problem.settings.model]
    if not (plan.approximation_may_answer and plan.approximate_first and spec.start_from) \
            or problem.settings.loss != "linear" or problem.consts.mu_s is not None:
        return None, state
    at_zero = [n for n in problem.settings.free if n in ("mu", "b", "D") and
               float(getattr(state.best.params, n)) < AT_ZERO * float(getattr(
                   state.best.stderr, n))]
    if at_zero:  # near eq. 3's kink: the one-step check sees the models agree, not the basin
        return None, state._replace(notes=state.notes + (
            f"the exact model answers: {', '.join(at_zero)} within {AT_ZERO:g} standard "
            "error of 0 in the ansatz's optimum, where a one-step check of the models' "
            "agreement is local",))
    bias = approximation_bias(problem, state.best)
    state = state._replace(notes=state.notes + (bias.text(),))
    if not bias.negligible:
        return None, state
    approx = dataclasses.replace(problem, settings=problem.settings._replace(
        model=state.last.model))
    # its residuals are eq. 3's (within a noise variance): their structure is judged as the
    # exact model's, against the approximate fit's own search of starts
    res = assess(approx, plan, state._replace(search=state.starts), exact=True)
    if not res.success:
        return None, state._replace(notes=state.notes[:-1] + (
            bias.text().replace("the ansatz answers", "the ansatz's bias is negligible") +
            f", but its fit failed ({res.reason}): the exact model answers",))
    return dataclasses.replace(res, diagnostics={**res.diagnostics, "answer": bias.text(),
                                                 "answer_shift_sd": bias.shift_sd,
                                                 "answer_remainder": bias.remainder}), state


def assess(problem: Problem, plan: Plan, state: Fit, *, exact: bool = False,
           lower: list | None = None) -> FitResult:
    """Stage 6: the result and its checks (``_result.build_result``; ``exact``: the
    residuals are eq. 3's, ``_assess.Inputs``); ``lower`` collects (cost, name, values) of
    the held fits of the checks that cost less than the fit: a damping constant held at 0
    (the tests at the bound), a profile's point by more than a step that decides nothing
    (:func:`from_the_bound`)."""
    s, data = problem.settings, problem.data
    profile, c = None, float(state.best.chisqr)
    if s.loss == "linear" and plan.profile_checks:
        refit = functools.partial(profile_refit, problem, state, first_model(problem, plan))
        floor = c - NEWTON_TOL * noise_variance(problem, state.best)

        def profile(name, value, *args, **kwargs):
            out = refit(name, value, *args, **{**kwargs, "values": True})
            if lower is not None and out[0] < (c if float(value) == 0.0 else floor):
                lower.append((out[0], name, out[1]))
            return out if kwargs.get("values") else out[0]
    res = build_result(state.best, FitContext(
        model=s.model, free=s.free, vary=problem.vary, consts=problem.consts, t=data.t,
        x=data.x, loss=s.loss, optimizer=s.optimizer, f_scale=state.last.fs,
        init={name: getattr(problem.guess, name) for name in varied_names(problem.vary)},
        source=data.source, full_t=data.t_all, full_x=data.x_all, warnings=problem.warnings,
        stages="; ".join(state.notes), per_mass=problem.per_mass, units=problem.units,
        analysis=data.analysis, starts=state.starts, profile=profile, search=state.search,
        exact=exact))
    if "unidentifiable" in res.diagnostics and plan.refuse_unidentifiable:
        raise ValueError(res.diagnostics["unidentifiable"])
    return _with_k3_hint(res, problem)


def from_the_bound(problem: Problem, state: Fit, lower: list) -> Fit | None:
    """Stage 6b: a held fit of the checks costs less than the optimum. A damping constant
    held at 0 (the tests at the bound): the optimizer stopped near its floor, where its
    log-step stalls (wide draw 2 of fit_calibration.py seed 9: mu 8.6e-7, 0.45 of its floor,
    the truth 0, the held fit 23 noise variances lower); a profile's point: the optimum was a
    local one (calibrated seed 34 draw 43: mu 0.43 of the truth, mu's and b's held fits 6-10
    noise variances lower). The fit again from the lowest held fit's values with the
    constant free (at 0: started at its lower bound, ``_core.Tuning.at_bound``); the new
    optimum where it costs less, else None."""
    cost, name, point = min(lower, key=lambda item: item[0])
    p = state.best.params._replace(**{k: float(v) for k, v in point.items()})
    value = float(getattr(p, name))
    last = problem.solve(p, state.last.model, state.last.fs, like=state.last,
                         at_bound=value == 0.0)
    if not float(last.out.chisqr) < float(state.best.chisqr):
        return None
    was = lower_cost(0.5 * cost, 0.5 * float(state.best.chisqr))
    note = (f"with {name} held at {value:.4g} the cost was lower ({was}): fitted again from "
            "there" + (f", {name} started at its bound" if value == 0.0 else ""))
    return Fit(last.out, last, state.starts, state.notes + (note,), state.search)


def search_on(problem: Problem, plan: Plan, state: Fit, res: FitResult) -> tuple | None:
    """Stage 6c: a fit that failed with structured residuals (a local optimum its search of
    starts did not settle; its tests at the bound need noise-like residuals and did not run)
    searches on: each free damping constant held at 0 with the rest refitted, continued from
    the lowest that costs less (:func:`from_the_bound`; fit_calibration.py wide seed 13 draw
    33: quadratic drag alone fitted as b 0.34 kg/s, D 2.5x the truth, 2.2x the truth's
    cost), else a batch of the exact model's starts around the fit's optimum, a constant at
    its bound moved to its share (``_profile.shared_start``; seed 15 draw 23: 6 % above the
    truth's cost). The settle rule keeps reading the first search (``Fit.search``).

    Returns:
        (the moved fit, its neighbouring halts: stage 5 again), or None where nothing cost
        less (or the fit did not fail with structured residuals).
    """
    s, spec = problem.settings, FIT_MODELS[problem.settings.model]
    if res.success or not plan.profile_checks or s.loss != "linear" or \
            not res.diagnostics.get("residual_p", 1.0) < STRUCTURE_P:
        return None
    first, best, lower = first_model(problem, plan), state.best, []
    # lower by more than a step that decides nothing (b at 4e-9 held at 0: 1e-14 lower)
    floor = float(best.chisqr) - NEWTON_TOL * float(res.chisqr) / max(res.ndata - res.nvarys, 1)
    for name in (n for n in s.free if n in DAMPING and float(getattr(best.params, n)) > 0.0):
        cost, point = profile_refit(problem, state, first, name, 0.0, values=True)
        if cost < floor:
            lower.append((cost, name, point))
    moved = from_the_bound(problem, state, lower) if lower else None
    if moved is None and s.starts > 1 and spec.integrates:
        opts = problem.reference_options(spec.name, best.params.w0)
        found = run_starts(problem, shared_start(best.params, s.free, problem.consts), spec.name,
                           state.last.fs, seed=int(s.seed) + 3, extra=(best.params,), opts=opts)
        last = problem.solve(found.params, spec.name, state.last.fs)
        c0, c1 = float(best.chisqr), float(last.out.chisqr)
        if c1 < c0:
            moved = Fit(last.out, last, state.starts, state.notes + (
                f"its residuals were not noise: {int(s.starts) - 1} jittered starts around "
                f"that optimum found a lower cost ({lower_cost(0.5 * c1, 0.5 * c0)})",),
                state.search)
    return None if moved is None else neighbouring_halts(problem, plan, moved)


def _with_k3_hint(res: FitResult, problem: Problem) -> FitResult:
    """Structured residuals of a linear spring whose data's frequency follows the amplitude:
    the inadequacy says that a cubic stiffness may take them up (``_measures.k3_hint``)."""
    structure = [i for i, s in enumerate(res.inadequacy) if "structure" in s]
    if not structure or problem.consts.k3 is not None or "k3" in problem.settings.free:
        return res
    hint = k3_hint(problem.data.analysis, problem.data.t, problem.data.x)
    if not hint:
        return res
    items = list(res.inadequacy)
    items[structure[0]] += hint
    return dataclasses.replace(res, inadequacy=items)


def prepare_programs(problem: Problem, plan: Plan) -> None:
    """Start compiling, in the background, the programs of the fit, traced one after another
    (``_cache._turn``) and compiled side by side: the first model's fit (traced in 0.7 s, so
    the second core compiles from then on; the exact model's first, traced in 1.8 s, left it
    idle that long: a cold fit 8.7 s, 8.3 s now, medians of alternating runs), then the
    exact model's (for the guess's frequency: the approximate optimum's nearly always shares
    its swing budget), the batch of starts, the motion of the neighbouring-halt search, the
    report's envelope and matched amplitude (issue 36)."""
    s, c = problem.settings, problem.consts
    if s.optimizer != "lm":
        return
    first = first_model(problem, plan)
    problem.prepare(problem.guess, first)  # the quickest to trace
    if first != s.model:
        problem.prepare(problem.guess, s.model)
    if batch_of_starts(problem, plan):
        prepare_starts(problem, problem.guess, first)
    if plan.neighbouring_halts and FIT_MODELS[s.model].integrates and problem.vary.mu and \
            c.mu_s is None and s.loss == "linear":
        prepare_motion(problem.guess, problem.data.t, *c.motion)
    prepare_envelope(problem.data.t)
    if FIT_MODELS[s.model].integrates:  # the report's matched amplitude and phase
        prepare_amplitude_phase(problem.guess._asdict(), c.m, c.g)


def run(problem: Problem, plan: Plan = FULL) -> FitResult:
    """The :class:`FitResult` of a prepared problem (from ``_problem.prepare``, and its
    ``holding`` / ``with_consts`` / ``starting_at``) fitted by ``plan`` (the module
    docstring's stages)."""
    answered, state, others = fitted(problem, plan)
    return answered if answered is not None else finished(problem, plan, state, others)


def fitted(problem: Problem, plan: Plan) -> tuple[FitResult | None, Fit, dict]:
    """Stages 1-5 of :func:`run`: (the approximation's answer or None, the fit, its
    neighbouring halts). A search that keeps one of its fits (k3's profile) assesses only
    that one (:func:`finished`)."""
    prepare_programs(problem, plan)
    state = global_starts(problem, plan)
    state = robust_restart(problem, state)
    answered, state = approximation_answers(problem, plan, state)
    if answered is not None:
        return answered, state, {}
    state = exact_model(problem, plan, state)
    state, others = neighbouring_halts(problem, plan, continue_budget(problem, state))
    return None, continue_budget(problem, state), others  # (its optimum: wide 18 draw 36)


def finished(problem: Problem, plan: Plan, state: Fit, others: dict) -> FitResult:
    """Stages 6-7 of :func:`run` on the fit of stages 1-5 (:func:`fitted`)."""
    lower = []
    res = assess(problem, plan, state, lower=lower)
    moved = from_the_bound(problem, state, lower) if lower else None
    if moved is not None:  # the motions that halt next to the new optimum's halt
        moved, others = neighbouring_halts(problem, plan, moved)
    if not lower and (found := search_on(problem, plan, state, res)) is not None:
        moved, others = found
    if moved is not None:
        state, res = moved, assess(problem, plan, moved)
    if others and res.success:
        res = other_halt_check(res, others, mu_profile(problem, state.best, state.last)) \
            if plan.halt_check else dataclasses.replace(res, other_halts=others)
    mu_s, c = problem.consts.mu_s, problem.consts
    if mu_s is not None and plan.static_halt:  # the halt of the motion with static friction
        res = above_mu_s(with_static_halt(res, *c.motion, mu_s), mu_s)
    return res
