"""The fit models: their curves, their coordinates and settings (:data:`FIT_MODELS`, one
entry each), and the budget of the reference integrator inside a fit.

Fit models:

- "ansatz": x(t) = offset + A f(t - t0) cos(wd (t - t0) + phi), the closed form of Lelas &
  Pezer (eqs. 11, 20) with a = d2 A, b' = d1, c = d0 / A (eq. 21), its phase advancing at the
  viscous damped frequency wd = sqrt(w0^2 - d1^2) (w0 when b = 0; ``_params.phase_rate``: with
  eq. 11's w0 a fit of w0 returns wd). Fitted in the coordinates (x0, y = A sin(phi)):
  x0 = A cos(phi) and v0 = -(a + b' + c) x0 - wd y is the matched (x0, v0) <-> (A, phi) map
  of eqs. 22-23, so no quartic is solved inside the fit.
- "reference": eq. 3 integrated by ``solve(method="reference")`` (DOP853, exact stick-slip)
  from (x0, v0), forward-mode derivatives; started from the "ansatz" fit.
- "envelope": E(t) = offset + A f(t - t1) for a table of successive maxima (eq. 20).

The solver that fits them (residuals, optimisers, covariance) is ``_core``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .._cache import call_cached, prepare_cached
from .._models._cubic import phase_excess_sampled
from .._models._decay import _decay_constants, _decay_from, decay
from .._oscillator import Oscillator
from .._solve import solve
from .._trig import sincos
from ._params import (
    Constants,
    EnvelopeParams,
    Setup,
    TraceCoords,
    TraceParams,
    ansatz_v0,
    ansatz_y,
    damping_d,
    envelope_setup,
    phase_rate,
    start_amplitude,
    trace_setup,
)

#: restarts of Levenberg-Marquardt of a fit model (``FitModel.lm_rounds``)
LM_ROUNDS = 5


class ReferenceOptions(NamedTuple):
    """Budget and tolerances of the reference integrator inside a fit (static)."""

    max_swings: int
    rtol: float
    atol: float


#: margins of the half-swing budget over the half swings of a span at the start's w0: a fit's
#: window, generated data and a posterior's curve, a batch of jittered starts (whose w0 vary)
SWING_MARGIN = {"fit": 1.15, "data": 1.2, "starts": 1.5}


#: the smallest budget of a fit's exact model (``use="starts"``): its compiled programs take
#: the budget as a static size, so traces of 2 to 15 periods (budgets 16, 32, 64 before) each
#: compiled them again (13-15 s per budget, issue 36); a larger budget costs memory, not time
#: (one papers'-regime fit with budget 32, 64, 128: 1.48, 1.39, 1.51 s CPU; 1.66, 1.74, 1.80 s)
MIN_FIT_SWINGS = 64


def swing_budget(span: float, w0: float, use: str = "fit") -> int:
    """The reference's half-swing budget over ``span`` seconds at angular frequency ``w0``:
    the span's half swings w0 span / pi times :data:`SWING_MARGIN` [``use``], plus 8; for
    ``use="starts"`` rounded up to a power of two (at least :data:`MIN_FIT_SWINGS`), so that
    windows of similar length share the compiled fit. The one home of the budget (issue 33).
    """
    need = int(SWING_MARGIN[use] * span * w0 / math.pi) + 8
    return 1 << int(math.ceil(math.log2(max(need, MIN_FIT_SWINGS)))) if use == "starts" \
        else need


# ----------------------------------------------------------------------------------------------
# the fit models: curve and per-model settings


def _ansatz_curve(tau, q: TraceCoords, consts: Constants, span, opts):
    """x(tau) = offset + A f(tau) cos(wd tau + phi), eqs. 11, 20-21 with the phase advancing
    at the viscous damped frequency wd = sqrt(w0^2 - d1^2) (``_params.phase_rate``; w0 when
    b = 0); x0 = A cos(phi), y = A sin(phi).

    With a cubic stiffness (``consts.k3`` not None; docs/cubic_stiffness.md):
    x = offset + A f [cos th + beta f^2 (cos 3th - cos th)], th = w0 tau + phi + P(tau),
    kappa = (3/4) k3 A^2 / (m w0^2), beta = k3 A^2 / (32 m w0^2).
    """
    d0, d1, d2 = damping_d(q.mu, q.b, q.D, q.w0, consts.m, consts.g)
    A = jnp.sqrt(q.x0 * q.x0 + q.y * q.y)
    phi = jnp.arctan2(q.y, q.x0)
    if consts.k3 is None:
        f = decay(tau, d2 * A, d1, d0 / A)
        return q.offset + A * f * sincos(phase_rate(q.w0, d1) * tau + phi)[1]

    k = _decay_constants(d2 * A, d1, d0 / A)
    f = _decay_from(k, tau)
    ratio = consts.k3 * A * A / (consts.m * q.w0 * q.w0)
    th = phase_rate(q.w0, d1) * tau + phi + phase_excess_sampled(k, q.w0, 0.75 * ratio,
                                                              tau, f)
    cth, sth = jnp.cos(th), jnp.sin(th)
    return q.offset + A * f * (cth - (ratio / 32.0) * f * f * 4.0 * cth * sth * sth)


def reference_solution(q: TraceCoords, consts: Constants, span, opts: ReferenceOptions,
                       adjoint: str = "forward"):
    """The reference solution (DOP853, exact stick-slip) of eq. 3 from (x0, v0 = y) over the
    window's span; with static friction ``consts.mu_s`` when it is not None."""

    m, g, k3 = consts.motion
    osc = Oscillator(m=m, k=m * q.w0 * q.w0, mu=q.mu, b=q.b, D=q.D, g=g, k3=k3,
                     mu_s=consts.mu_s)
    return solve(osc, q.x0, q.y, method="reference", t_end=span * (1.0 + 1e-6) + 1e-9,
                 rtol=opts.rtol, atol=opts.atol, max_swings=opts.max_swings, adjoint=adjoint)


