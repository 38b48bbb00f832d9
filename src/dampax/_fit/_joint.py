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

import functools
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._cache import call_cached_tree
from .._oscillator import is_concrete
from .._solution import result_where
from .._trace import Trace
from . import _intervals
from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    MAX_STEPS,
    MODELS,
    CoreResult,
    ReferenceOptions,
    _materialised,
    _result_code,
)
from ._guess import analyse
from ._params import (
    DAMPING,
    Constants,
    TraceCoords,
    TraceParams,
    check_choice,
    check_free,
    damping_floors,
    oscillator_values,
    unit_of,
    vary_mask,
)
from ._result import FitContext, build_result

#: what ``shared`` may name: the damping constants, the angular frequency and the cubic
#: stiffness (in this order in the joint parameter vector)
SHARED = DAMPING + ("w0", "k3")
#: the model coordinates of a run, the layout of the internal per-run blocks
COORDS = TraceCoords._fields
#: Levenberg-Marquardt rounds (rescaling the log coordinates between them)
ROUNDS = 3
#: restarts of the exact model's joint fit from where its step budget ran out
CONTINUATIONS = 2


# ----------------------------------------------------------------------------------------------
# the static layout of a joint problem


class Layout(NamedTuple):
    """The static layout of a joint fit (hashable: part of the compiled program's key).

    Attributes:
        model: the fit model's name.
        n_runs: number of runs.
        shared: the shared parameters, a subset of :data:`SHARED` in its order.
        local: the model coordinates fitted per run (among :data:`COORDS`, in its order).
        k3: "none" (the linear spring), "fixed" (held at a value) or "shared" (fitted).
    """

    model: str
    n_runs: int
    shared: tuple
    local: tuple
    k3: str

    def names(self) -> list[str]:
        """Names of the joint physical parameters: the shared ones, then ``name[j]`` per run
        (v0 for the velocity coordinate y)."""
        per = [("v0" if c == "y" else c) for c in self.local]
        return list(self.shared) + [f"{c}[{j}]" for j in range(self.n_runs) for c in per]

    @property
    def size(self) -> int:
        return len(self.shared) + self.n_runs * len(self.local)


class JointArrays(NamedTuple):
    """The arrays of a joint problem (a pytree; runs along the first axis).

    Attributes:
        tau, x, weight: times from each run's window start, data, weight 1/sigma_j per sample
            (0 on the padding), shape (N, n_pad).
        span: window lengths (N,).
        ref, scale, lo: per-run reference model coordinates (the start), scales of the internal
            coordinates and lower bounds of the damping log coordinates (N, 7) in the order of
            :data:`COORDS`.
        start: per-run physical parameters at the start, :data:`~dampax._fit._params.PARAMS`
            order (N, 7): the values of the fixed parameters.
        sref, sscale, slo: reference, scale and lower bound of the shared coordinates (S,).
        m, g, k3: mass, g and the cubic stiffness (its value when fixed, its start when
            shared; 0 for the linear spring).
    """

    tau: Any
    x: Any
    weight: Any
    span: Any
    ref: Any
    scale: Any
    lo: Any
    start: Any
    sref: Any
    sscale: Any
    slo: Any
    m: Any
    g: Any
    k3: Any


def _consts(lay: Layout, a: JointArrays, k3):
    return Constants(m=a.m, g=a.g, k3=None if lay.k3 == "none" else k3)


def _k3_of(lay: Layout, a: JointArrays, values):
    """The cubic stiffness: fitted (its entry of the shared ``values``) or ``a.k3``."""
    if lay.k3 == "shared":
        return values[lay.shared.index("k3")]
    return a.k3


def _shared_values(lay: Layout, a: JointArrays, th_s):
    """Physical values of the shared parameters from their internal coordinates."""
    out = []
    for i, name in enumerate(lay.shared):
        if name in DAMPING:
            out.append(a.sref[i] * jnp.exp(jnp.maximum(th_s[i], a.slo[i])))
        else:
            out.append(a.sref[i] + a.sscale[i] * th_s[i])
    return out


def coords_of(theta, lay: Layout, a: JointArrays):
    """(model coordinates (N, 7) in the order of :data:`COORDS`, k3) of the internal vector."""
    S = len(lay.shared)
    th_s = theta[:S]
    th_l = theta[S:].reshape(lay.n_runs, len(lay.local))
    values = _shared_values(lay, a, th_s)
    cols = []
    for i, name in enumerate(COORDS):
        if name in lay.shared:
            col = jnp.broadcast_to(values[lay.shared.index(name)], (lay.n_runs,))
        elif name in lay.local:
            th = th_l[:, lay.local.index(name)]
            if name in DAMPING:
                col = a.ref[:, i] * jnp.exp(jnp.maximum(th, a.lo[:, i]))
            else:
                col = a.ref[:, i] + a.scale[:, i] * th
        else:
            col = a.ref[:, i]
        cols.append(col)
    return jnp.stack(cols, axis=1), _k3_of(lay, a, values)


