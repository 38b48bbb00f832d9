"""The start of a joint fit (``_joint``, where the method is described): each run's single
fit, the start of the joint problem (each run's start, the weights, the candidates for the
shared constants, the padded arrays) and the arrays of a restart; the joint optimisation
itself is ``_joint_search``'s."""

from __future__ import annotations

import math
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._core import (
    FIT_MODELS,
)
from ._joint_problem import (
    COORDS,
    JointArrays,
    JointCore,
    Layout,
)
from ._params import (
    DAMPING,
    FREE,
    Constants,
    TraceParams,
    check_free,
    damping_floors,
)
from ._pipeline import INNER, run
from ._problem import Settings, bucket, pad, prepare


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
