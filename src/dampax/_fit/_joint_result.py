"""The result of a joint fit (``_joint``): :class:`JointResult` (shared and per-run
parameters, intervals, report, figure) and :class:`JointProblem` for samplers built on it
(its construction from the joint optimum: ``_joint_build``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from .._plot_fit import plot_joint_fit
from . import _intervals
from ._joint_problem import (
    JointArrays,
    Layout,
    physical_residuals,
)
from ._params import (
    DAMPING,
    unit_of,
)

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
        """Save a figure: each run's data and joint fit above its residuals, in s and the fit's
        units (``dampax._plot_fit.plot_joint_fit``).

        Returns:
            The path written.
        """
        return plot_joint_fit(self, path, title=title)

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={self.values[k]:.4g}" for k in self.shared)
        rms = ", ".join(f"{v:.3g}" for v in self.rms)
        return (f"JointResult({len(self.runs)} runs, model={self.model!r}, {vals}, "
                f"rms=[{rms}], success={self.success})")
