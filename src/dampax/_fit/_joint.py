"""Joint fits of several runs of one apparatus (issue 25, item 2): shared damping constants.

``fit([run1, run2, ...], shared=("b", "D"))`` fits the damping constants named in ``shared``
(and, when named, a shared w0 and a shared cubic stiffness k3) together with each run's own
start (x0, v0 at its window's start), offset and, for the constants not shared, its own values,
as ONE least-squares problem (docs/DESIGN.md, fitting):

    min  sum_j sum_i ((model(t_ij - t0_j; shared, local_j) - x_ij) / sigma_j)^2,

with sigma_j each run's noise level (the rms of its single fit), so runs of different noise
weigh as their information does. The runs are padded to one length with a mask, and the model
is vmapped over them: one compiled program per number of runs, padded length and parameter
layout, whatever the lengths of the runs.

Starts: each run is first fitted alone by :func:`~dampax._fit._api.fit` (its window, guesses,
global starts: the single-fit machinery). The shared constants start from a batch of
n_runs + 1 candidates, the median of the single fits and each single fit's own values (with few
runs one poor single fit spoils the median), optimised together in one vmapped call of the
approximate model; the lowest converged cost goes on to the exact model. From each start, each
run's own coordinates are first fitted with the shared ones held (a run whose single fit was
poor gets a start consistent with the shared constants). The optimizer is optimistix
Levenberg-Marquardt in the internal coordinates of ``_params`` (log coordinates for the damping
constants, natural scales for the rest; the model's own velocity coordinate y), in rounds that
rescale the log coordinates (as the single fit); a round that ends non-finite or with a higher
cost is not taken, and an exact-model fit whose step budget ran out continues from where it
stopped (:data:`CONTINUATIONS`).

Intervals: the AR(1)-prewhitened HAC sandwich of ``_intervals`` (cov = H^-1 S H^-1 with
H = J^T J of the joint Jacobian in the physical parameters and S the sum over runs of each run's
prewhitened score covariance: the runs' noises are independent, each may be correlated in time).

For other samplers (the posterior): :meth:`JointResult.problem` returns the joint problem as a
:class:`JointProblem`, the layout of the joint parameter vector and a pure residual function of
it (jit / grad-able).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._trace import Trace, load_trace
from ._api import _swings_bucket
from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    MAX_STEPS,
    MODELS,
    ReferenceOptions,
)
from ._joint_problem import (
    CONTINUATIONS,
    COORDS,
    SHARED,
    JointArrays,
    JointCore,
    Layout,
    best_start,
    run_joint_batch,
    run_joint_core,
)
from ._joint_result import JointResult, _result
from ._options import LeastSquares, Window
from ._params import (
    DAMPING,
    FREE,
    Constants,
    TraceParams,
    check_choice,
    check_free,
    damping_floors,
    oscillator_values,
)
from ._pipeline import INNER, run
from ._problem import Settings, bucket, pad, prepare, units_of

# ----------------------------------------------------------------------------------------------
# the public function


def _per_run(value, n, name):
    """A per-run list of an argument that is either one value or a list of n."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ValueError(f"{name}: give one value or one per run ({n}), got {len(value)}")
        return list(value)
    return [value] * n


def _loaded(item, j):
    """A run's file read into a Trace (errors name ``traces[j]``); anything else as it is."""
    if not isinstance(item, (str, Path)):
        return item
    try:
        return load_trace(item)
    except ValueError as err:
        raise ValueError(f"traces[{j}]: {err}") from err