def _curves(q, k3, lay: Layout, a: JointArrays, opts):
    """The model of every run at its times (N, n_pad), q the model coordinates (N, 7)."""
    spec = FIT_MODELS[lay.model]
    consts = _consts(lay, a, k3)

    def one(tau, qj, span):
        return spec.curve(tau, TraceCoords(*(qj[i] for i in range(7))), consts, span, opts)

    return jax.vmap(one)(a.tau, q, a.span)


def _residuals(theta, a: JointArrays, lay: Layout, opts):
    """The weighted residuals (model - data)/sigma_j of every run, flat (masked)."""
    q, k3 = coords_of(theta, lay, a)
    r = (_curves(q, k3, lay, a, opts) - a.x) * a.weight
    return jnp.where(a.weight > 0.0, r, 0.0).reshape(-1)


def params_of(theta, lay: Layout, a: JointArrays):
    """(physical parameters (N, 7) in the order of PARAMS, k3) of the internal vector."""
    spec = FIT_MODELS[lay.model]
    q, k3 = coords_of(theta, lay, a)
    consts = _consts(lay, a, k3)

    def one(qj):
        return jnp.stack(list(spec.to_params(TraceCoords(*(qj[i] for i in range(7))), consts)))

    return jax.vmap(one)(q), k3


def _physical_vector(P, k3, lay: Layout):
    """The joint physical vector (layout :meth:`Layout.names`) from per-run parameters."""
    shared = [k3 if name == "k3" else P[0, TraceParams._fields.index(name)]
              for name in lay.shared]
    per = [TraceParams._fields.index("v0" if c == "y" else c) for c in lay.local]
    local = P[:, jnp.array(per, dtype=int)].reshape(-1) if per else jnp.zeros(0)
    return jnp.concatenate([jnp.stack(shared) if shared else jnp.zeros(0), local])


def _unpack(p, lay: Layout, a: JointArrays):
    """(per-run physical parameters (N, 7) in PARAMS order, k3) from the joint physical vector
    ``p`` (layout :meth:`Layout.names`); fixed parameters at their start values."""
    S = len(lay.shared)
    per = p[S:].reshape(lay.n_runs, len(lay.local))
    cols = []
    for i, name in enumerate(TraceParams._fields):
        coord = "y" if name == "v0" else name
        if name in lay.shared:
            cols.append(jnp.broadcast_to(p[lay.shared.index(name)], (lay.n_runs,)))
        elif coord in lay.local:
            cols.append(per[:, lay.local.index(coord)])
        else:
            cols.append(a.start[:, i])
    k3 = p[lay.shared.index("k3")] if lay.k3 == "shared" else a.k3
    return jnp.stack(cols, axis=1), k3


def physical_residuals(p, a: JointArrays, lay: Layout, opts):
    """model - data (data units, (N, n_pad), 0 on the padding) of the joint physical vector
    ``p`` (layout :meth:`Layout.names`; v0 per run, as the single fit reports it)."""
    spec = FIT_MODELS[lay.model]
    P, k3 = _unpack(p, lay, a)
    consts = _consts(lay, a, k3)

    def one(pj):
        return spec.to_coords(TraceParams(*(pj[i] for i in range(7))), consts)

    q = jax.vmap(one)(P)
    q = jnp.stack(list(q), axis=1)
    r = _curves(q, k3, lay, a, opts) - a.x
    return jnp.where(a.weight > 0.0, r, 0.0)


# ----------------------------------------------------------------------------------------------
# the compiled core: optimise, then the Jacobian in the physical parameters


class JointCore(NamedTuple):
    """Output of :func:`joint_core` (arrays)."""

    p: Any          # the joint physical vector at the optimum
    P: Any          # per-run physical parameters (N, 7)
    q: Any          # per-run model coordinates (N, 7)
    k3: Any
    code: Any
    steps: Any
    jac: Any        # d r / d p of the weighted residual rows, (N, n_pad, size)
    resid: Any      # the weighted residual rows (N, n_pad)
    curve: Any      # the model (N, n_pad)


