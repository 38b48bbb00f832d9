"""The joint optimisation of several runs (``_joint.fit_joint``): every candidate start of the
shared constants in one batch with the approximate model, the best one on to the exact model,
and where the exact optimum's residuals are structured the exact model's own search of
starts (issue 36, item 4): the single fits' values, each shared damping constant's decay
handed to the others, each run's own exact fit; the start of the lowest cost that ran out of
steps continued."""

from __future__ import annotations

import jax
import numpy as np

from ._api import _swings_bucket
from ._checks import STRUCTURE_P, residual_structure
from ._core import FIT_MODELS, FIT_RESULTS, ReferenceOptions, is_code
from ._joint_problem import (
    CONTINUATIONS,
    JointArrays,
    JointCore,
    best_start,
    run_joint_batch,
    run_joint_core,
)
from ._joint_stages import (
    JointSettings,
    JointStart,
    _arrays,
    _restart,
    _single_fits,
    _start_params,
)
from ._measures import SETTLE_RTOL, settled_starts
from ._params import DAMPING, PARAMS, d_per_unit
from ._profile import transferred_start
from ._starts import BATCH_LANES, REACHED_RTOL, Starts


def _optimise(init: JointStart, cfg: JointSettings) -> tuple:
    """The joint optimisation: every candidate start of the shared constants optimised in one
    vmapped batch with the approximate model, the best one on to the exact model (continued
    where its step budget ran out).

    Arguments:
        init: the start.
        cfg: the settings.

    Returns:
        (the core's output, the arrays it was fitted with, the reference options, the
        stages it went through, the exact model's search (:func:`_exact_search`; None for
        the approximate model)).
    """
    spec = FIT_MODELS[cfg.model]
    first = spec.start_from or cfg.model
    lay, data = init.lay, init.data
    batch = [_arrays(data, FIT_MODELS[first], lay, sv) for sv in init.candidates]
    spans = np.asarray(batch[0].span)
    opts = None
    if spec.integrates:
        longest = int(np.argmax(spans))
        opts = ReferenceOptions(_swings_bucket(cfg.max_swings, data.singles[longest].t,
                                               max(init.w0s)), 1e-8, 1e-10)
    budget = dict(max_steps=cfg.max_steps, rtol=cfg.rtol, atol=cfg.atol)
    outs = run_joint_batch(jax.tree_util.tree_map(lambda *v: np.stack(v), *batch),
                           lay=lay._replace(model=first),
                           opts=None if spec.start_from else opts, **budget)
    best = best_start(outs)
    arrays = batch[best]
    out = jax.tree_util.tree_map(lambda v: v[best], outs)
    which = "the median of the single fits" if best == 0 else f"run {best - 1}'s single fit"
    stages = [f"{len(batch)} starts of the shared constants, the best from {which}"]
    search = None
    if spec.start_from:  # the approximate model's joint optimum first
        arrays = _restart(arrays, out, lay, spec, data.consts)
        stages.append(f"started from the joint {first} fit ({int(out.steps)} steps)")
        out = run_joint_core(arrays, lay=lay, opts=opts, **budget)
        # a budget ran out on the way (the approximate optimum far from the exact one):
        # continue from where it stopped, with the same compiled program
        for _ in range(CONTINUATIONS):
            if not is_code(out.code, FIT_RESULTS.max_steps_reached):
                break
            arrays = _restart(arrays, out, lay, spec, data.consts)
            done = int(out.steps)
            out = run_joint_core(arrays, lay=lay, opts=opts, **budget)
            stages.append(f"continued after {done} steps")
        out, arrays, search = _exact_search(out, arrays, init, cfg, opts)
        if search is not None:
            # the settle rule of the verdict (``_measures.settled_starts``), not "reached"
            stages.append(f"{search.n} starts of the exact model, "
                          f"{settled_starts(search.costs)} settled within "
                          f"{100 * SETTLE_RTOL:g} % of the best cost")
    return out, arrays, opts, stages, search


def _structured(out: JointCore, a: JointArrays) -> bool:
    """Whether some run's residuals at the joint optimum hold structure that AR(1) noise
    cannot produce (``_checks.residual_structure``): only then does the exact model's search
    have two causes to tell apart."""
    weight, resid = np.asarray(a.weight, dtype=float), np.asarray(out.resid, dtype=float)
    for j in range(weight.shape[0]):
        rows = weight[j] > 0
        p = residual_structure(np.asarray(a.tau, dtype=float)[j, rows], resid[j, rows],
                               float(np.asarray(out.P)[j, 3]))["p"]
        if p < STRUCTURE_P:
            return True
    return False


