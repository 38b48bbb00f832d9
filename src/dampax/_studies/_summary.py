"""Solve several models of one oscillator and summarise them (halt, turning points, curves).

``dampax solve`` prints what :func:`run_models` computes and ``dampax._plot.plot_results``
draws it: one evaluation, compiled once per model and re-used for other numbers.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .._cache import call_cached_tree
from .._models._registry import MODELS, applicable_models, check_models
from .._oscillator import Oscillator, as_float, check_finite
from .._solve import solve_checked, turning_points_checked


@dataclasses.dataclass
class ModelResult:
    """Solution and summary of one model; ``error`` says why it is missing (then no solution)."""

    name: str
    solution: object | None
    halt_time: float = math.nan
    halt_position: float = math.nan
    turning_t: np.ndarray | None = None
    turning_x: np.ndarray | None = None
    error: str | None = None

    @property
    def label(self) -> str:
        return MODELS[self.name].label


@dataclasses.dataclass
class ModelRun:
    """Everything :func:`run_models` computed for one oscillator and initial state."""

    osc: Oscillator
    x0: float
    v0: float
    results: dict[str, ModelResult]
    t_end: float
    notes: list[str]

    def ok(self) -> dict[str, ModelResult]:
        """The models that could be solved, in table order."""
        return {k: r for k, r in self.results.items() if r.error is None}

    def curves(self, t) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """x(t) and E(t) of every solved model at the times t (compiled, one call per model).

        Arguments:
            t: 1-d array of times [s].

        Returns:
            {name: (x, E)} in table order.
        """
        t = jnp.asarray(t, dtype=float)
        return {k: tuple(map(np.asarray, _curves(r.solution, t))) for k, r in self.ok().items()}


# One compiled program per model (name and n_turning are static), reused for every oscillator
# and initial state: a second call with other numbers costs no compilation. The programs are
# kept (``_cache.call_cached_tree``): a repeated ``dampax solve`` neither traces nor compiles.


def _solve_and_summarize(osc, x0, v0, *, name: str, n_turning: int):
    # x0, v0 were checked by run_models, the registry's options are valid: trusted here
    sol = solve_checked(osc, x0, v0, **MODELS[name].solve_options)
    return sol, _summary_of(sol, n_turning=n_turning)


def _summary_of(sol, *, n_turning: int):
    return sol.halt_time, sol.halt_position, turning_points_checked(sol, n_turning)


def _x_and_energy(sol, t):
    return sol.x(t), sol.energy(t)


def _solve_one(osc, x0, v0, name: str, n_turning: int):
    """(solution, summary) of one model, by the kept program of (name, n_turning)."""
    return call_cached_tree("solve-model", (name, n_turning), functools.partial(
        _solve_and_summarize, name=name, n_turning=n_turning), osc, x0, v0)


def _summarize(sol, n_turning: int):
    """(halt time, halt position, (turning times, positions)) of a solution, kept program."""
    return call_cached_tree("solve-summary", n_turning,
                            functools.partial(_summary_of, n_turning=n_turning), sol)


def _curves(sol, t):
    """(x(t), E(t)) of a solution, kept program."""
    return call_cached_tree("solve-curves", (), _x_and_energy, sol, t)


def default_t_end(osc: Oscillator, halt_times: Sequence[float]) -> float:
    """Time span of a plot: half an undamped period past the latest finite halt time.

    Arguments:
        osc: the oscillator (its undamped period T0 = 2 pi / w0 sets the margin).
        halt_times: halt times [s] of the models; inf / nan entries are ignored.

    Returns:
        t_end [s]: latest finite halt + T0/2, at most 100 T0; 6 T0 when nothing halts.
    """
    period = 2.0 * math.pi / as_float(osc.omega0)
    finite = [t for t in halt_times if math.isfinite(t)]
    if not finite:
        return 6.0 * period
    return min(max(finite) + 0.5 * period, 100.0 * period)


def _result(name, sol, summary) -> ModelResult:
    tau, x_h, (tt, tx) = summary
    return ModelResult(name, sol, as_float(tau), as_float(x_h), np.asarray(tt), np.asarray(tx))


def run_models(osc: Oscillator, x0: float, v0: float, *, models: Sequence[str] | None = None,
               n_turning: int = 6, t_end: float | None = None) -> ModelRun:
    """Solve and summarise several models of one oscillator with compiled code.

    The analytic models are solved under ``jax.jit``, one compiled program per model that is
    reused for other numbers; a model that comes out invalid keeps its ``result`` message as
    ``error``. The reference is integrated over [0, t_end].

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator`.
        x0, v0: initial displacement [m] and velocity [m/s].
        models: names from the registry (``dampax._models._registry.MODELS``); default
            :func:`~dampax._models._registry.applicable_models`.
        n_turning: how many turning points to compute per model.
        t_end: time span [s] (reference integration, plots); default :func:`default_t_end`.

    Returns:
        A :class:`ModelRun`; ``results[name].error`` holds the reason a model is missing.
    """
    if np.ndim(osc.m) or any(np.ndim(v) for v in (osc.k, osc.mu, osc.b, osc.D, osc.g)):
        raise ValueError("osc: plots and summaries need a scalar Oscillator, not a batch")
    check_finite("x0", x0)
    check_finite("v0", v0)
    x0, v0 = float(x0), float(v0)
    if n_turning < 0:
        raise ValueError(f"n_turning must be >= 0, got {n_turning}")
    if t_end is not None and not (math.isfinite(t_end) and t_end > 0.0):
        raise ValueError(f"t_end must be a finite time > 0, got {t_end}")
    names = applicable_models(osc) if models is None else check_models(models)
    notes: list[str] = []
    results: dict[str, ModelResult] = {}
    for k in names:
        if k == "reference":
            continue
        sol, summary = _solve_one(osc, jnp.asarray(x0), jnp.asarray(v0), k, n_turning)
        if bool(sol.valid):
            results[k] = _result(k, sol, summary)
        else:
            results[k] = ModelResult(k, None, error=sol.message)
    if t_end is None:
        t_end = default_t_end(osc, [r.halt_time for r in results.values() if r.error is None])
    if "reference" in names:
        try:
            sol = solve_checked(osc, x0, v0, method="reference", t_end=t_end)
            results["reference"] = _result("reference", sol, _summarize(sol, n_turning))
        except ValueError as err:  # e.g. its step budget ran out before t_end
            notes.append(f"reference integrator failed, skipped: {err}")
            results["reference"] = ModelResult("reference", None, error=str(err))
    results = {k: results[k] for k in MODELS if k in results}
    return ModelRun(osc, x0, v0, results, float(t_end), notes)


def damping_ratios(osc: Oscillator, x0: float, v0: float) -> tuple[float, float, float]:
    """The dimensionless ratios d0/(w0 A0), d1/w0, d2 A0/w0 (docs/DESIGN.md section 1).

    Arguments:
        osc: a scalar oscillator.
        x0, v0: initial state; A0 = sqrt(x0^2 + (v0/w0)^2).

    Returns:
        (d0/(w0 A0), d1/w0, d2 A0/w0); the first is inf (nan without friction) when A0 = 0.
    """
    w0 = as_float(osc.omega0)
    d0, d1, d2 = (as_float(d) for d in osc.damping_coefficients)
    A0 = math.hypot(x0, v0 / w0)
    r0 = d0 / (w0 * A0) if A0 > 0 else (math.inf if d0 > 0 else math.nan)
    return r0, d1 / w0, d2 * A0 / w0