def _common_unit(runs, units) -> str:
    """The position unit of every run: ``units`` when given, else each run's own (the unit in
    its position column's name); ValueError naming ``traces`` when the runs' units differ
    (a shared D in kg/m, or mu, means one length unit: m and mm gave one D, wrong for one of
    them).

    Arguments:
        runs: the runs (Trace objects or arrays).
        units: Window.units (None: from each run).

    Returns:
        The unit.
    """
    found = [units_of(tr, units) for tr in runs]
    if len(set(found)) > 1:
        listed = ", ".join(f"traces[{j}]: {u!r}" for j, u in enumerate(found))
        raise ValueError(f"traces: the runs' positions are in different units ({listed}); "
                         "shared constants need one unit: read them in one unit (load_trace("
                         "scale=1e-3) turns mm into m) and pass Window(units=...)")
    return found[0]


def _run_input(item, j):
    """(trace_or_t, x) of one run: a Trace, a path, or a pair (t, x)."""
    if isinstance(item, (Trace, str, Path)):
        return item, None
    if isinstance(item, (list, tuple)) and len(item) == 2:
        return item[0], item[1]
    raise ValueError(f"traces[{j}]: give a dampax.Trace, a file path or a pair (t, x), got "
                     f"{type(item).__name__}")


def check_shared(shared, free, *, fit_omega0: bool, k3) -> tuple[tuple, tuple]:
    """(shared, free) of a joint fit: ``shared`` among :data:`SHARED` (a comma list or a
    tuple; default: the free damping constants), the free damping constants including the
    shared ones.

    Raises:
        ValueError: an unknown or repeated name, a shared w0 without ``fit_omega0``, k3 both
            shared and held, or "k3" in ``free`` (a joint fit fits k3 only as shared).
    """
    free = check_free(free, allowed=DAMPING + ("k3",))
    if "k3" in free:
        raise ValueError("free: a joint fit fits k3 as one constant of all runs: name it in "
                         "shared=(..., 'k3'), not in free")
    if shared is None:
        shared = free
    if isinstance(shared, str):
        shared = tuple(s.strip() for s in shared.split(",") if s.strip())
    shared = tuple(shared)
    bad = [s for s in shared if s not in SHARED]
    if bad or len(set(shared)) != len(shared) or not shared:
        raise ValueError(f"shared must name distinct parameters among {SHARED}, got "
                         f"{shared!r}")
    if "w0" in shared and not fit_omega0:
        raise ValueError("shared: 'w0' is shared only when it is fitted (fit_omega0=True, or "
                         "no oscillator)")
    if "k3" in shared and k3 is not None:
        raise ValueError("shared: 'k3' is fitted; do not also pass a fixed k3")
    free = tuple(n for n in DAMPING if n in free or n in shared)
    return tuple(n for n in SHARED if n in shared), free


