"""The stages of a joint fit (``_joint``, where the method is described): each run's single
fit, the start of the joint problem (each run's start, the weights, the candidates for the
shared constants, the padded arrays), and the joint optimisation (the batch of starts with the
approximate model, then the exact model, continued where its budget ran out, from restarted
arrays)."""

from __future__ import annotations

import math
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._api import _swings_bucket
from ._checks import STRUCTURE_P, residual_structure
from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    ReferenceOptions,
)
from ._joint_problem import (
    CONTINUATIONS,
    COORDS,
    JointArrays,
    JointCore,
    Layout,
    best_start,
    run_joint_batch,
    run_joint_core,
)
from ._measures import SETTLE_RTOL, settled_starts
from ._params import (
    DAMPING,
    FREE,
    PARAMS,
    Constants,
    TraceParams,
    check_free,
    damping_d,
    damping_floors,
)
from ._pipeline import INNER, run
from ._problem import Settings, bucket, pad, prepare
from ._profile import transferred_start
from ._starts import REACHED_RTOL, Starts


class JointSettings(NamedTuple):
    """The checked settings of a joint fit (the same for every run; see :func:`fit_joint`).

    Attributes:
        model: the fit model's name.
        shared, free: the shared parameters and the free damping constants (checked).
        oscillator, osc: the oscillator as given (None: per unit mass) and its values.
        fit_omega0, offset, units, starts, seed, k3: as in ``fit``.
        max_steps, rtol, atol: the joint optimizer's budget (a number) and tolerances.
        max_swings: the reference model's budget (None: from the longest window).
    """

    model: str
    shared: tuple
    free: tuple
    oscillator: Any
    osc: dict
    fit_omega0: Any
    offset: bool
    units: str | None
    starts: int
    seed: int
    k3: float | None
    max_steps: int
    rtol: float
    atol: float
    max_swings: int | None


class StartData(NamedTuple):
    """What the arrays of a joint fit are made of, whatever the shared constants' start.

    Attributes:
        singles: the runs' single fits (their windows).
        own: each run's start (dicts of :data:`~dampax._fit._params.PARAMS`).
        sigma, amp: each run's noise level and amplitude.
        n_pad: the padded length.
        consts: the constants of the fit (k3 at its start).
        k3_start, k3_scale: the cubic stiffness's start and scale.
        osc: the oscillator's values (m, g).
    """

    singles: list
    own: list
    sigma: np.ndarray
    amp: np.ndarray
    n_pad: int
    consts: Constants
    k3_start: float
    k3_scale: float
    osc: dict


class JointStart(NamedTuple):
    """The start of a joint fit.

    Attributes:
        data: the arrays' ingredients (:class:`StartData`).
        lay: the layout of the fit (its model the exact one).
        candidates: the starts of the shared constants (dicts by name): the median of the
            single fits, then each run's own values (the median where its fit is not usable).
        w0s: each run's w0 at the start.
    """

    data: StartData
    lay: Layout
    candidates: list
    w0s: list


def _single_fits(runs, windows, cfg: JointSettings, model: str | None = None
                 ) -> tuple[list, list]:
    """Each run alone (its window, guesses, global starts; the approximate model where the
    fit model starts from one, else ``model``): the starts of the joint fit.

    Arguments:
        runs: (trace_or_t, x) of each run.
        windows: (starts, ends) of the runs' windows.
        cfg: the settings.
        model: the model of the single fits (None: the first model of ``cfg.model``).

    Returns:
        (the single fits, the sorted distinct warnings they gave).

    Raises:
        ValueError: a run cannot be fitted (its index named).
    """
    starts_at, ends_at = windows
    first = model or FIT_MODELS[cfg.model].start_from or cfg.model
    singles = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for j, (tr, x) in enumerate(runs):
            try:
                res = run(prepare(tr, x, Settings(
                    oscillator=cfg.oscillator, free=check_free(cfg.free, allowed=FREE),
                    model=first, fit_omega0=cfg.fit_omega0, offset=cfg.offset,
                    start=starts_at[j], end=ends_at[j], units=cfg.units, starts=cfg.starts,
                    seed=cfg.seed, k3=cfg.k3)), INNER)
            except ValueError as err:
                raise ValueError(f"traces[{j}]: {err}") from err
            singles.append(res)
    return singles, sorted({str(w.message) for w in caught})