def _log_info(lay: Layout, a: JointArrays):
    """(is_log, reference, lower bound) per entry of the internal vector."""
    is_log = [name in DAMPING for name in lay.shared]
    dref = [a.sref[i] for i in range(len(lay.shared))]
    lo = [a.slo[i] for i in range(len(lay.shared))]
    for j in range(lay.n_runs):
        for c in lay.local:
            i = COORDS.index(c)
            is_log.append(c in DAMPING)
            dref.append(a.ref[j, i])
            lo.append(a.lo[j, i])
    return jnp.array(is_log, dtype=bool), jnp.stack(dref), jnp.stack(lo)


def joint_core(a: JointArrays, *, lay: Layout, opts, max_steps: int, rtol: float,
               atol: float) -> JointCore:
    """The joint fit, pure: Levenberg-Marquardt in ``ROUNDS`` rounds, then the physical
    Jacobian. ``lay``, ``opts`` and the budget are static."""
    size = lay.size
    fn = _materialised(functools.partial(_residuals, lay=lay, opts=opts), a)
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    is_log, dref, lo = _log_info(lay, a)
    per_round = max(int(max_steps) // ROUNDS, 1)

    def cost(theta):
        r = fn(theta, a)
        return jnp.sum(r * r)

    def solve(theta, scale):
        def scaled(u, args):
            return fn(theta + scale * u, args)

        sol = optx.least_squares(scaled, solver, jnp.zeros_like(theta), args=a,
                                 max_steps=per_round, throw=False)
        th = theta + scale * sol.value
        th = jnp.where(is_log, jnp.maximum(th, lo), th)
        # a round that ends non-finite or above its start is not taken (its code says so)
        c0, c1 = cost(theta), cost(th)
        keep = jnp.all(jnp.isfinite(th)) & jnp.isfinite(c1) & ~(c1 > c0)
        code = result_where(keep, _result_code(sol.result), FIT_RESULTS.failed)
        return jnp.where(keep, th, theta), sol.stats["num_steps"], code

    # first each run's own coordinates with the shared ones held at the start: a run whose
    # single fit was poor gets a start consistent with the shared constants
    local_only = jnp.concatenate([jnp.zeros(len(lay.shared)), jnp.ones(size - len(lay.shared))])
    theta0, steps0, _ = solve(jnp.zeros(size), local_only)

    def one(carry, _):
        theta, scale, steps, code, redo = carry
        again = (steps == 0) | (code != FIT_RESULTS.successful) | redo
        theta, n_steps, code = jax.lax.cond(again, solve, lambda th, sc: (th, 0, code),
                                            theta, scale)
        J, r = jax.jacfwd(lambda th: (_residuals(th, a, lay, opts),) * 2, has_aux=True)(theta)
        # Gauss-Newton step in the physical damping constants: one it sends to <= 0 goes to
        # its lower bound (the single fit's rounds, ``_core._lm_rounds``)
        p = dref * jnp.exp(theta)
        Jx = jnp.where(is_log, J / p, J)
        step = jnp.linalg.lstsq(Jx, -r)[0]
        snap = is_log & (p + step <= 0.0) & (theta > lo + 1.0)
        theta = jnp.where(snap, lo + 1.0, theta)
        cn = jnp.sqrt(jnp.sum(J * J, axis=0))
        ref = jnp.max(jnp.where(~is_log, cn, 0.0))
        safe = jnp.where(cn > 0.0, cn, 1.0)
        new = jnp.where(is_log & (cn > 0.0), jnp.clip(ref / safe, 1.0, 1e15), 1.0)
        ratio = new / scale
        redo = jnp.any(snap) | jnp.any((ratio > 10.0) | (ratio < 0.1))
        return (theta, new, steps + n_steps, code, redo), None

    init = (theta0, jnp.ones(size), jnp.asarray(steps0), FIT_RESULTS.successful,
            jnp.array(True))
    (theta, _, steps, code, _), _ = jax.lax.scan(one, init, None, length=ROUNDS)
    P, k3 = params_of(theta, lay, a)
    q, _ = coords_of(theta, lay, a)
    p = _physical_vector(P, k3, lay)

    def rows(pv):
        r = physical_residuals(pv, a, lay, opts)
        return r * a.weight, r

    J, r = jax.jacfwd(rows, has_aux=True)(p)
    curve = r + a.x
    return JointCore(p=p, P=P, q=q, k3=k3, code=code, steps=steps, jac=J,
                     resid=r * a.weight, curve=curve)


def run_joint_core(a: JointArrays, **static) -> JointCore:
    """:func:`joint_core` through a kept program (``_cache.call_cached_tree``) when eager."""
    a = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), a)
    if is_concrete(a):
        return call_cached_tree("fit-joint", sorted(static.items()),
                                functools.partial(joint_core, **static), a)
    return joint_core(a, **static)


