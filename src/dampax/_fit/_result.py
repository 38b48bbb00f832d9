"""Results of the fits: :class:`FitResult` (report, plot, JSON), :class:`ModelComparison`
(candidate damping models ranked by BIC or AIC) and :class:`ArrayFit` (the vmappable arrays of
``fit_arrays``). Statistics follow lmfit's definitions (docs/DESIGN.md, fitting).

:func:`build_result` makes a FitResult from the core's output and the fit's
:class:`~dampax._fit._context.FitContext` (what the fit was asked to do, and the quantities
derived from its parameters: ``_context``); :func:`rank` ranks fits into a ModelComparison.
The report's text and the figure are ``_report``'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import numpy as np

from .._plot_fit import plot_fit
from . import _intervals
from ._assess import Inputs, assess
from ._checks import data_rows
from ._context import FitContext, envelope_derived, trace_derived
from ._core import FIT_MODELS, FIT_RESULTS, CoreResult, is_code
from ._dist import norm_ppf
from ._params import DAMPING, check_choice, d_per_unit, varied_names
from ._report import fit_report


def _jsonable(v):
    """A diagnostic as JSON: strings as they are, numbers (None where not finite), and dicts
    and sequences of them."""
    if isinstance(v, str) or v is None or isinstance(v, bool):
        return v
    if isinstance(v, dict):
        return {str(k): _jsonable(w) for k, w in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(w) for w in v]
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass
class FitResult:
    """Result of :func:`fit` / :func:`fit_envelope`.

    Attributes:
        params: fitted and fixed parameters in physical units (dict name -> float): the damping
            constants mu, b, D, w0, offset, x0, v0 (x0, v0 at the fit start t_start) for traces;
            mu, b, D, A, offset for envelopes.
        stderr: standard errors (dict; NaN for fixed parameters).
        varied: names of the fitted parameters (the order of ``covariance``).
        covariance, correlation: matrices over ``varied``.
        residuals: data minus model over the fitted window.
        t, x, model_x: the fitted window (times, data, model).
        success, message, n_iterations: optimizer outcome.
        chisqr, redchi, aic, bic, ndata, nvarys: fit statistics (lmfit's definitions:
            aic = n ln(chisqr/n) + 2 nvarys, bic = n ln(chisqr/n) + ln(n) nvarys).
        derived: d0, d1, d2, xc, k, A and phi (the ansatz's amplitude and phase, eqs. 22-23,
            matched to the fitted start; for the exact model of an overdamped motion, where
            that ansatz does not exist, the start's undamped ones), halt_time, mu_g (the
            friction deceleration mu g in position units/s^2), b/m [1/s], D/m [1/position
            unit].
        free, model, loss, optimizer, kind ("trace" or "envelope"), t_start, source.
        success: the fit can be trusted as a fit: the optimizer converged and none of the
            checks of ``_assess.assess`` failed; else ``reason`` says why in one line.
        converged: the optimizer alone converged (``message``).
        reason: "" or the failures, one line.
        adequate: the model describes the data (residuals near the noise level, no phase
            drift, halts where the data stop); ``inadequacy`` lists what is not.
        diagnostics: the measured numbers behind the checks.
        starts: the global starts (``_starts.Starts``) or None.
        per_mass: no oscillator was given: m = 1 kg, so b and D are b/m and D/m.
        units: the unit of the positions ("m", "deg", ...).
    """

    params: dict
    stderr: dict
    varied: list
    covariance: np.ndarray
    correlation: np.ndarray
    residuals: np.ndarray
    t: np.ndarray
    x: np.ndarray
    model_x: np.ndarray
    success: bool
    message: str
    n_iterations: int
    chisqr: float
    redchi: float
    aic: float
    bic: float
    ndata: int
    nvarys: int
    free: tuple
    model: str
    loss: str
    optimizer: str
    kind: str = "trace"
    t_start: float = 0.0
    source: str = ""
    fixed: dict = field(default_factory=dict)
    derived: dict = field(default_factory=dict)
    init: dict = field(default_factory=dict)
    envelope: np.ndarray | None = None
    full_t: np.ndarray | None = None
    full_x: np.ndarray | None = None
    f_scale: float = math.inf
    warnings: list = field(default_factory=list)
    converged: bool = True
    reason: str = ""
    adequate: bool = True
    inadequacy: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    starts: object = None
    per_mass: bool = False
    units: str = "m"
    jac: np.ndarray | None = None
    profiled: dict = field(default_factory=dict)
    resid_rows: np.ndarray | None = None
    extra_cov: np.ndarray | None = None
    #: the neighbouring-halt search's held fits ({mu: (cost, first halt, values)}), for a
    #: check made later (``_halts.other_halt_check``: the k3 profile's, with k3's uncertainty)
    other_halts: dict = field(default_factory=dict)

    def _hac(self):
        """(HAC covariance over ``varied``, bandwidth) of ``_intervals.hac_covariance``."""
        if self.jac is None or self.resid_rows is None:
            raise ValueError("conf_interval: this result carries no Jacobian")
        cached = getattr(self, "_hac_cache", None)
        if cached is None:
            w0 = self.params.get("w0", self.derived.get("w0", math.nan))
            dt = float(np.median(np.diff(self.t))) if len(self.t) > 1 else 1.0
            period = 2 * math.pi / w0 / dt if math.isfinite(w0) and w0 > 0 else 8.0
            if self.kind == "envelope":
                period = 1.0
            cached = _intervals.hac_covariance(self.jac, self.resid_rows,
                                               period_samples=period)
            if self.extra_cov is not None:  # a profiled k3: its uncertainty carried over
                cached = (cached[0] + self.extra_cov, cached[1])
            object.__setattr__(self, "_hac_cache", cached)
        return cached

    @property
    def hac_stderr(self) -> dict:
        """Standard errors from the HAC covariance (allowing for correlated residuals)."""
        cov, _ = self._hac()
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return {name: float(v) for name, v in zip(self.varied, sd, strict=True)}

    def conf_interval(self, level: float = 0.95) -> dict:
        """Confidence intervals {name: (lo, hi)} of every fitted parameter that allow for
        autocorrelated residuals: a Newey-West (HAC) sandwich covariance with a Bartlett
        kernel whose bandwidth comes from the autocorrelation of the scores
        (``dampax._fit._intervals``: why this method), normal intervals value +- z sd,
        clipped at 0 for the damping constants; a side over which the profile of the cost
        rises c < 1 times what the interval assumes is widened by 1/sqrt(c), and where a
        damping constant held at 0 costs less than chi2(1)'s 1 % point although its interval
        excludes 0, every side is widened to reach that held fit's values
        (``diagnostics["interval_scale"]``, ``_profile.PROFILE_FAIL``,
        ``_profile.bound_verdict``; ``diagnostics["note_bound"]`` says so).

        Arguments:
            level: two-sided coverage, in (0, 1).
        """
        sd = self.hac_stderr
        out = _intervals.normal_intervals({n: self.params[n] for n in self.varied}, sd,
                                          level, nonneg=DAMPING,
                                          scale=self.diagnostics.get("interval_scale"))
        if self.profiled:  # k3 of fit(free=(..., "k3")): from the profile's curvature

            z = norm_ppf(0.5 + 0.5 * level)
            for name, pr in self.profiled.items():
                if "interval" in pr:  # mu_s: the values that give the fitted halt
                    out[name] = tuple(pr["interval"])
                    continue
                below, above = pr.get("scale", (1.0, 1.0))
                out[name] = (pr["value"] - z * pr["stderr"] * below,
                             pr["value"] + z * pr["stderr"] * above)
        return out

    @property
    def rms(self) -> float:
        """Root mean square of the residuals (data units)."""
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={self.params[k]:.4g}" for k in self.free)
        return (f"FitResult({self.kind}, model={self.model!r}, free={self.free}, {vals}, "
                f"rms={self.rms:.3g}, bic={self.bic:.1f}, success={self.success})")

    def report(self, *, min_correl: float = 0.1) -> str:
        """A text report like lmfit's fit_report: statistics, values, correlations
        (``_report.fit_report``).

        Arguments:
            min_correl: the smallest correlation reported.

        Returns:
            The report, one section after another.
        """
        return fit_report(self, min_correl)

    def to_dict(self) -> dict:
        """JSON-ready summary (no arrays of data)."""
        def num(v):
            v = float(v)
            return v if math.isfinite(v) else None

        return {
            "kind": self.kind, "model": self.model, "free": list(self.free), "loss": self.loss,
            "optimizer": self.optimizer, "source": self.source,
            "params": {k: num(v) for k, v in self.params.items()},
            "stderr": {k: num(v) for k, v in self.stderr.items()},
            "varied": list(self.varied),
            "covariance": [[num(c) for c in row] for row in np.asarray(self.covariance)],
            "correlation": [[num(c) for c in row] for row in np.asarray(self.correlation)],
            "derived": {k: num(v) for k, v in self.derived.items()},
            "fixed": {k: num(v) for k, v in self.fixed.items()},
            "statistics": {"chisqr": num(self.chisqr), "redchi": num(self.redchi),
                           "aic": num(self.aic), "bic": num(self.bic), "ndata": self.ndata,
                           "nvarys": self.nvarys, "rms": num(self.rms),
                           "t_start": num(self.t_start)},
            "success": bool(self.success), "message": self.message, "reason": self.reason,
            "converged": bool(self.converged), "adequate": bool(self.adequate),
            "inadequacy": list(self.inadequacy), "per_mass": bool(self.per_mass),
            "units": self.units,
            "diagnostics": {k: _jsonable(v) for k, v in self.diagnostics.items()},
            "starts": self.starts.to_dict() if self.starts is not None else None,
            "n_iterations": int(self.n_iterations), "warnings": list(self.warnings),
        }

    def plot(self, path, *, title: str | None = None):
        """Save a figure: data, fit, envelope and sticking band above, residuals below, the
        axes in s and the fit's units (``dampax._plot_fit.plot_fit``; the static band where mu_s
        is set).

        Arguments:
            path: the file to write.
            title: the title (default: the data's source, the fitted terms and the rms).

        Returns:
            The path written.
        """
        return plot_fit(self, path, title=title)


@dataclass
class ModelComparison:
    """Candidate damping models fitted to the same data, ranked by an information criterion.

    Attributes:
        results: successful candidate (tuple of free terms) -> FitResult, best first.
        criterion: "bic" or "aic" (the ranking).
        table: one dict per successful candidate, best first: free, aic, bic, delta
            (criterion minus the best), chisqr, rms, nvarys, success, adequate.
        failed: the candidates whose fit failed (left out of the ranking): -> FitResult.
        skipped: the candidates that could not be fitted to these data at all (left out):
            -> the reason (e.g. more parameters than an envelope has maxima).
    """

    results: dict
    criterion: str
    table: list
    failed: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)

    @property
    def best(self) -> FitResult | None:
        """The fit of the best-ranked candidate (None when every candidate failed)."""
        return next(iter(self.results.values()), None)

    @property
    def ranking(self) -> list:
        """Candidates (tuples of free terms), best first."""
        return list(self.results)

    @property
    def supported(self) -> tuple:
        """Damping terms of the best-ranked model (() when every candidate failed)."""
        return tuple(self.best.free) if self.best is not None else ()

    def evidence(self) -> dict:
        """Per damping term: the criterion change when it is removed from / added to the best
        model (positive = the data support the best model's choice), where such a candidate
        was fitted."""
        if self.best is None:
            return {}
        best = tuple(self.best.free)
        score = {tuple(sorted(k)): getattr(r, self.criterion) for k, r in self.results.items()
                 if r.success}
        ref = getattr(self.best, self.criterion)
        out = {}
        for term in DAMPING:
            other = tuple(sorted(set(best) ^ {term}))
            if other and other in score:
                out[term] = score[other] - ref
        return out

    def report(self) -> str:
        """The ranking as a text table and which damping terms the data support."""
        name = self.criterion.upper()
        lines = [f"Model ranking by {name} (lower is better):",
                 f"  {'rank':>4}  {'free terms':<12} {'AIC':>12} {'BIC':>12} {'d' + name:>10} "
                 f"{'rms':>10}  {'ok':>3}"]
        for i, row in enumerate(self.table):
            lines.append(f"  {i + 1:>4}  {','.join(row['free']):<12} {row['aic']:>12.2f} "
                         f"{row['bic']:>12.2f} {row['delta']:>10.2f} {row['rms']:>10.4g}  "
                         f"{'yes' if row['success'] else 'no':>3}"
                         + ("" if row.get("adequate", True) else "  (model inadequate)"))
        for cand, r in self.results.items():
            if not r.success:
                lines.append(f"  ranked, but its verdict failed: {','.join(cand)}: {r.reason}")
        for cand, r in self.failed.items():
            lines.append(f"  left out (no optimum): {','.join(cand)}: {r.reason}")
        for cand, why in self.skipped.items():
            lines.append(f"  left out (not fitted): {','.join(cand)}: {why}")
        if self.best is None:
            lines.append("  no candidate fit reached an optimum: the data support no model")
            return "\n".join(lines)
        best = self.best.free
        lines.append(f"  the data support: {' + '.join(best)} "
                     f"({', '.join(f'{k} = {self.best.params[k]:.4g}' for k in best)})")
        ev = self.evidence()
        for term, delta in ev.items():
            verb = "removing" if term in best else "adding"
            lines.append(f"    {verb} {term} changes {name} by {delta:+.1f}"
                         + ("" if delta > 0 else "  (not decisive)"))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"criterion": self.criterion,
                "ranking": [{**row, "free": list(row["free"])} for row in self.table],
                "supported": list(self.supported),
                "failed": {",".join(k): r.reason for k, r in self.failed.items()},
                "skipped": {",".join(k): why for k, why in self.skipped.items()}}


class ArrayFit(NamedTuple):
    """Result of :func:`fit_arrays`: arrays only (vmappable); layout PARAMS.

    Attributes:
        params: fitted (mu, b, D, w0, offset, x0, v0); fixed entries hold their p0 value.
        stderr: standard errors (NaN for fixed entries).
        success: the optimizer converged and everything is finite.
        n_iterations: optimizer steps.
        chisqr: sum of squared (robust-weighted) residuals in data units.
        covariance: 7 x 7 covariance of params (zero rows/columns for fixed entries).
        jac, resid: the Jacobian of the (normalised) residuals in the physical parameters
            (n x 7, zero columns for fixed entries) and those residuals: the input of
            ``dampax._fit._intervals.hac_covariance`` (intervals for correlated residuals).
    """

    params: jax.Array
    stderr: jax.Array
    success: jax.Array
    n_iterations: jax.Array
    chisqr: jax.Array
    covariance: jax.Array
    jac: jax.Array | None = None
    resid: jax.Array | None = None


def build_result(out: CoreResult, ctx: FitContext) -> FitResult:
    """The :class:`FitResult` of the core's output ``out`` for the fit described by ``ctx``."""
    mask = ctx.vary._asdict()
    idx = [i for i, on in enumerate(mask.values()) if on]  # rows of the covariance
    cov = np.asarray(out.covariance, dtype=float)[np.ix_(idx, idx)]
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    params = {name: float(v) for name, v in out.params._asdict().items()}
    stderr = {name: float(v) if mask[name] else math.nan
              for name, v in out.stderr._asdict().items()}
    n = len(ctx.t)
    curve = np.asarray(out.curve, dtype=float)[:n]
    ndata, nvarys, chisqr = int(out.ndata), int(out.nvarys), float(out.chisqr)
    neg2ll = ndata * math.log(max(chisqr, 1e-300) / ndata)
    text = FIT_RESULTS[out.code]
    message = f"{text}; {ctx.stages}" if ctx.stages else text
    kind = FIT_MODELS[ctx.model].kind
    derive = trace_derived if kind == "trace" else envelope_derived
    derived, envelope, fixed = derive(params, out.coords, ctx)
    converged = is_code(out.code, FIT_RESULTS.successful)
    capped = is_code(out.code, FIT_RESULTS.max_steps_reached)
    jac, rows = data_rows(out, ctx.vary, n)
    fails, bad, diag = [], [], {}
    if ctx.analysis is not None or kind != "trace":

        fails, bad, diag = assess(Inputs(
            t=ctx.t, x=ctx.x, curve=curve, params=params, stderr=stderr,
            varied=varied_names(ctx.vary), derived=derived, an=ctx.analysis,
            converged=converged, message=text, kind=kind, model=ctx.model, jac=jac, rows=rows,
            capped=capped, profile=ctx.profile, chisqr=chisqr, search=ctx.search, exact=ctx.exact,
            d_scale=d_per_unit(params["w0"], ctx.consts.m, ctx.consts.g)
            if "w0" in params else None))
        if not converged and "note_steps" in diag:  # as good as converged: say so first
            converged = True
            text = f"{FIT_RESULTS[FIT_RESULTS.successful]} ({diag['note_steps']})"
            message = f"{text}; {ctx.stages}" if ctx.stages else text
    elif not converged:
        fails = [f"the optimizer did not converge ({text})"]
    return FitResult(
        params=params, stderr=stderr, varied=varied_names(ctx.vary), covariance=cov,
        correlation=corr, residuals=ctx.x - curve, t=ctx.t, x=ctx.x, model_x=curve,
        success=converged and not fails, message=message, converged=converged,
        reason="; ".join(fails), adequate=not bad, inadequacy=bad, diagnostics=diag,
        starts=ctx.starts, per_mass=ctx.per_mass, units=ctx.units, jac=jac, resid_rows=rows,
        n_iterations=int(out.steps), chisqr=chisqr,
        redchi=chisqr / max(ndata - nvarys, 1), aic=neg2ll + 2 * nvarys,
        bic=neg2ll + math.log(ndata) * nvarys, ndata=ndata, nvarys=nvarys, free=tuple(ctx.free),
        model=ctx.model, loss=ctx.loss, optimizer=ctx.optimizer, kind=kind,
        t_start=float(ctx.t[0]), source=ctx.source, fixed=fixed, derived=derived,
        init={k: float(v) for k, v in ctx.init.items()}, envelope=envelope, full_t=ctx.full_t,
        full_x=ctx.full_x, f_scale=float(ctx.f_scale), warnings=list(ctx.warnings))


def rank(results: dict, criterion: str, skipped: dict | None = None) -> ModelComparison:
    """A :class:`ModelComparison` of fits (candidate -> FitResult) ranked by their statistics:
    every fit that reached an optimum (converged, finite cost and criterion) by increasing
    ``criterion`` ("aic" or "bic"), whatever its verdict (a fit that fails a check of its
    intervals or of its residuals is still the optimum of its model, and its cost is what the
    ranking compares; the table says which failed, the report why); fits without an optimum
    are left out and listed in ``failed``; ``skipped`` (candidate -> reason) lists the
    candidates that could not be fitted at all."""
    check_choice("criterion", criterion, ("aic", "bic"))

    def ranked(r) -> bool:
        return bool(r.converged) and math.isfinite(r.chisqr) and \
            math.isfinite(getattr(r, criterion))

    ok = {k: r for k, r in results.items() if ranked(r)}
    failed = {k: r for k, r in results.items() if not ranked(r)}
    ordered = dict(sorted(ok.items(), key=lambda item: getattr(item[1], criterion)))
    best = getattr(next(iter(ordered.values())), criterion) if ordered else math.nan
    table = [dict(free=tuple(k), aic=r.aic, bic=r.bic,
                  delta=getattr(r, criterion) - best, chisqr=r.chisqr, rms=r.rms,
                  nvarys=r.nvarys, success=r.success, adequate=r.adequate)
             for k, r in ordered.items()]
    return ModelComparison(results=ordered, criterion=criterion, table=table, failed=failed,
                           skipped=dict(skipped or {}))