def _joint_start(singles, cfg: JointSettings) -> JointStart:
    """The start of the joint fit from the single fits: each run's start (its single fit;
    where that is not finite, a start from its data), the layout, the weights, the
    candidates for the shared constants.

    Arguments:
        singles: the runs' single fits.
        cfg: the settings.

    Returns:
        A :class:`JointStart`.
    """
    osc, shared, k3 = cfg.osc, cfg.shared, cfg.k3
    own, usable = _start_params(singles, osc)
    # the common start of the shared constants: the median of the single fits
    start_vals = {n: float(np.median([p[n] for p in own])) for n in shared if n != "k3"}
    lay_local = tuple(c for c in COORDS if c not in shared and (
        (c in DAMPING and c in cfg.free) or (c == "w0" and cfg.fit_omega0)
        or (c == "offset" and cfg.offset) or c in ("x0", "y")))
    k3_mode = "shared" if "k3" in shared else ("fixed" if k3 is not None else "none")
    lay = Layout(model=cfg.model, n_runs=len(singles), shared=shared, local=lay_local,
                 k3=k3_mode)
    sigma = np.array([_noise_level(s) for s in singles])
    w0s = [start_vals.get("w0", p["w0"]) for p in own]
    amp = np.array([math.hypot(p["x0"], p["v0"] / w) for p, w in zip(own, w0s, strict=True)])
    k3_start = 0.0 if k3 is None else float(k3)
    k3_scale = float(osc["m"] * np.median(w0s) ** 2 / np.median(amp) ** 2)
    consts = Constants(m=osc["m"], g=osc["g"], k3=None if k3_mode == "none" else k3_start)
    # the starts of the shared constants: the median of the single fits and each single
    # fit's own values (a poor single fit spoils the median of few runs)
    candidates = [start_vals] + [{n: float(p[n]) for n in start_vals} if ok else start_vals
                                 for p, ok in zip(own, usable, strict=True)]
    data = StartData(singles=singles, own=own, sigma=sigma, amp=amp,
                     n_pad=bucket(max(s.t.size for s in singles)), consts=consts,
                     k3_start=k3_start, k3_scale=k3_scale, osc=osc)
    return JointStart(data=data, lay=lay, candidates=candidates, w0s=w0s)


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
            if out.code != FIT_RESULTS.max_steps_reached:
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
    exact = _single_fits([(s.t, s.x) for s in init.data.singles],
                         ([float(s.t[0]) for s in init.data.singles],
                          [None] * len(init.data.singles)), cfg, model=cfg.model)[0]
    own, usable = _start_params(exact, init.data.osc)
    data = init.data._replace(own=own)
    shared = [n for n in init.candidates[0]]
    batch += [_arrays(data, spec, init.lay, {n: float(p[n]) for n in shared})
              for p, ok in zip(own, usable, strict=True) if ok]
    outs = run_joint_batch(jax.tree_util.tree_map(lambda *v: np.stack(v), *batch),
                           lay=init.lay, opts=opts, max_steps=cfg.max_steps, rtol=cfg.rtol,
                           atol=cfg.atol)
    both = jax.tree_util.tree_map(lambda a, b: np.concatenate([np.asarray(a)[None],
                                                               np.asarray(b)]), out, outs)
    best = best_start(both)
    cost = 0.5 * np.sum(np.asarray(both.resid, dtype=float) ** 2, axis=(1, 2))
    cost = np.where(np.isfinite(cost), cost, np.nan)
    reached = int(np.sum(cost <= cost[best] * (1.0 + REACHED_RTOL) + 1e-300))
    search = Starts(n=cost.size, reached=reached, costs=cost, best=best, stride=1,
                    params=None)
    if best == 0:
        return out, arrays, search
    # arrays, not numpy scalars: an enumeration item (the code) reads its message only from
    # an array (equinox's Enumeration: a numpy scalar's message is "unknown")
    return jax.tree_util.tree_map(lambda v: np.asarray(v[best]), both), batch[best - 1], \
        search


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
    per_unit = damping_d(1.0, 1.0, 1.0, w0, data.consts.m, data.consts.g)
    d_scale = {n: float(d) for n, d in zip(DAMPING, per_unit, strict=True)}
    amplitude = float(np.median(np.hypot(P[:, PARAMS.index("x0")],
                                         P[:, PARAMS.index("v0")] / P[:, PARAMS.index("w0")])))
    out_starts = []
    for name in damping:
        start = transferred_start(name, vals, damping, d_scale, amplitude)
        if start is not None:
            out_starts.append({**vals, **start, name: 0.0})
    return out_starts