def run_joint_batch(batch: JointArrays, **static) -> JointCore:
    """:func:`joint_core` vmapped over a batch of starts (every leaf of ``batch`` with a
    leading batch axis), through a kept program when eager."""
    batch = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), batch)
    fn = jax.vmap(functools.partial(joint_core, **static))
    if is_concrete(batch):
        return call_cached_tree("fit-joint-batch", sorted(static.items()), fn, batch)
    return fn(batch)


def best_start(out: JointCore) -> int:
    """Index of the best start of a batch: the lowest weighted cost among the converged
    ones with finite values (else among the finite ones; else the first)."""
    cost = np.sum(np.asarray(out.resid, dtype=float) ** 2, axis=1).sum(axis=1)
    finite = np.isfinite(cost) & np.all(np.isfinite(np.asarray(out.p)), axis=1)
    ok = finite & (np.asarray(out.code._value) == FIT_RESULTS.successful._value)
    for pick in (ok, finite):
        if pick.any():
            return int(np.argmin(np.where(pick, cost, np.inf)))
    return 0


# ----------------------------------------------------------------------------------------------
# intervals: the runs' score covariances summed


def score_covariance(J: np.ndarray, r: np.ndarray, period_samples: float) -> np.ndarray:
    """S of the AR(1)-prewhitened HAC sandwich of one run (``_intervals.hac_covariance``,
    whose H^-1 S H^-1 it completes): the scores of the prewhitened residuals, with the
    Bartlett kernel only where those are not white.

    Arguments:
        J, r: the run's rows of the joint Jacobian (n x p) and its residuals (n).
        period_samples: samples per oscillation period.
    """
    n = r.size
    phi = float(np.dot(r[1:], r[:-1]) / max(np.dot(r, r), 1e-300)) if n > 2 else 0.0
    phi = min(max(phi, -0.99), 0.999)
    e = np.empty_like(r)
    e[0] = math.sqrt(1.0 - phi * phi) * r[0]
    e[1:] = r[1:] - phi * r[:-1]
    K = _intervals._backward_ar1(np.ascontiguousarray(J), phi)
    K[0] = K[0] / math.sqrt(1.0 - phi * phi)
    g = K * e[:, None]
    if _intervals.whiteness_p(e, period_samples) >= _intervals.WHITE_P:
        L = 0
    else:
        L = _intervals.bandwidth(g, period_samples)
    L = min(L, g.shape[0] - 1)
    G = _intervals._autocov(g, L)
    w = 1.0 - np.arange(L + 1) / (L + 1.0)
    return w[0] * G[0] + np.einsum("l,lij->ij", w[1:], G[1:] + np.transpose(G[1:], (0, 2, 1)))


def _inverse(H):
    if not np.all(np.isfinite(H)):  # a Jacobian with NaN in it: no intervals (named failure)
        return np.full_like(H, np.nan)
    d = np.sqrt(np.where(np.diag(H) > 0, np.diag(H), 1.0))
    return np.linalg.pinv(H / np.outer(d, d)) / np.outer(d, d)


# ----------------------------------------------------------------------------------------------
# the result


class JointProblem(NamedTuple):
    """The joint least-squares problem, for samplers (the posterior) built on it.

    Attributes:
        names: the joint physical parameters (:meth:`Layout.names`): the shared ones, then
            ``name[j]`` per run (x0, v0 at the run's window start, offset, its own constants).
        p0: their values at the joint optimum.
        residuals: ``residuals(p)`` -> model - data of every run, (n_runs, n_pad), data units,
            0 on the padding; pure (jit / grad / vmap-able).
        mask: (n_runs, n_pad) booleans, the samples that are data.
        t, x: each run's window (padded), absolute times.
        sigma: each run's noise level (the rms of its single fit).
        nonneg: the names that are >= 0 (damping constants).
        residual, args: the same residuals as a hashable callable ``residual(p, args)`` (a
            :class:`JointResidual`, data - model) and its arrays (a :class:`JointArrays`),
            for compiled samplers that take the function as a static argument.
    """

    names: list
    p0: np.ndarray
    residuals: Any
    mask: np.ndarray
    t: np.ndarray
    x: np.ndarray
    sigma: np.ndarray
    nonneg: tuple
    residual: Any = None
    args: Any = None


@dataclass(frozen=True)
class JointResidual:
    """data - model of every run, (n_runs, n_pad), 0 on the padding, of the joint physical
    vector p (layout :meth:`Layout.names`): :func:`physical_residuals` with the sign of the
    posterior's residuals; static and hashable (the joint layout and the reference options).

    Attributes:
        layout: the joint :class:`Layout`.
        opts: the reference integrator's budget and tolerances (None for the ansatz).
    """

    layout: Layout
    opts: Any = None

    def __call__(self, p, args: JointArrays):
        return -physical_residuals(p, args, self.layout, self.opts)


