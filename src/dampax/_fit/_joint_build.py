"""The construction of a joint fit's :class:`~dampax._fit._joint_result.JointResult` from the
joint optimum (``_joint``): the chi-square and the delta-method and HAC covariances, each run's
FitResult at the optimum (the single fit's checks on each run), the reasons a fit cannot be
trusted, and the :class:`~dampax._fit._joint_result.JointProblem` for samplers."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._core import (
    FIT_RESULTS,
    CoreResult,
    is_code,
)
from ._guess import analyse
from ._intervals import gram_basis
from ._joint_problem import (
    JointArrays,
    JointCore,
    Layout,
    physical_residuals,
    score_covariance,
)
from ._joint_result import JointProblem, JointResidual, JointResult
from ._params import (
    DAMPING,
    Constants,
    TraceCoords,
    TraceParams,
    vary_mask,
)
from ._result import FitContext, build_result


class JointContext(NamedTuple):
    """What the result of a joint fit is built from beside the core's output and the arrays.

    Attributes:
        lay: the joint :class:`Layout`.
        singles: the runs' single fits (their windows; the starts).
        sigma: each run's noise level (the weights 1/sigma).
        free: the free damping constants.
        model: the fit model's name.
        unit: the position unit.
        per_mass: no oscillator given (b and D per unit mass).
        fit_omega0: w0 fitted.
        opts: the reference integrator's budget and tolerances (None for the ansatz).
        stages: what the fit did, in order (appended to the message).
        notes: the single fits' warnings.
        osc: the oscillator's values (m, g, w0).
        search: the exact model's search (``_joint_stages._exact_search``; None for the
            approximate model): each run's check of structured residuals reads it.
    """

    lay: Layout
    singles: list
    sigma: Any
    free: tuple
    model: str
    unit: str
    per_mass: bool
    fit_omega0: bool
    opts: Any
    stages: list
    notes: list
    osc: dict
    search: Any = None


class JointStatistics(NamedTuple):
    """The statistics of a joint optimum (numpy).

    Attributes:
        J, r: the weighted Jacobian rows (N, n_pad, size) and residual rows (N, n_pad).
        mask, ns: the samples that are data (N, n_pad) and each run's count of them.
        chisqr: the sum of the weighted squared residuals.
        delta: the delta-method covariance s^2 H^-1.
        hac: the HAC covariance H^-1 S H^-1 (S summed over the runs).
        sd: the delta-method standard errors (NaN where the parameter moves nothing).
    """

    J: np.ndarray
    r: np.ndarray
    mask: np.ndarray
    ns: list
    chisqr: float
    delta: np.ndarray
    hac: np.ndarray
    sd: np.ndarray


def _score_sum(out: JointCore, J, r, ns, singles, basis) -> np.ndarray:
    """S of the HAC sandwich: the runs' score covariances summed (NaN where a run has under
    3 samples or a non-finite row).

    Arguments:
        out: the core's output (each run's w0 sets its period in samples).
        J, r: the weighted Jacobian and residual rows (N, n_pad, size), (N, n_pad).
        ns: each run's number of samples.
        singles: the runs' single fits (their sampling steps).
        basis: T of ``_intervals.gram_basis`` (S in its basis, T^T S T: the sandwich's
            stable form, as ``_intervals.hac_covariance`` takes it).

    Returns:
        S, (size, size).
    """
    k = J.shape[2]
    S = np.zeros((k, k))
    for j in range(len(ns)):
        w0 = float(out.P[j, 3])
        dt = float(np.median(np.diff(singles[j].t)))
        period = 2 * math.pi / w0 / dt if math.isfinite(w0) and w0 > 0 else 8.0
        Jj, rj = J[j, :ns[j]], r[j, :ns[j]]
        if ns[j] < 3 or not (np.all(np.isfinite(Jj)) and np.all(np.isfinite(rj))):
            S += np.nan
            continue
        S += score_covariance(Jj, rj, period, basis)
    return S


def _statistics(out: JointCore, a: JointArrays, singles) -> JointStatistics:
    """The chi-square, the delta-method and the HAC covariances of the core's output.

    Arguments:
        out: the core's output.
        a: the arrays of the fit (the weights mark the data).
        singles: the runs' single fits.

    Returns:
        A :class:`JointStatistics`.
    """
    J = np.asarray(out.jac, dtype=float)          # (N, n_pad, size)
    r = np.asarray(out.resid, dtype=float)        # (N, n_pad)
    mask = np.asarray(a.weight) > 0
    ns = [int(m.sum()) for m in mask]
    Jd = np.concatenate([J[j, :ns[j]] for j in range(len(ns))])
    rd = np.concatenate([r[j, :ns[j]] for j in range(len(ns))])
    n, k = rd.size, J.shape[2]
    chisqr = float(rd @ rd)
    T, w = gram_basis(Jd)
    Hinv = (T * w) @ T.T
    s2 = chisqr / max(n - k, 1)
    delta = s2 * Hinv
    hac = T @ (_score_sum(out, J, r, ns, singles, T) * np.outer(w, w)) @ T.T
    hac = 0.5 * (hac + hac.T)
    active = np.einsum("ij,ij->j", Jd, Jd) > 0
    sd = np.where(active, np.sqrt(np.clip(np.diag(delta), 0.0, None)), np.nan)
    return JointStatistics(J=J, r=r, mask=mask, ns=ns, chisqr=chisqr, delta=delta, hac=hac,
                           sd=sd)


def _columns(lay: Layout, j: int) -> dict:
    """{field: its column of the joint vector} of run ``j``'s fitted parameters."""
    idx = {}
    S_ = len(lay.shared)
    L = len(lay.local)
    for name in TraceParams._fields:
        coord = "y" if name == "v0" else name
        if name in lay.shared:
            idx[name] = lay.shared.index(name)
        elif coord in lay.local:
            idx[name] = S_ + j * L + lay.local.index(coord)
    return idx