def _reference_curve(tau, q: TraceCoords, consts: Constants, span, opts: ReferenceOptions):
    """x(tau) of eq. 3 from (x0, v0 = y): :func:`reference_solution` (forward mode)."""
    return q.offset + reference_solution(q, consts, span, opts).x(tau)


def _envelope_curve(tau, q: EnvelopeParams, consts: Constants, span, opts):
    """E(tau) = offset + A f(tau), f of eq. 20 with w0 fixed (eq. 21)."""
    d0, d1, d2 = damping_d(q.mu, q.b, q.D, consts.w0, consts.m, consts.g)
    return q.offset + q.A * decay(tau, d2 * q.A, d1, d0 / q.A)


def _coords_with(p: TraceParams, y) -> TraceCoords:
    return TraceCoords(mu=p.mu, b=p.b, D=p.D, w0=p.w0, offset=p.offset, x0=p.x0, y=y)


def _params_with(q: TraceCoords, v0) -> TraceParams:
    return TraceParams(mu=q.mu, b=q.b, D=q.D, w0=q.w0, offset=q.offset, x0=q.x0, v0=v0)


def _ansatz_coords(p: TraceParams, consts: Constants) -> TraceCoords:
    return _coords_with(p, ansatz_y(p, consts))


def _ansatz_params(q: TraceCoords, consts: Constants) -> TraceParams:
    return _params_with(q, ansatz_v0(q.x0, q.y, q.mu, q.b, q.D, q.w0, consts.m, consts.g))


def _ansatz_amplitude_phase(params: dict, q, m, g):
    """(A, phi) of the fitted ansatz: its coordinates x0 = A cos(phi), y = A sin(phi)."""
    x0, y = float(q.x0), float(q.y)
    return math.hypot(x0, y), math.atan2(y, x0)


def _matched(m, w0, mu, b, D, g, x0, v0):
    """(A, phi) of the ansatz matched (eqs. 22-23) to (x0, v0); NaN where it does not exist
    (traceable: the program of :func:`_reference_amplitude_phase`)."""
    sol = solve(Oscillator(m=m, k=m * w0 * w0, mu=mu, b=b, D=D, g=g), x0, v0)
    return sol.amplitude, sol.phase


def _matched_args(params: dict, m, g) -> tuple:
    return tuple(np.asarray(float(v)) for v in (m, params["w0"], params["mu"], params["b"],
                                                 params["D"], g, params["x0"], params["v0"]))