@dataclass
class JointResult:
    """Result of a joint fit of several runs (:func:`fit_joint`, ``fit([run1, run2, ...])``).

    Attributes:
        names: the joint parameters (the shared ones, then ``name[j]`` per run).
        values: their fitted values (dict).
        stderr: delta-method standard errors (dict).
        covariance: the HAC covariance over ``names`` (what :meth:`conf_interval` uses).
        shared: the shared parameter names; ``params`` their values.
        runs: one ``FitResult`` per run at the joint optimum (its window, residuals,
            checks; its own ``conf_interval`` uses that run's data alone).
        singles: the single fits of the runs (the starts), for comparison.
        success, converged, reason: the joint fit can be trusted: the optimizer converged,
            every standard error is finite and no run's checks failed; ``reason`` says why not.
        adequate: the model describes every run.
        chisqr: sum of the weighted squared residuals; ndata, nvarys.
        sigma: each run's noise level (the weights 1/sigma).
    """

    names: list
    values: dict
    stderr: dict
    covariance: np.ndarray
    delta_covariance: np.ndarray
    shared: tuple
    free: tuple
    runs: list
    singles: list
    success: bool
    converged: bool
    reason: str
    adequate: bool
    message: str
    n_iterations: int
    chisqr: float
    ndata: int
    nvarys: int
    sigma: np.ndarray
    model: str
    per_mass: bool
    units: str
    fit_omega0: bool
    warnings: list = field(default_factory=list)
    _problem: Any = field(default=None, repr=False)

    @property
    def params(self) -> dict:
        """The shared parameters' values."""
        return {n: self.values[n] for n in self.shared}

    @property
    def hac_stderr(self) -> dict:
        """Standard errors from the HAC covariance (allowing for correlated residuals)."""
        sd = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {n: float(v) for n, v in zip(self.names, sd, strict=True)}

    @property
    def rms(self) -> list:
        """Each run's rms residual (data units)."""
        return [r.rms for r in self.runs]

    def conf_interval(self, level: float = 0.95, *, runs: bool = False) -> dict:
        """Confidence intervals {name: (lo, hi)} of the shared parameters (and with ``runs``
        every run's own) from the HAC covariance (``_intervals``: AR(1)-prewhitened sandwich,
        the runs' noises independent), value +- z sd, clipped at 0 for damping constants.

        Arguments:
            level: two-sided coverage, in (0, 1).
            runs: also the per-run parameters (``name[j]``).
        """
        names = self.names if runs else list(self.shared)
        sd = self.hac_stderr
        nonneg = tuple(n for n in names if n.split("[")[0] in DAMPING)
        return _intervals.normal_intervals({n: self.values[n] for n in names}, sd, level,
                                           nonneg=nonneg)

    def problem(self) -> JointProblem:
        """The joint problem (layout and pure residual function) at this fit's optimum."""
        return self._problem

    def summary(self, level: float = 0.95) -> str:
        """A short table: the shared parameters with their intervals, each run's rms."""
        ci = self.conf_interval(level)
        hac = self.hac_stderr
        lines = [f"joint fit of {len(self.runs)} runs ({self.model}), shared: "
                 f"{', '.join(self.shared)}; success = {self.success}"
                 + (f" ({self.reason})" if self.reason else "")]
        for n in self.shared:
            unit = unit_of(n, self.units, self.per_mass)
            lines.append(f"  {n:<6} {self.values[n]:.6g} +/- {hac[n]:.3g}  "
                         f"{round(100 * level)} % [{ci[n][0]:.6g}, {ci[n][1]:.6g}] {unit}".rstrip())
        for j, r in enumerate(self.runs):
            lines.append(f"  run {j}: rms {r.rms:.4g} {self.units}, "
                         f"{r.ndata} samples from t = {r.t_start:.4g} s"
                         f"{'' if r.success else '  (checks: ' + r.reason + ')'}"
                         f"  {r.source}".rstrip())
        return "\n".join(lines)

    def report(self, level: float = 0.95) -> str:
        """The full report: statistics, the shared parameters with intervals beside the
        single fits' values, each run's parameters, rms and checks."""
        lines = []
        if not self.success:
            lines.append(f"FIT FAILED: {self.reason}")
        if not self.adequate:
            bad = [f"run {j}: " + "; ".join(r.inadequacy) for j, r in enumerate(self.runs)
                   if not r.adequate]
            lines.append("MODEL DOES NOT DESCRIBE THE DATA: " + " | ".join(bad))
        lines += ["[[Model]]",
                  f"    joint fit of {len(self.runs)} runs, model = {self.model!r}, shared = "
                  f"{', '.join(self.shared)}, free damping = {', '.join(self.free)}"]
        if self.per_mass:
            lines.append("    no oscillator given: w0 fitted, unit mass (m = 1 kg): b and D "
                         f"are per unit mass; positions in {self.units}")
        else:
            lines.append(f"    positions in {self.units}")
        lines += ["    each run has its own window, start (x0, v0), offset"
                  + ("" if "w0" in self.shared or not self.fit_omega0 else ", w0")
                  + "".join(f", {n}" for n in self.free if n not in self.shared)
                  + "; residuals weighted by 1/(rms of the run's single fit)",
                  "[[Fit Statistics]]",
                  f"    # iterations       = {self.n_iterations}",
                  f"    # data points      = {self.ndata}",
                  f"    # variables        = {self.nvarys}",
                  f"    weighted chi-square = {self.chisqr:.6g}",
                  f"    success            = {self.success} ({self.message})",
                  f"[[Shared]] value +/- HAC sd, {round(100 * level)} % interval "
                  "(HAC sandwich, AR(1)-prewhitened, summed over the runs); single fits beside"]
        ci = self.conf_interval(level)
        hac = self.hac_stderr
        for n in self.shared:
            singles = ", ".join(
                f"{s.params[n]:.4g}" if s is not None and n in s.params else "-"
                for s in self.singles)
            lines.append(f"    {n + ':':<7} {self.values[n]:.6g} +/- {hac[n]:.3g}  "
                         f"[{ci[n][0]:.6g}, {ci[n][1]:.6g}] "
                         f"{unit_of(n, self.units, self.per_mass)}   (single fits: {singles})")
        lines.append("[[Runs]]")
        for j, r in enumerate(self.runs):
            own = ", ".join(f"{n} = {r.params[n]:.5g}" for n in r.varied if n not in self.shared)
            lines.append(f"    run {j}: {r.source or '(arrays)'}")
            lines.append(f"      window {r.t_start:.5g}-{r.t[-1]:.5g} s ({r.ndata} samples), "
                         f"rms {r.rms:.4g} (weight 1/{self.sigma[j]:.4g}), "
                         f"checks {'pass' if r.success else 'FAIL: ' + r.reason}")
            lines.append(f"      {own}")
        for note in self.warnings:
            lines.append(f"[[Warning]] {note}")
        return "\n".join(lines)

    def to_dict(self, level: float = 0.95) -> dict:
        """JSON-ready summary."""
        def num(v):
            v = float(v)
            return v if math.isfinite(v) else None

        ci = self.conf_interval(level)
        return {
            "kind": "joint", "model": self.model, "shared": list(self.shared),
            "free": list(self.free), "params": {n: num(self.values[n]) for n in self.shared},
            "stderr": {n: num(self.stderr[n]) for n in self.shared},
            "hac_stderr": {n: num(v) for n, v in self.hac_stderr.items() if n in self.shared},
            "conf_interval": {"level": level, "intervals": {n: list(v) for n, v in ci.items()}},
            "values": {n: num(v) for n, v in self.values.items()},
            "success": bool(self.success), "converged": bool(self.converged),
            "reason": self.reason, "adequate": bool(self.adequate), "message": self.message,
            "statistics": {"chisqr": num(self.chisqr), "ndata": self.ndata,
                           "nvarys": self.nvarys, "n_iterations": self.n_iterations},
            "runs": [{"source": r.source, "rms": num(r.rms), "sigma": num(s),
                      "t_start": num(r.t_start), "ndata": r.ndata, "success": bool(r.success),
                      "reason": r.reason, "params": {k: num(v) for k, v in r.params.items()}}
                     for r, s in zip(self.runs, self.sigma, strict=True)],
            "per_mass": bool(self.per_mass), "units": self.units,
        }

    def plot(self, path, *, title: str | None = None):
        """Save a figure: each run's data and joint fit above, its residuals below."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from .._io import save_figure

        n = len(self.runs)
        fig = Figure(figsize=(10, 2.6 * n + 1.0), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(2 * n, 1, height_ratios=[3, 1] * n)
        for j, r in enumerate(self.runs):
            ax, axr = axes[2 * j], axes[2 * j + 1]
            ax.plot(r.t, r.x, color="tab:blue", lw=0.6, label="data")
            ax.plot(r.t, r.model_x, color="tab:red", lw=0.9, label=f"joint fit ({self.model})")
            ax.set_ylabel(f"run {j}")
            ax.set_title(f"{r.source or f'run {j}'}: rms {r.rms:.3g}", fontsize=8)
            ax.legend(fontsize=7, loc="upper right")
            axr.plot(r.t, r.residuals, color="tab:blue", lw=0.5)
            axr.axhline(0.0, color="k", lw=0.6)
        axes[-1].set_xlabel("t [s]")
        terms = ", ".join(f"{k} = {self.values[k]:.4g}" for k in self.shared)
        fig.suptitle(title or f"joint fit, shared {terms}", fontsize=9)
        save_figure(fig, path, dpi=110)
        return Path(path)

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={self.values[k]:.4g}" for k in self.shared)
        rms = ", ".join(f"{v:.3g}" for v in self.rms)
        return (f"JointResult({len(self.runs)} runs, model={self.model!r}, {vals}, "
                f"rms=[{rms}], success={self.success})")


# ----------------------------------------------------------------------------------------------
# the public function


def _per_run(value, n, name):
    """A per-run list of an argument that is either one value or a list of n."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ValueError(f"{name}: give one value or one per run ({n}), got {len(value)}")
        return list(value)
    return [value] * n


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
    from ._api import _bucket, _check_max_steps, _swings_bucket, _units_of, fit

    if not isinstance(traces, (list, tuple)) or len(traces) < 2:
        raise ValueError("traces: a joint fit needs a list of two or more runs")
    check_choice("model", model, MODELS)
    if loss != "linear":
        raise ValueError(f"loss: a joint fit is least squares ('linear'), got {loss!r}")
    if optimizer != "lm":
        raise ValueError(f"optimizer: a joint fit uses 'lm', got {optimizer!r}")
    max_steps = _check_max_steps(max_steps)
    per_mass = oscillator is None
    if fit_omega0 is None:
        fit_omega0 = per_mass
    shared, free = check_shared(shared, free, fit_omega0=bool(fit_omega0), k3=k3)
    n_runs = len(traces)
    starts_at = _per_run(start, n_runs, "start")
    ends_at = _per_run(end, n_runs, "end")
    spec = FIT_MODELS[model]
    first = spec.start_from or model
    osc = oscillator_values(oscillator)
    singles, inputs = [], []
    # each run alone (its window, guesses, global starts): the starts of the joint fit
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for j, item in enumerate(traces):
            tr, x = _run_input(item, j)
            inputs.append(tr)
            try:
                res = fit(tr, x, oscillator=oscillator, free=free, model=first,
                          fit_omega0=fit_omega0, offset=offset, start=starts_at[j],
                          end=ends_at[j], units=units, starts=starts, seed=seed, k3=k3,
                          _inner=True)
            except ValueError as err:
                raise ValueError(f"traces[{j}]: {err}") from err
            singles.append(res)
    notes = sorted({str(w.message) for w in caught})
    unit = _units_of(inputs[0], units)
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
    n_pad = _bucket(n_max)
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
    from ._api import _pad

    rows = {k: [] for k in ("tau", "x", "weight", "span", "ref", "scale", "lo", "start")}
    for j, s in enumerate(singles):
        tp, xp, wt = _pad(s.t, s.x, n_pad)
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