def _run_core(out: JointCore, st: JointStatistics, j: int, ctx: JointContext) -> CoreResult:
    """Run ``j``'s share of the joint optimum as a single fit's :class:`CoreResult` (its rows
    of the Jacobian, its block of the delta-method covariance, its own chi-square).

    Arguments:
        out: the core's output.
        st: the optimum's statistics.
        j: the run.
        ctx: the fit's context (the layout, the noise levels).

    Returns:
        The run's :class:`CoreResult`.
    """
    idx = _columns(ctx.lay, j)
    J, r, ns = st.J, st.r, st.ns
    fields = TraceParams._fields
    cov7 = np.zeros((7, 7))
    jac7 = np.zeros((J.shape[1], 7))
    for a_, fa in enumerate(fields):
        if fa in idx:
            jac7[:, a_] = J[j, :, idx[fa]]
            for b_, fb in enumerate(fields):
                if fb in idx:
                    cov7[a_, b_] = st.delta[idx[fa], idx[fb]]
    sd7 = [math.sqrt(max(cov7[i, i], 0.0)) if f in idx else math.nan
           for i, f in enumerate(fields)]
    ctr = r[j] * ctx.sigma[j]
    return CoreResult(
        params=TraceParams(*(float(v) for v in np.asarray(out.P)[j])),
        stderr=TraceParams(*sd7), covariance=cov7, code=out.code, steps=out.steps,
        chisqr=float(np.sum(ctr[:ns[j]] ** 2)), ndata=ns[j], nvarys=len(idx),
        curve=np.asarray(out.curve)[j],
        coords=TraceCoords(*(float(v) for v in np.asarray(out.q)[j])),
        jac=jac7, resid=r[j])


def _run_results(out: JointCore, st: JointStatistics, ctx: JointContext) -> list:
    """One ``FitResult`` per run at the joint optimum (the single fit's checks, on each run).

    Arguments:
        out: the core's output.
        st: the optimum's statistics.
        ctx: the fit's context.

    Returns:
        The runs' FitResults, in order.
    """
    lay, osc = ctx.lay, ctx.osc
    c = Constants(m=osc["m"], g=osc["g"], k3=None if lay.k3 == "none" else float(out.k3))
    vary = vary_mask(TraceParams, ctx.free, fit_omega0=ctx.fit_omega0,
                     offset="offset" in lay.local)
    runs = []
    for j, single in enumerate(ctx.singles):
        core = _run_core(out, st, j, ctx)
        an = analyse(single.t, single.x, omega0=None if ctx.fit_omega0 else osc["w0"])
        fc = FitContext(model=ctx.model, free=ctx.free, vary=vary, consts=c, t=single.t,
                        x=single.x, loss="linear", optimizer="lm", source=single.source,
                        full_t=single.full_t, full_x=single.full_x, per_mass=ctx.per_mass,
                        units=ctx.unit, analysis=an, stages="joint fit",
                        search=ctx.search)
        runs.append(build_result(core, fc))
    return runs


