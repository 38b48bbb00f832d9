"""The text report and the figure of a single fit (:class:`~dampax._fit._result.FitResult`):
:func:`fit_report`, lmfit's fit_report in sections (the verdict, the model, the statistics,
the variables, the derived quantities, the intervals, the correlations, the notes), and
(the figure is ``dampax._plot_fit.plot_fit``'s).
"""

from __future__ import annotations

import math

import numpy as np

from . import _intervals
from ._core import METHOD_NAMES
from ._params import unit_of


def _verdict(res) -> list:
    """The first lines of a fit that failed or whose model does not describe the data."""
    lines = []
    if not res.success:
        lines.append(f"FIT FAILED: {res.reason}")
    if not res.adequate:
        lines.append("MODEL DOES NOT DESCRIBE THE DATA: " + "; ".join(res.inadequacy))
    return lines


def _model(res) -> list:
    """[[Model]]: the fit, its data, the unit of the positions and the global starts."""
    lines = ["[[Model]]",
             f"    {res.kind} fit, model = {res.model!r}, free damping = "
             f"{', '.join(res.free) or 'none'}, loss = {res.loss}"
             + (f" (f_scale = {res.f_scale:.4g})" if math.isfinite(res.f_scale) else ""),
             ]
    if res.source:
        lines.append(f"    data: {res.source}")
    if res.per_mass and res.kind == "trace":
        lines.append("    no oscillator given: w0 fitted, unit mass (m = 1 kg): b and D are "
                     f"per unit mass (b/m in 1/s, D/m in 1/{res.units}); positions in "
                     f"{res.units}")
    elif res.kind == "trace":
        lines.append(f"    positions in {res.units}")
    if res.starts is not None:
        lines.append(f"    global starts: {res.starts.summary()}")
    return lines


def _statistics(res) -> list:
    """[[Fit Statistics]]: the optimizer's outcome and lmfit's statistics."""
    method = METHOD_NAMES.get(res.optimizer, res.optimizer)
    lines = [
        "[[Fit Statistics]]",
        f"    # fitting method   = {method}",
        f"    # iterations       = {res.n_iterations}",
        f"    # data points      = {res.ndata}",
        f"    # variables        = {res.nvarys}",
        f"    chi-square         = {res.chisqr:.6g}",
        f"    reduced chi-square = {res.redchi:.6g}",
        f"    Akaike info crit   = {res.aic:.6g}",
        f"    Bayesian info crit = {res.bic:.6g}",
        f"    rms residual       = {res.rms:.6g}",
        f"    success            = {res.success} ({res.message})",
        f"    model adequate     = {res.adequate}",
    ]
    if res.kind == "trace":
        lines.append(f"    fit start t0       = {res.t_start:.6g}")
    return lines


def _variable(res, name: str, value: float, width: int) -> str:
    """One line of [[Variables]]: a fitted value with its standard error (and start), a
    profiled one with its sd, or a fixed one."""
    unit = unit_of(name, res.units, res.per_mass)
    if name in res.varied:
        err = res.stderr[name]
        rel = abs(err / value) * 100 if value != 0 and math.isfinite(err) else math.nan
        rel_text = f" ({rel:.2f}%)" if math.isfinite(rel) else ""
        init = res.init.get(name)
        init_text = f" (init = {init:.6g})" if init is not None else ""
        return (f"    {name + ':':<{width}} {value:.6g} +/- {err:.4g}{rel_text}"
                f"{init_text} {unit}".rstrip())
    if name in res.profiled:  # k3 of fit(free=(..., "k3")): profiled
        sd = res.profiled[name]["stderr"]
        how = ("every value in its interval gives the same halt"
               if "interval" in res.profiled[name]
               else "sd from the curvature of S, AR(1)-inflated")
        return (f"    {name + ':':<{width}} {value:.6g} +/- {sd:.4g} (profiled: "
                f"{how}) {unit}".rstrip())
    return f"    {name + ':':<{width}} {value:.6g} (fixed) {unit}".rstrip()


def _variables(res, width: int) -> list:
    """[[Variables]], then [[Derived]] where the fit derived quantities."""
    lines = ["[[Variables]]"]
    lines += [_variable(res, name, value, width) for name, value in res.params.items()]
    if res.derived:
        lines.append("[[Derived]]")
        for name, value in res.derived.items():
            lines.append(f"    {name + ':':<{width}} {value:.6g} "
                         f"{unit_of(name, res.units, res.per_mass)}".rstrip())
    return lines


def _interval_lines(res, width: int) -> list:
    """[[Intervals]]: the 95 % intervals allowing for correlated residuals (none where the
    result carries no Jacobian or they cannot be computed)."""
    if res.jac is None or not res.varied:
        return []
    try:
        ci = res.conf_interval(0.95)
        _, lags = res._hac()
    except (ValueError, np.linalg.LinAlgError):
        return []
    lines = [f"[[Intervals]] 95 %, allowing for correlated residuals "
             f"({_intervals.METHOD}, L = {lags} samples); delta-method stderr beside"]
    for name in res.varied:
        lo, hi = ci[name]
        lines.append(f"    {name + ':':<{width}} [{lo:.6g}, {hi:.6g}]  "
                     f"(stderr {res.stderr[name]:.4g}, HAC sd "
                     f"{res.hac_stderr[name]:.4g})")
    for name in res.profiled:
        lo, hi = ci[name]
        how = ("every value gives the fitted halt" if "interval" in
               res.profiled[name] else "the others allow for its uncertainty")
        lines.append(f"    {name + ':':<{width}} [{lo:.6g}, {hi:.6g}]  (profiled; {how})")
    return lines


def _correlations(res, min_correl: float) -> list:
    """[[Correlations]]: the pairs correlated by at least ``min_correl``, strongest first."""
    pairs = []
    n = len(res.varied)
    for i in range(n):
        for j in range(i + 1, n):
            c = float(res.correlation[i, j])
            if math.isfinite(c) and abs(c) >= min_correl:
                pairs.append((abs(c), f"    C({res.varied[i]}, {res.varied[j]})", c))
    lines = [f"[[Correlations]] (unreported correlations are < {min_correl:.3f})"]
    if pairs:
        w = max(len(p[1]) for p in pairs)
        for _, label, c in sorted(pairs, reverse=True):
            lines.append(f"{label:<{w}} = {c:+.4f}")
    return lines


def _notes(res) -> list:
    """[[Warning]] about the data and [[Note]] of the checks."""
    lines = [f"[[Warning]] {note}" for note in res.warnings]
    for key in ("note_decay", "note_bound", "note_first_halt", "note_other_halt", "note"):
        if key in res.diagnostics:
            lines.append(f"[[Note]] {res.diagnostics[key]}")
    return lines


def fit_report(res, min_correl: float) -> str:
    """A text report like lmfit's fit_report: statistics, values, correlations.

    Arguments:
        res: the :class:`~dampax._fit._result.FitResult`.
        min_correl: the smallest correlation reported.

    Returns:
        The report, its sections one after another.
    """
    width = max(len(k) for k in res.params) + 1
    lines = (_verdict(res) + _model(res) + _statistics(res) + _variables(res, width)
             + _interval_lines(res, width) + _correlations(res, min_correl) + _notes(res))
    return "\n".join(lines)
