"""The joint least-squares problem of several runs (``_joint``): its static layout, the
padded arrays, the residuals in internal and physical coordinates, the compiled
Levenberg-Marquardt core over a batch of starts, and the score covariance of the HAC
intervals (docs/DESIGN.md, fitting; the method is described in ``_joint``)."""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import call_cached_tree
from .._models._solution import result_where
from .._oscillator import is_concrete
from . import _intervals
from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    _lm_code,
)
from ._linalg import tall_lstsq
from ._lm import levenberg_marquardt, rows_and_jacobian
from ._params import (
    DAMPING,
    Constants,
    TraceCoords,
    TraceParams,
)

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
    fn = functools.partial(_residuals, lay=lay, opts=opts)
    is_log, dref, lo = _log_info(lay, a)
    per_round = max(int(max_steps) // ROUNDS, 1)

    def cost(theta):
        r = fn(theta, a)
        return jnp.sum(r * r)

    def solve(theta, scale):
        sol = levenberg_marquardt(lambda u: fn(theta + scale * u, a), jnp.zeros_like(theta),
                                  rtol=rtol, atol=atol, max_steps=per_round)
        th = theta + scale * sol.value
        th = jnp.where(is_log, jnp.maximum(th, lo), th)
        # a round that ends non-finite or above its start is not taken (its code says so)
        c0, c1 = cost(theta), cost(th)
        keep = jnp.all(jnp.isfinite(th)) & jnp.isfinite(c1) & ~(c1 > c0)
        code = result_where(keep, _lm_code(sol), FIT_RESULTS.failed)
        return jnp.where(keep, th, theta), sol.steps, code

    # first each run's own coordinates with the shared ones held at the start: a run whose
    # single fit was poor gets a start consistent with the shared constants
    local_only = jnp.concatenate([jnp.zeros(len(lay.shared)), jnp.ones(size - len(lay.shared))])
    theta0, steps0, _ = solve(jnp.zeros(size), local_only)

    def one(carry, index):
        theta, scale, steps, code, redo = carry
        again = (steps == 0) | (code != FIT_RESULTS.successful) | redo
        theta, n_steps, code = jax.lax.cond(again, solve, lambda th, sc: (th, 0, code),
                                            theta, scale)
        r, J = rows_and_jacobian(lambda th: _residuals(th, a, lay, opts), theta)
        # Gauss-Newton step in the physical damping constants: one it sends to <= 0 goes to
        # its lower bound (the single fit's rounds, ``_core._lm_rounds``)
        p = dref * jnp.exp(theta)
        Jx = jnp.where(is_log, J / p, J)
        step = tall_lstsq(Jx, -r)  # (_linalg: XLA's CPU lstsq of a tall J is slow)
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
    return _at_optimum(theta, a, lay, opts, code, steps)


def _at_optimum(theta, a: JointArrays, lay: Layout, opts, code, steps) -> JointCore:
    """The :class:`JointCore` of the optimum ``theta`` (internal coordinates): the physical
    parameters, the model and the Jacobian of the weighted residuals in the physical vector.

    Arguments:
        theta: the internal vector at the optimum.
        a: the arrays of the problem.
        lay, opts: the layout and the reference options (static).
        code, steps: the optimizer's result code and its number of steps.

    Returns:
        The :class:`JointCore`.
    """
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
    """:func:`joint_core` over a batch of starts (every leaf of ``batch`` with a leading
    batch axis): vmapped, through a kept program when eager; on a CPU, the exact model's
    starts one after the other through the single fit's program instead
    (:func:`run_joint_core`: no second program of the integrating fit to compile, 11-15 s on
    2 cores for two runs, and no start waits for the slowest of its batch; a GPU runs the
    lanes side by side)."""
    batch = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), batch)
    if is_concrete(batch) and FIT_MODELS[static["lay"].model].integrates \
            and jax.default_backend() == "cpu":
        size = jax.tree_util.tree_leaves(batch)[0].shape[0]
        outs = [run_joint_core(jax.tree_util.tree_map(lambda v, i=i: v[i], batch), **static)
                for i in range(size)]
        return jax.tree_util.tree_map(lambda *v: jnp.stack(v), *outs)
    return vmapped_batch(batch, **static)


def vmapped_batch(batch: JointArrays, **static) -> JointCore:
    """:func:`joint_core` vmapped over the batch's leading axis, through a kept program when
    eager (``benchmarks/joint_cold.py`` races it against the CPU's start-by-start route)."""
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


def score_covariance(J: np.ndarray, r: np.ndarray, period_samples: float,
                     basis: np.ndarray | None = None) -> np.ndarray:
    """S of the AR(1)-prewhitened HAC sandwich of one run (``_intervals.score_matrix``,
    whose H^-1 S H^-1 ``_intervals.hac_covariance`` completes).

    Arguments:
        J, r: the run's rows of the joint Jacobian (n x p) and its residuals (n).
        period_samples: samples per oscillation period.
        basis: T^T S T in the joint Jacobian's orthogonal basis (``_intervals.gram_basis``).
    """
    return _intervals.score_matrix(np.ascontiguousarray(J), r,
                                   period_samples=period_samples, basis=basis)[0]