def _failures(stderr: dict, converged: bool, text: str, runs: list) -> list:
    """Why a joint fit cannot be trusted: the optimizer, non-finite standard errors, the
    runs' failed checks (empty: it can).

    Arguments:
        stderr: the delta-method standard errors by name.
        converged, text: whether the optimizer converged, and its message.
        runs: the runs' FitResults.

    Returns:
        The reasons, in order.
    """
    fails = [f"the standard error of {nm} is not finite" for nm in stderr
             if not math.isfinite(stderr[nm])]
    if not converged:
        fails.insert(0, f"the optimizer did not converge ({text})")
    for j, res in enumerate(runs):
        own = [f for f in res.reason.split("; ") if f and "optimizer" not in f]
        if own:
            fails.append(f"run {j}: " + "; ".join(own))
    return fails


def _problem(p, a: JointArrays, mask, ctx: JointContext) -> JointProblem:
    """The :class:`JointProblem` at the joint optimum ``p``.

    Arguments:
        p: the joint physical vector at the optimum.
        a: the arrays of the fit.
        mask: the samples that are data (N, n_pad).
        ctx: the fit's context.

    Returns:
        The problem.
    """
    lay, opts, names = ctx.lay, ctx.opts, ctx.lay.names()
    arrays = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), a)
    t_abs = np.asarray(a.tau) + np.array([s.t[0] for s in ctx.singles])[:, None]

    def residuals(pv):
        return physical_residuals(pv, arrays, lay, opts)

    return JointProblem(names=names, p0=p, residuals=residuals, mask=mask, t=t_abs,
                        x=np.asarray(a.x), sigma=np.asarray(ctx.sigma),
                        nonneg=tuple(nm for nm in names if nm.split("[")[0] in DAMPING),
                        residual=JointResidual(lay, opts), args=arrays)


def _result(out: JointCore, a: JointArrays, ctx: JointContext) -> JointResult:
    """The :class:`JointResult` (and the per-run FitResults) of the core's output.

    Arguments:
        out: the core's output at the joint optimum.
        a: the arrays of the fit.
        ctx: the fit's context.

    Returns:
        The :class:`JointResult`.
    """
    lay = ctx.lay
    names = lay.names()
    p = np.asarray(out.p, dtype=float)
    st = _statistics(out, a, ctx.singles)
    values = {nm: float(v) for nm, v in zip(names, p, strict=True)}
    stderr = {nm: float(v) for nm, v in zip(names, st.sd, strict=True)}
    code = out.code
    converged = is_code(code, FIT_RESULTS.successful)
    text = FIT_RESULTS[code]
    finite = np.all(np.isfinite(p)) and np.isfinite(st.chisqr)
    if not finite:
        converged, text = False, FIT_RESULTS[FIT_RESULTS.failed]
    message = "; ".join([text] + ctx.stages)
    runs = _run_results(out, st, ctx)
    fails = _failures(stderr, converged, text, runs)
    return JointResult(
        names=names, values=values, stderr=stderr, covariance=st.hac, delta_covariance=st.delta,
        shared=lay.shared, free=ctx.free, runs=runs, singles=ctx.singles,
        success=converged and not fails, converged=converged, reason="; ".join(fails),
        adequate=all(res.adequate for res in runs), message=message,
        n_iterations=int(out.steps), chisqr=st.chisqr, ndata=int(sum(st.ns)), nvarys=len(names),
        sigma=np.asarray(ctx.sigma), model=ctx.model, per_mass=ctx.per_mass, units=ctx.unit,
        fit_omega0=ctx.fit_omega0, warnings=list(ctx.notes),
        _problem=_problem(p, a, st.mask, ctx))