def _noise_level(single) -> float:
    """A run's weight 1/sigma: the rms of its single fit; where that is not a positive finite
    number (a failed single fit), the noise of the data's first differences (rms / sqrt 2)."""
    floor = 1e-12 * max(float(np.ptp(single.x)), 1e-300)
    rms = float(single.rms)
    if not (math.isfinite(rms) and rms > 0.0):
        rms = float(np.std(np.diff(np.asarray(single.x, dtype=float)))) / math.sqrt(2.0)
    return max(rms, floor) if math.isfinite(rms) else 1.0


def _start_params(singles, osc) -> tuple[list, list]:
    """Each run's start (dicts of the :data:`~dampax._fit._params.PARAMS`) and whether it is
    its single fit's optimum: where that has a non-finite or absurd value, the run starts
    from its data (offset the median, x0 the first sample about it, v0 the slope of the first
    samples) with w0 and the damping constants at the median of the finite single fits."""
    fields = TraceParams._fields
    # a wild single fit may end finite but absurd (joint_calibration.py set 6: D 3e293, an
    # amplitude of 1e289 m): no start, as where it is not finite
    usable = [all(math.isfinite(float(s.params[n])) for n in fields)
              and float(s.params["w0"]) > 0.0 and math.hypot(
                  float(s.params["x0"]), float(s.params["v0"]) / float(s.params["w0"]))
              <= 100.0 * float(np.ptp(np.asarray(s.x, dtype=float))) for s in singles]
    pool = [s.params for s, ok in zip(singles, usable, strict=True) if ok]
    med = {n: (float(np.median([p[n] for p in pool])) if pool else
               (float(osc["w0"]) if n == "w0" and osc.get("w0") else 0.0)) for n in fields}
    if not pool and not med["w0"] > 0:
        med["w0"] = 1.0
    out = []
    for s, ok in zip(singles, usable, strict=True):
        if ok:
            out.append({n: float(s.params[n]) for n in fields})
            continue
        t, x = np.asarray(s.t, dtype=float), np.asarray(s.x, dtype=float)
        p = dict(med)  # w0 and the damping constants: the median of the sound fits
        off = float(np.median(x))
        k = max(2, min(x.size, int(0.1 * 2 * math.pi / p["w0"] / max(t[1] - t[0], 1e-300))))
        p.update(offset=off, x0=float(x[0] - off),
                 v0=float(np.polyfit(t[:k] - t[0], x[:k], 1)[0]))
        out.append(p)
    return out, usable