def fit_joint(traces, *, shared=None, free=("mu", "D"), oscillator=None, model: str = "ansatz",
              fit_omega0: bool | None = None, offset: bool = True, start="auto", end=None,
              loss: str = "linear", optimizer: str = "lm", max_steps: int | None = None,
              rtol: float = 1e-8, atol: float = 1e-10, max_swings: int | None = None,
              units: str | None = None, starts: int = 32, seed: int = 0,
              k3: float | None = None) -> JointResult:
    """Fit several runs of one apparatus together: shared damping constants (eq. 3), each run
    with its own start, offset and window, as one vmapped least-squares problem.

    Arguments:
        traces: two or more runs: :class:`Trace` objects, file paths or pairs (t, x).
        shared: the parameters common to all runs, among "mu", "b", "D", "w0" and "k3"
            (a tuple or a comma list; default: the free damping constants). A shared damping
            constant is fitted even when not in ``free``; "w0" needs a fitted w0; "k3" fits
            one cubic stiffness for all runs (a parameter of the joint problem, not profiled).
        free: the damping constants fitted; those not shared are fitted per run.
        oscillator, model, fit_omega0, offset, units, starts, seed, k3: as in
            :func:`~dampax._fit._api.fit` (the same for every run).
        start, end: each run's window, as in ``fit``: one value or one per run.
        loss, optimizer: "linear" and "lm" (the joint fit is least squares).
        max_steps, rtol, atol: the joint optimizer's budget and tolerances.
        max_swings: the reference model's budget (default from the longest window).

    Returns:
        A :class:`JointResult`.

    Raises:
        ValueError: fewer than two runs, bad arguments (named), or a run without a free decay
            in it (its index and the reason named).
    """

    if not isinstance(traces, (list, tuple)) or len(traces) < 2:
        raise ValueError("traces: a joint fit needs a list of two or more runs")
    check_choice("model", model, MODELS)
    if loss != "linear":
        raise ValueError(f"loss: a joint fit is least squares ('linear'), got {loss!r}")
    if optimizer != "lm":
        raise ValueError(f"optimizer: a joint fit uses 'lm', got {optimizer!r}")
    # the settings checked once, here (dp.fit hands a list of runs over unchecked)
    checked = LeastSquares(loss=loss, optimizer=optimizer, rtol=rtol, atol=atol,
                           max_steps=max_steps, starts=starts, seed=seed,
                           max_swings=max_swings).checked()
    max_steps, starts, max_swings = checked.max_steps, checked.starts, checked.max_swings
    units = Window(units=units).checked().units
    per_mass = oscillator is None
    if fit_omega0 is None:
        fit_omega0 = per_mass
    shared, free = check_shared(shared, free, fit_omega0=bool(fit_omega0), k3=k3)
    n_runs = len(traces)
    starts_at = _per_run(start, n_runs, "start")
    ends_at = _per_run(end, n_runs, "end")
    for s_at, e_at in zip(starts_at, ends_at, strict=True):  # finite, ordered, as a single fit
        Window(start=s_at, end=e_at)
    spec = FIT_MODELS[model]
    first = spec.start_from or model
    osc = oscillator_values(oscillator)
    runs = [_run_input(item, j) for j, item in enumerate(traces)]
    runs = [(_loaded(tr, j), x) for j, (tr, x) in enumerate(runs)]
    unit = _common_unit([tr for tr, _ in runs], units)
    singles = []
    # each run alone (its window, guesses, global starts): the starts of the joint fit
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for j, (tr, x) in enumerate(runs):
            try:
                res = run(prepare(tr, x, Settings(
                    oscillator=oscillator, free=check_free(free, allowed=FREE), model=first,
                    fit_omega0=fit_omega0, offset=offset, start=starts_at[j], end=ends_at[j],
                    units=units, starts=starts, seed=seed, k3=k3)), INNER)
            except ValueError as err:
                raise ValueError(f"traces[{j}]: {err}") from err
            singles.append(res)
    notes = sorted({str(w.message) for w in caught})
    # each run's start: its single fit (where that is not finite, a start from its data)
    own, usable = _start_params(singles, osc)
    # the common start of the shared constants: the median of the single fits
    start_vals = {n: float(np.median([p[n] for p in own])) for n in shared if n != "k3"}
    lay_local = tuple(c for c in COORDS if c not in shared and (
        (c in DAMPING and c in free) or (c == "w0" and fit_omega0)
        or (c == "offset" and offset) or c in ("x0", "y")))
    k3_mode = "shared" if "k3" in shared else ("fixed" if k3 is not None else "none")
    lay = Layout(model=model, n_runs=n_runs, shared=shared, local=lay_local, k3=k3_mode)
    n_max = max(s.t.size for s in singles)
    n_pad = bucket(n_max)
    sigma = np.array([_noise_level(s) for s in singles])
    w0s = [start_vals.get("w0", p["w0"]) for p in own]
    amp = np.array([math.hypot(p["x0"], p["v0"] / w) for p, w in zip(own, w0s, strict=True)])
    k3_start = 0.0 if k3 is None else float(k3)
    k3_scale = float(osc["m"] * np.median(w0s) ** 2 / np.median(amp) ** 2)
    consts = Constants(m=osc["m"], g=osc["g"], k3=None if k3_mode == "none" else k3_start)
    # the starts of the shared constants: the median of the single fits and each single
    # fit's own values (a poor single fit spoils the median of few runs); all optimised in
    # one vmapped batch with the approximate model, the best one goes on
    candidates = [start_vals] + [{n: float(p[n]) for n in start_vals} if ok else start_vals
                                 for p, ok in zip(own, usable, strict=True)]
    batch = [_arrays(singles, own, FIT_MODELS[first], lay, consts, sv, sigma, amp, n_pad,
                     osc=osc, k3_start=k3_start, k3_scale=k3_scale) for sv in candidates]
    spans = np.asarray(batch[0].span)
    opts = None
    if spec.integrates:
        longest = int(np.argmax(spans))
        opts = ReferenceOptions(_swings_bucket(max_swings, singles[longest].t,
                                               max(w0s)), 1e-8, 1e-10)
    steps = int(max_steps or MAX_STEPS["lm"])
    stages = []
    approx = Layout(model=first, n_runs=n_runs, shared=shared, local=lay_local, k3=k3_mode)
    outs = run_joint_batch(jax.tree_util.tree_map(lambda *v: np.stack(v), *batch), lay=approx,
                           opts=None if spec.start_from else opts, max_steps=steps,
                           rtol=float(rtol), atol=float(atol))
    best = best_start(outs)
    arrays = batch[best]
    out0 = jax.tree_util.tree_map(lambda v: v[best], outs)
    which = "the median of the single fits" if best == 0 else f"run {best - 1}'s single fit"
    stages.append(f"{len(batch)} starts of the shared constants, the best from {which}")
    if spec.start_from:  # the approximate model's joint optimum first
        arrays = _restart(arrays, out0, lay, spec, consts)
        stages.append(f"started from the joint {first} fit ({int(out0.steps)} steps)")
        out = run_joint_core(arrays, lay=lay, opts=opts, max_steps=steps, rtol=float(rtol),
                             atol=float(atol))
        # a budget ran out on the way (the approximate optimum far from the exact one):
        # continue from where it stopped, with the same compiled program
        for _ in range(CONTINUATIONS):
            if out.code != FIT_RESULTS.max_steps_reached:
                break
            arrays = _restart(arrays, out, lay, spec, consts)
            done = int(out.steps)
            out = run_joint_core(arrays, lay=lay, opts=opts, max_steps=steps,
                                 rtol=float(rtol), atol=float(atol))
            stages.append(f"continued after {done} steps")
    else:
        out = out0
    return _result(out, arrays, lay, singles, sigma, free=free, model=model, unit=unit,
                   per_mass=per_mass, fit_omega0=bool(fit_omega0), opts=opts, stages=stages,
                   notes=notes, osc=osc)



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
    its single fit's optimum: where that has a non-finite value, the run starts from its
    data (offset the median, x0 the first sample about it, v0 the slope of the first samples)
    with w0 and the damping constants at the median of the finite single fits."""
    fields = TraceParams._fields
    usable = [all(math.isfinite(float(s.params[n])) for n in fields) for s in singles]
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
        p = {n: (float(s.params[n]) if math.isfinite(float(s.params[n])) else med[n])
             for n in fields}
        if not p["w0"] > 0:
            p["w0"] = med["w0"]
        off = float(np.median(x))
        k = max(2, min(x.size, int(0.1 * 2 * math.pi / p["w0"] / max(t[1] - t[0], 1e-300))))
        p.update(offset=off, x0=float(x[0] - off),
                 v0=float(np.polyfit(t[:k] - t[0], x[:k], 1)[0]))
        out.append(p)
    return out, usable


def _arrays(singles, own, spec, lay: Layout, consts, start_vals, sigma, amp, n_pad, *, osc,
            k3_start, k3_scale) -> JointArrays:
    """The arrays of a joint fit started from each run's start ``own`` (the shared parameters
    at ``start_vals``), in the coordinates of the fit model ``spec``."""

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
                lo.append(math.log(1e-6 * fl / v))
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