def _reference_amplitude_phase(params: dict, q, m, g):
    """(A, phi) of the ansatz matched (eqs. 22-23) to the fitted (x0, v0); where that ansatz
    does not exist (an overdamped motion, b >= 2 m w0: eq. 3 holds, the ansatz's oscillation
    does not), the start's undamped amplitude and phase, x0 = A cos(phi), v0 = -w0 A sin(phi),
    so that the fit of the exact model is judged on its own (it failed before as "the
    fitted amplitude ... is not a positive finite number" with the truth inside its
    intervals). A kept program (``_cache.call_cached``), started early by
    :func:`prepare_amplitude_phase`: an eager solve compiled it on the fit's last step (0.3 s
    of a cold fit, issue 36)."""
    A, phi = call_cached("fit-matched", (), _matched, *_matched_args(params, m, g))
    A, phi = float(A), float(phi)
    if not (math.isfinite(A) and A > 0):
        A = start_amplitude(params)
        phi = math.atan2(-float(params["v0"]) / float(params["w0"]), float(params["x0"]))
    return A, phi


def prepare_amplitude_phase(params: dict, m, g) -> None:
    """Start compiling :func:`_reference_amplitude_phase`'s program in the background."""
    prepare_cached("fit-matched", (), _matched, *_matched_args(params, m, g))


@dataclass(frozen=True)
class FitModel:
    """One fit model: its curve and its settings. A new model is one entry of FIT_MODELS.

    Attributes:
        name: the ``model`` argument of the fits.
        kind: "trace" (parameters TraceParams) or "envelope" (EnvelopeParams).
        description: one line, for the command-line help.
        params: the type of the reported parameters.
        coords: the type of the model's coordinates (and of the internal theta).
        curve: (tau, q, consts, span, opts) -> the model at tau = t - t0, q in the model's
            coordinates.
        setup: (p0, t, consts, model) -> the reference point and scales (``_params.Setup``).
        to_coords, to_params: (parameters, consts) <-> the model's coordinates.
        y_scale: trace models: (w0, sx) -> the scale of the velocity coordinate y.
        amplitude_phase: trace models: (params, q, m, g) -> (A, phi) of the fitted ansatz.
        lm_rounds: restarts of Levenberg-Marquardt (see :func:`_lm_rounds`).
        start_from: fit this model first and start from its optimum (``fit``).
        reuse_jacobian: the statistics reuse the optimizer's last residuals and Jacobian (no
            further copy of the model to compile).
        integrates: the curve integrates eq. 3 and needs :class:`ReferenceOptions`.
    """

    name: str
    kind: str
    description: str
    params: type
    coords: type
    curve: Callable
    setup: Callable
    to_coords: Callable
    to_params: Callable
    y_scale: Callable | None = None
    amplitude_phase: Callable | None = None
    lm_rounds: int = LM_ROUNDS
    start_from: str | None = None
    reuse_jacobian: bool = False
    integrates: bool = False


def _identity(p, consts):
    return p


#: the fit models by name: a new model is one entry
FIT_MODELS = {m.name: m for m in (
    FitModel(
        name="ansatz", kind="trace", description="the closed form of Lelas & Pezer (fast)",
        params=TraceParams, coords=TraceCoords, curve=_ansatz_curve, setup=trace_setup,
        to_coords=_ansatz_coords, to_params=_ansatz_params, y_scale=lambda w0, sx: sx,
        amplitude_phase=_ansatz_amplitude_phase),
    FitModel(
        name="reference", kind="trace",
        description="eq. 3 integrated by DOP853, started from the ansatz fit",
        params=TraceParams, coords=TraceCoords, curve=_reference_curve, setup=trace_setup,
        to_coords=lambda p, consts: _coords_with(p, p.v0),
        to_params=lambda q, consts: _params_with(q, q.y), y_scale=lambda w0, sx: w0 * sx,
        amplitude_phase=_reference_amplitude_phase,
        # started from the ansatz optimum: one round
        lm_rounds=1, start_from="ansatz", reuse_jacobian=True, integrates=True),
    FitModel(
        name="envelope", kind="envelope", description="E(t) = A f(t) of the maxima",
        params=EnvelopeParams, coords=EnvelopeParams, curve=_envelope_curve,
        setup=envelope_setup, to_coords=_identity, to_params=_identity),
)}
#: the models of trace fits (the ``model`` argument of ``fit``)
MODELS = tuple(name for name, m in FIT_MODELS.items() if m.kind == "trace")


def model_curve(model: FitModel, t, q, setup: Setup, opts):
    """The model at the data times, q in the model's coordinates."""
    return model.curve(t - setup.t0, q, setup.consts, setup.span, opts)