def _result(out: JointCore, a: JointArrays, lay: Layout, singles, sigma, *, free, model, unit,
            per_mass, fit_omega0, opts, stages, notes, osc) -> JointResult:
    """The :class:`JointResult` (and the per-run FitResults) of the core's output."""
    names = lay.names()
    p = np.asarray(out.p, dtype=float)
    J = np.asarray(out.jac, dtype=float)          # (N, n_pad, size)
    r = np.asarray(out.resid, dtype=float)        # (N, n_pad)
    mask = np.asarray(a.weight) > 0
    ns = [int(m.sum()) for m in mask]
    Jd = np.concatenate([J[j, :ns[j]] for j in range(lay.n_runs)])
    rd = np.concatenate([r[j, :ns[j]] for j in range(lay.n_runs)])
    n, k = rd.size, len(names)
    chisqr = float(rd @ rd)
    H = Jd.T @ Jd
    Hinv = _inverse(H)
    s2 = chisqr / max(n - k, 1)
    delta = s2 * Hinv
    S = np.zeros((k, k))
    for j in range(lay.n_runs):
        w0 = float(out.P[j, 3])
        dt = float(np.median(np.diff(singles[j].t)))
        period = 2 * math.pi / w0 / dt if math.isfinite(w0) and w0 > 0 else 8.0
        Jj, rj = J[j, :ns[j]], r[j, :ns[j]]
        if ns[j] < 3 or not (np.all(np.isfinite(Jj)) and np.all(np.isfinite(rj))):
            S += np.nan
            continue
        S += score_covariance(Jj, rj, period)
    hac = Hinv @ S @ Hinv
    hac = 0.5 * (hac + hac.T)
    active = np.diag(H) > 0
    sd = np.where(active, np.sqrt(np.clip(np.diag(delta), 0.0, None)), np.nan)
    values = {nm: float(v) for nm, v in zip(names, p, strict=True)}
    stderr = {nm: float(v) for nm, v in zip(names, sd, strict=True)}
    code = out.code
    converged = bool(code == FIT_RESULTS.successful)
    text = FIT_RESULTS[code]
    finite = np.all(np.isfinite(p)) and np.isfinite(chisqr)
    if not finite:
        converged, text = False, FIT_RESULTS[FIT_RESULTS.failed]
    message = "; ".join([text] + stages)
    # per-run FitResults at the joint optimum (the single fit's checks, on each run)
    c = Constants(m=osc["m"], g=osc["g"], k3=None if lay.k3 == "none" else float(out.k3))
    vary = vary_mask(TraceParams, free, fit_omega0=fit_omega0,
                     offset="offset" in lay.local)
    runs = []
    S_ = len(lay.shared)
    L = len(lay.local)
    for j, single in enumerate(singles):
        idx = {}  # field -> column of the joint vector
        for name in TraceParams._fields:
            coord = "y" if name == "v0" else name
            if name in lay.shared:
                idx[name] = lay.shared.index(name)
            elif coord in lay.local:
                idx[name] = S_ + j * L + lay.local.index(coord)
        fields = TraceParams._fields
        cov7 = np.zeros((7, 7))
        jac7 = np.zeros((J.shape[1], 7))
        for a_, fa in enumerate(fields):
            if fa in idx:
                jac7[:, a_] = J[j, :, idx[fa]]
                for b_, fb in enumerate(fields):
                    if fb in idx:
                        cov7[a_, b_] = delta[idx[fa], idx[fb]]
        sd7 = [math.sqrt(max(cov7[i, i], 0.0)) if f in idx else math.nan
               for i, f in enumerate(fields)]
        ctr = r[j] * sigma[j]
        core = CoreResult(
            params=TraceParams(*(float(v) for v in np.asarray(out.P)[j])),
            stderr=TraceParams(*sd7), covariance=cov7, code=code, steps=out.steps,
            chisqr=float(np.sum(ctr[:ns[j]] ** 2)), ndata=ns[j], nvarys=len(idx),
            curve=np.asarray(out.curve)[j],
            coords=TraceCoords(*(float(v) for v in np.asarray(out.q)[j])),
            jac=jac7, resid=r[j])
        an = analyse(single.t, single.x, omega0=None if fit_omega0 else osc["w0"])
        ctx = FitContext(model=model, free=free, vary=vary, consts=c, t=single.t, x=single.x,
                         loss="linear", optimizer="lm", source=single.source,
                         full_t=single.full_t, full_x=single.full_x, per_mass=per_mass,
                         units=unit, analysis=an, stages="joint fit")
        runs.append(build_result(core, ctx))
    fails = [f"the standard error of {nm} is not finite" for nm in names
             if not math.isfinite(stderr[nm])]
    if not converged:
        fails.insert(0, f"the optimizer did not converge ({text})")
    for j, res in enumerate(runs):
        own = [f for f in res.reason.split("; ") if f and "optimizer" not in f]
        if own:
            fails.append(f"run {j}: " + "; ".join(own))
    arrays = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), a)
    t_abs = np.asarray(a.tau) + np.array([s.t[0] for s in singles])[:, None]

    def residuals(pv):
        return physical_residuals(pv, arrays, lay, opts)

    problem = JointProblem(names=names, p0=p, residuals=residuals, mask=mask, t=t_abs,
                           x=np.asarray(a.x), sigma=np.asarray(sigma),
                           nonneg=tuple(nm for nm in names if nm.split("[")[0] in DAMPING),
                           residual=JointResidual(lay, opts), args=arrays)
    return JointResult(
        names=names, values=values, stderr=stderr, covariance=hac, delta_covariance=delta,
        shared=lay.shared, free=free, runs=runs, singles=singles,
        success=converged and not fails, converged=converged, reason="; ".join(fails),
        adequate=all(res.adequate for res in runs), message=message,
        n_iterations=int(out.steps), chisqr=chisqr, ndata=n, nvarys=k, sigma=np.asarray(sigma),
        model=model, per_mass=per_mass, units=unit, fit_omega0=fit_omega0,
        warnings=list(notes), _problem=problem)