def _exact_search(out: JointCore, arrays: JointArrays, init: JointStart, cfg: JointSettings,
                  opts) -> tuple:
    """The exact model's own search (issue 36, item 4): the exact joint fit again from each
    candidate start of the shared constants (the median of the single fits, each run's),
    in one batch (``run_joint_batch``: start by start on a CPU), beside the fit started from
    the approximate model's optimum, where some run's residuals are structured
    (:func:`_structured`). Structured residuals at an optimum that no start improves on, on
    which the starts settle, are the model's (it lacks something), not a local optimum's.
    The starts also hand each shared damping constant's decay to the others
    (:func:`_transferred`: a split of the decay between the terms that none of the single
    fits suggests; joint_calibration.py set 4: b 8 sd from its truth 0, every start settled
    there), and start from each run's own fit with the exact model (every run's values).

    Arguments:
        out, arrays: the exact fit from the approximate model's optimum and its arrays.
        init: the start (its candidates).
        cfg: the settings.
        opts: the reference options.

    Returns:
        (the best output, its arrays, a ``_starts.Starts`` of the search: n, reached, costs;
        None where no run's residuals are structured).
    """
    if not _structured(out, arrays):  # noise is all the runs leave: nothing to tell apart
        return out, arrays, None
    spec = FIT_MODELS[cfg.model]
    batch = [_arrays(init.data, spec, init.lay, sv)
             for sv in list(init.candidates) + _transferred(out, init)]
    # each run's own exact fit: the approximate single fits may all lie in a valley of the
    # approximation (joint_calibration.py set 26: Coulomb friction over 3 half swings, the
    # ansatz's runs all at b 15 times its truth and mu 0, the exact fits at the truth)
    # (one batch of BATCH_LANES starts each: the batch program of the tests at the bound)
    exact = _single_fits([(s.t, s.x) for s in init.data.singles],
                         ([float(s.t[0]) for s in init.data.singles],
                          [None] * len(init.data.singles)),
                         cfg._replace(starts=min(cfg.starts, BATCH_LANES)), model=cfg.model)[0]
    own, usable = _start_params(exact, init.data.osc)
    data = init.data._replace(own=own)
    shared = list(init.candidates[0])
    batch += [_arrays(data, spec, init.lay, {n: float(p[n]) for n in shared})
              for p, ok in zip(own, usable, strict=True) if ok]
    outs = run_joint_batch(jax.tree_util.tree_map(lambda *v: np.stack(v), *batch),
                           lay=init.lay, opts=opts, max_steps=cfg.max_steps, rtol=cfg.rtol,
                           atol=cfg.atol)
    both = jax.tree_util.tree_map(lambda a, b: np.concatenate([np.asarray(a)[None],
                                                               np.asarray(b)]), out, outs)
    both, arrs = _continue_lowest(both, [arrays] + batch, init, cfg, opts)
    best = best_start(both)
    cost = 0.5 * np.sum(np.asarray(both.resid, dtype=float) ** 2, axis=(1, 2))
    # the settle rule counts the starts that converged, as ``best_start`` chooses among them
    # (set 25 of joint_calibration.py: seven starts that ran out of steps lay within 1 % of
    # each other, below the converged optimum chosen, 100 times the noise: "settled")
    done = np.asarray(both.code._value) == FIT_RESULTS.successful._value
    cost = np.where(np.isfinite(cost) & done, cost, np.nan)
    reached = int(np.sum(cost <= cost[best] * (1.0 + REACHED_RTOL) + 1e-300))
    search = Starts(n=cost.size, reached=reached, costs=cost, best=best, stride=1,
                    params=None)
    # arrays, not numpy scalars: an enumeration item (the code) reads its message only from
    # an array (equinox's Enumeration: a numpy scalar's message is "unknown")
    return jax.tree_util.tree_map(lambda v: np.asarray(v[best]), both), arrs[best], search


def _continue_lowest(both: JointCore, batch: list, init: JointStart, cfg: JointSettings,
                     opts) -> tuple:
    """The search's start of the lowest cost, where it ran out of steps below every converged
    start's cost, continued from where it stopped (at most ``CONTINUATIONS`` times, the first
    exact fit's rule) and put back in its place.

    Returns:
        (the outputs, the arrays of each start): ``both`` and ``batch`` with that start's
        replaced.
    """
    cost = np.sum(np.asarray(both.resid, dtype=float) ** 2, axis=(1, 2))
    cost = np.where(np.isfinite(cost), cost, np.inf)
    done = np.asarray(both.code._value) == FIT_RESULTS.successful._value
    i = int(np.argmin(cost))
    if done[i] or not np.isfinite(cost[i]):
        return both, batch
    spec = FIT_MODELS[cfg.model]
    out = jax.tree_util.tree_map(lambda v: v[i], both)
    arrays = batch[i]
    for _ in range(CONTINUATIONS):
        arrays = _restart(arrays, out, init.lay, spec, init.data.consts)
        out = run_joint_core(arrays, lay=init.lay, opts=opts, max_steps=cfg.max_steps,
                             rtol=cfg.rtol, atol=cfg.atol)
        if not is_code(out.code, FIT_RESULTS.max_steps_reached):
            break
    return jax.tree_util.tree_map(
        lambda a, v: np.concatenate([a[:i], np.asarray(v)[None], a[i + 1:]]), both, out), \
        batch[:i] + [arrays] + batch[i + 1:]


def _transferred(out: JointCore, init: JointStart) -> list:
    """Starts of the shared constants at the joint optimum ``out`` with each shared damping
    constant's decay handed to the other shared ones (``_profile.transferred_start``, as the
    single fit's test at the bound: at half the runs' median amplitude; the constant itself
    started at 0, its floor): where the optimum is a split of the decay that the data do
    not hold, the other valley is reached from there.

    Returns:
        A list of dicts by name (empty where fewer than two damping constants are shared).
    """
    lay, data = init.lay, init.data
    vals = {n: float(v) for n, v in zip(lay.shared, np.asarray(out.p), strict=False)}
    damping = [n for n in lay.shared if n in DAMPING and vals[n] > 0.0]
    if len(damping) < 2:
        return []
    P = np.asarray(out.P, dtype=float)
    w0 = vals.get("w0", float(np.median(P[:, PARAMS.index("w0")])))
    d_scale = d_per_unit(w0, data.consts.m, data.consts.g)
    amplitude = float(np.median(np.hypot(P[:, PARAMS.index("x0")],
                                         P[:, PARAMS.index("v0")] / P[:, PARAMS.index("w0")])))
    out_starts = []
    for name in damping:
        start = transferred_start(name, vals, damping, d_scale, amplitude)
        if start is not None:
            out_starts.append({**vals, **start, name: 0.0})
    return out_starts