def _arrays(data: StartData, spec, lay: Layout, start_vals) -> JointArrays:
    """The arrays of a joint fit started from each run's start (the shared parameters at
    ``start_vals``), in the coordinates of the fit model ``spec``.

    Arguments:
        data: the runs, their starts, weights and scales (:class:`StartData`).
        spec: the fit model (``_core.FIT_MODELS``) whose coordinates the arrays hold.
        lay: the layout of the fit.
        start_vals: the shared parameters' start (dict by name; w0 and the damping constants).

    Returns:
        The :class:`JointArrays`.
    """
    singles, own, sigma, amp, n_pad = data.singles, data.own, data.sigma, data.amp, data.n_pad
    consts, osc, k3_start, k3_scale = data.consts, data.osc, data.k3_start, data.k3_scale
    rows = {k: [] for k in ("tau", "x", "weight", "span", "ref", "scale", "lo", "start")}
    for j, s in enumerate(singles):
        tp, xp, wt = pad(s.t, s.x, n_pad)
        p = TraceParams(**{n: start_vals.get(n, own[j][n]) for n in TraceParams._fields})
        sx = amp[j] if amp[j] > 0 else 1.0
        span = max(float(s.t[-1] - s.t[0]), 1e-12)
        q = spec.to_coords(jax.tree_util.tree_map(jnp.asarray, p), consts)
        floors = damping_floors(p.w0, sx, consts)
        ref, lo = [], []
        for name in COORDS:
            v = float(getattr(q, name))
            if name in DAMPING and (name in lay.shared or name in lay.local):
                fl = float(getattr(floors, name))
                v = max(v, fl)
                lo.append(math.log(max(1e-6 * fl / v, 1e-300)))  # (v may be absurd)
            else:
                lo.append(-math.inf)
            ref.append(v)
        scale = [1.0, 1.0, 1.0, 1.0 / span, sx, sx, float(spec.y_scale(p.w0, sx))]
        rows["tau"].append(tp - tp[0])
        rows["x"].append(xp)
        rows["weight"].append(wt / sigma[j])
        rows["span"].append(span)
        rows["ref"].append(ref)
        rows["scale"].append(scale)
        rows["lo"].append(lo)
        rows["start"].append([float(v) for v in p])
    ref = np.array(rows["ref"])
    lo = np.array(rows["lo"])
    spans = np.array(rows["span"])
    sref, sscale, slo = [], [], []
    for name in lay.shared:
        if name in DAMPING:
            i = COORDS.index(name)
            v = float(np.max(ref[:, i]))
            sref.append(v)
            sscale.append(1.0)
            slo.append(float(np.max(lo[:, i] + np.log(ref[:, i] / v))))
        elif name == "w0":
            sref.append(start_vals["w0"])
            sscale.append(1.0 / float(np.max(spans)))
            slo.append(-math.inf)
        else:  # k3, linear around its start in units of m w0^2 / A^2
            sref.append(k3_start)
            sscale.append(k3_scale)
            slo.append(-math.inf)
    return JointArrays(tau=np.array(rows["tau"]), x=np.array(rows["x"]),
                       weight=np.array(rows["weight"]), span=spans, ref=ref,
                       scale=np.array(rows["scale"]), lo=lo, start=np.array(rows["start"]),
                       sref=np.array(sref), sscale=np.array(sscale), slo=np.array(slo),
                       m=osc["m"], g=osc["g"], k3=k3_start)

def _restart(a: JointArrays, out: JointCore, lay: Layout, spec, consts) -> JointArrays:
    """The arrays of a joint fit restarted from ``out``'s optimum (reference points moved)."""
    P = np.asarray(out.P)
    k3 = float(out.k3)
    c = consts._replace(k3=None if lay.k3 == "none" else k3)
    ref = np.array(a.ref)
    lo = np.array(a.lo)
    for j in range(lay.n_runs):
        q = spec.to_coords(TraceParams(*(jnp.asarray(v) for v in P[j])), c)
        for i, name in enumerate(COORDS):
            v = float(getattr(q, name))
            if name in DAMPING and math.isfinite(lo[j, i]):
                fl = ref[j, i] * math.exp(lo[j, i]) * 1e6
                v = max(v, fl)
                lo[j, i] = math.log(1e-6 * fl / v)
            ref[j, i] = v
    sref = np.array(a.sref)
    slo = np.array(a.slo)
    for i, name in enumerate(lay.shared):
        v = float(np.asarray(out.p)[i])
        if name in DAMPING:
            fl = sref[i] * math.exp(slo[i]) * 1e6
            v = max(v, fl)
            slo[i] = math.log(1e-6 * fl / v)
        sref[i] = v
    scale = np.array(a.scale)
    for j in range(lay.n_runs):
        scale[j, 6] = float(spec.y_scale(P[j, 3], scale[j, 5]))
    return a._replace(ref=ref, lo=lo, start=P, sref=sref, slo=slo, scale=scale,
                      k3=k3 if lay.k3 != "none" else a.k3)
