"""Fitting the damping constants mu, b, D to measured free-decay traces (issue 5).

Models (the ``model`` argument):

- "ansatz": x(t) = offset + A f(t - t0) cos(w0 (t - t0) + phi), the closed form of Lelas &
  Pezer (DESIGN 2.1-2.3) with a = d2 A, b' = d1, c = d0 / A and f = ``_ansatz.decay``.
  Fitted in the coordinates (x0, A sin(phi)): x0 = A cos(phi) is the initial position and the
  initial velocity is v0 = -(a + b' + c) x0 - w0 A sin(phi); the matched (x0, v0) <-> (A, phi)
  map of eqs. 22-23 is this one, so the reported (x0, v0) is the fitted initial state (its
  covariance by the delta method), and no quartic has to be solved inside the fit.
- "reference": eq. 3 integrated by ``solve(method="reference")`` (diffrax, exact stick-slip)
  from (x0, v0), with forward-mode derivatives; started from the "ansatz" fit.
- envelope fits (:func:`fit_envelope`): E(t) = A f(t - t0) for a table of successive maxima.

Parameters: the damping constants named in ``free`` (mu, b, D >= 0 as log-parameters), and
always the nuisance parameters: x0, v0 at the fit start, the equilibrium ``offset`` and, with
``fit_omega0``, w0 (m fixed, k = m w0^2, so mu, b, D keep their units). Non-free damping
constants stay at the oscillator's values. Internally every parameter set has the same layout
(mu, b, D, w0, offset, x0, v0) and a mask says which ones vary (a fixed one is pinned by an
extra residual row), so one compiled solver serves every candidate model of
:func:`compare_models`, and :func:`fit_arrays` vmaps over traces.

Optimizers: optimistix Levenberg-Marquardt (default), optax adam or L-BFGS on the same
(robust) sum of squares. ``loss="soft_l1"``: rho(z) = 2 (sqrt(1 + z) - 1) of z = (r / s)^2 as
scipy, by residual reweighting r -> r sqrt(rho(z) / z) (an exact least-squares form of the
robust loss), with s = 1.4826 MAD of the residuals of a linear-loss fit. Covariance:
s2 (J^T J)^-1 in the internal (log) coordinates at the optimum, s2 = chi2 / (n - n_varys),
carried to the physical parameters by the delta method (computed as (J_p^T J_p)^-1 with the
Jacobian J_p = J G^-1 in physical coordinates, G the Jacobian of the map, which stays exact
when a log-parameter tends to 0).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optax
import optimistix as optx

from ._ansatz import decay, halt_time
from ._oscillator import Oscillator
from ._trace import Trace, load_trace

__all__ = [
    "FitResult", "ModelComparison", "ArrayFit", "fit", "fit_arrays", "fit_envelope",
    "compare_models", "compare_envelope_models", "initial_guess", "example_trace",
    "residual_function",
    "PARAMS", "ENVELOPE_PARAMS", "CANDIDATES", "add_arguments", "run",
]

#: layout of the parameter vector of trace fits (:func:`fit_arrays`)
PARAMS = ("mu", "b", "D", "w0", "offset", "x0", "v0")
#: layout of the parameter vector of envelope fits
ENVELOPE_PARAMS = ("mu", "b", "D", "A", "offset")
DAMPING = ("mu", "b", "D")
#: the candidate damping models of :func:`compare_models`
CANDIDATES = (("mu",), ("D",), ("b",), ("mu", "D"), ("b", "D"), ("mu", "b"), ("mu", "b", "D"))
MODELS = ("ansatz", "reference")
LOSSES = ("linear", "soft_l1")
OPTIMIZERS = ("lm", "adam", "lbfgs")
_UNITS = {"mu": "", "b": "kg/s", "D": "kg/m", "w0": "rad/s", "offset": "", "x0": "",
          "v0": "/s", "A": "", "k": "N/m"}
_MAX_STEPS = {"lm": 256, "lbfgs": 1000, "adam": 4000}
_METHOD_NAMES = {"lm": "Levenberg-Marquardt (optimistix)", "adam": "adam (optax)",
                 "lbfgs": "L-BFGS (optax)"}
_MAD = 1.482602218505602  # 1 / Phi^-1(3/4): MAD -> sigma for Gaussian noise


# ----------------------------------------------------------------------------------------------
# the pure core: parameter maps, model curves, residuals, one optimisation


def _damping_d(mu, b, D, w0, m, g):
    """(d0, d1, d2) of eq. 21."""
    return 2.0 * mu * g / (math.pi * w0), b / (2.0 * m), 4.0 * D * w0 / (3.0 * math.pi * m)


def _d_to_physical(d0, d1, d2, w0, m, g):
    """Inverse of eq. 21: (mu, b, D) from (d0, d1, d2)."""
    return d0 * math.pi * w0 / (2.0 * g), 2.0 * m * d1, 3.0 * math.pi * m * d2 / (4.0 * w0)


def _ansatz_w(x0, v0, mu, b, D, w0, m, g, iters=40):
    """A sin(phi) of the ansatz through (x0, v0): v0 = -(d2 A + d1 + d0/A) x0 - w0 A sin(phi)."""
    d0, d1, d2 = _damping_d(mu, b, D, w0, m, g)

    def body(_, w):
        A = jnp.sqrt(x0 * x0 + w * w)
        A = jnp.where(A > 0.0, A, 1.0)
        return -(v0 + (d2 * A + d1 + d0 / A) * x0) / w0

    return jax.lax.fori_loop(0, iters, body, -v0 / w0)


def _setup(p0, t, model, consts):
    """Reference point (theta = 0 at p0) and scales of the internal coordinates."""
    m, g = consts[0], consts[1]
    t0 = t[0]
    span = jnp.maximum(jnp.max(t) - t0, 1e-12)
    if model == "envelope":
        w0 = consts[2]
        A = jnp.maximum(jnp.abs(p0[3]), 1e-300)
        sx = A
        floors = _d_to_physical(1e-4 * w0 * A, 1e-4 * w0, 1e-4 * w0 / A, w0, m, g)
        ref = jnp.stack([p0[0], p0[1], p0[2], A, p0[4]])
        scale = jnp.stack([1.0, 1.0, 1.0, 1.0, sx])
    else:
        mu, b, D, w0, off, x0, v0 = (p0[i] for i in range(7))
        sx = jnp.sqrt(x0 * x0 + (v0 / w0) ** 2)
        sx = jnp.where(sx > 0.0, sx, 1.0)
        floors = _d_to_physical(1e-4 * w0 * sx, 1e-4 * w0, 1e-4 * w0 / sx, w0, m, g)
        if model == "ansatz":
            y = _ansatz_w(x0, v0, mu, b, D, w0, m, g)
            y_scale = sx
        else:
            y, y_scale = v0, w0 * sx
        ref = jnp.stack([mu, b, D, w0, off, x0, y])
        scale = jnp.stack([1.0, 1.0, 1.0, 1.0 / span, sx, sx, y_scale])
    floors = jnp.stack(floors)
    return dict(ref=ref, scale=scale, floors=floors, sx=sx, t0=t0, span=span,
                  consts=consts)


def _log_bounds(st, vary):
    """(reference, lowest log-offset) of the damping log-parameters: a constant that the data
    do not support stops at 1e-6 of its small floor (~1e-10 of the damping scale) instead of
    drifting to -inf, so the optimizer converges (gracefully at ~0)."""
    dref = jnp.where(vary[:3], jnp.maximum(st["ref"][:3], st["floors"]), 1.0)
    return dref, jnp.log(1e-6 * st["floors"] / dref)


def _clamped(theta, st, vary):
    _, lo = _log_bounds(st, vary)
    return theta.at[:3].set(jnp.maximum(theta[:3], lo))


def _physical(theta, st, vary, model, clamp=True):
    """Model parameters from the internal vector; fixed entries stay at their p0 value."""
    ref, scale = st["ref"], st["scale"]
    dref, lo = _log_bounds(st, vary)
    th = jnp.maximum(theta[:3], lo) if clamp else theta[:3]
    damp = jnp.where(vary[:3], dref * jnp.exp(th), ref[:3])
    if model == "envelope":
        A = ref[3] * jnp.exp(theta[3])
        off = jnp.where(vary[4], ref[4] + scale[4] * theta[4], ref[4])
        return damp[0], damp[1], damp[2], A, off
    lin = ref[3:] + scale[3:] * theta[3:]
    w0 = jnp.where(vary[3], lin[0], ref[3])
    off = jnp.where(vary[4], lin[1], ref[4])
    return damp[0], damp[1], damp[2], w0, off, lin[2], lin[3]


def _reported(theta, st, vary, model, clamp=True):
    """The reported (physical) parameter vector in the layout PARAMS / ENVELOPE_PARAMS."""
    P = _physical(theta, st, vary, model, clamp)
    if model != "ansatz":
        return jnp.stack(P)
    mu, b, D, w0, off, x0, y = P
    m, g = st["consts"][0], st["consts"][1]
    d0, d1, d2 = _damping_d(mu, b, D, w0, m, g)
    A = jnp.sqrt(x0 * x0 + y * y)
    v0 = -(d2 * A + d1 + d0 / A) * x0 - w0 * y
    return jnp.stack([mu, b, D, w0, off, x0, v0])


def _curve(t, P, st, model, ref_opts):
    """The model x(t) (or E(t) for envelopes) at the data times."""
    m, g = st["consts"][0], st["consts"][1]
    tau = t - st["t0"]
    if model == "envelope":
        mu, b, D, A, off = P
        d0, d1, d2 = _damping_d(mu, b, D, st["consts"][2], m, g)
        return off + A * decay(tau, d2 * A, d1, d0 / A)
    mu, b, D, w0, off, x0, y = P
    if model == "ansatz":
        d0, d1, d2 = _damping_d(mu, b, D, w0, m, g)
        A = jnp.sqrt(x0 * x0 + y * y)
        phi = jnp.arctan2(y, x0)
        f = decay(tau, d2 * A, d1, d0 / A)
        return off + A * f * jnp.cos(w0 * tau + phi)
    from ._solve import solve

    max_swings, rtol, atol = ref_opts
    osc = Oscillator(m=m, k=m * w0 * w0, mu=mu, b=b, D=D, g=g)
    sol = solve(osc, x0, y, method="reference", t_end=st["span"] * (1.0 + 1e-6) + 1e-9,
                rtol=rtol, atol=atol, max_swings=max_swings, adjoint="forward")
    return off + sol.x(tau)


def _robust(r, fs):
    """soft_l1 reweighting: r sqrt(rho(z)/z), z = (r/fs)^2, rho(z)/z = 2/(1 + sqrt(1 + z))."""
    z = (r / fs) ** 2
    return r * jnp.sqrt(2.0 / (1.0 + jnp.sqrt(1.0 + z)))


def _residual_rows(theta, args, model, ref_opts, clamp=True, with_curve=False):
    """Normalised residuals (model - data)/sx of the data rows, robust-weighted, masked."""
    t, x, wt, st, vary, fs = args
    P = _physical(theta, st, vary, model, clamp)
    curve = _curve(t, P, st, model, ref_opts)
    r = (curve - x) / st["sx"] * wt
    r = jnp.where(wt > 0.0, _robust(r, fs / st["sx"]), 0.0)
    return (r, curve) if with_curve else r


def _residual_fn(theta, args, model, ref_opts):
    """Data rows plus one pin row per parameter: theta_i for fixed ones (0 at the optimum)."""
    vary = args[4]
    pins = jnp.where(vary, 0.0, theta)
    return jnp.concatenate([_residual_rows(theta, args, model, ref_opts), pins])


def _materialised(fn, args):
    """``fn(theta, args)`` whose derivative is an explicit Jacobian matrix (custom_jvp).

    Its JVP computes r and J = jacfwd(fn) together and returns J @ dtheta, so the linear map
    that optimistix keeps per step is a matrix product: materialising it (as QR or the normal
    equations do) and transposing it cost nothing more, and the model (for "reference" the
    whole diffrax integrator) is traced and compiled once per step instead of once for the
    linearisation and again for its transpose.
    """
    @jax.custom_jvp
    def residuals(theta):
        return fn(theta, args)

    @residuals.defjvp
    def residuals_jvp(primals, tangents):
        (theta,), (dtheta,) = primals, tangents
        J, r = jax.jacfwd(lambda th: (fn(th, args),) * 2, has_aux=True)(theta)
        return r, J @ dtheta

    return lambda theta, _args: residuals(theta)


def _optax_minimise(loss_fn, theta0, optimizer, max_steps, rtol, atol):
    """Minimise loss_fn with optax adam (decaying rate) or L-BFGS; (theta, code, steps)."""
    lbfgs = optimizer == "lbfgs"
    if lbfgs:
        opt = optax.lbfgs()
        value_and_grad = optax.value_and_grad_from_state(loss_fn)
    else:
        opt = optax.adam(optax.exponential_decay(0.02, max_steps, 1e-3))
        value_and_grad = jax.value_and_grad(loss_fn)

    def cond(c):
        k, _, _, _, done = c
        return (k < max_steps) & ~done

    def body(c):
        k, theta, state, prev, _ = c
        if lbfgs:
            value, grad = value_and_grad(theta, state=state)
            updates, state = opt.update(grad, state, theta, value=value, grad=grad,
                                        value_fn=loss_fn)
        else:
            value, grad = value_and_grad(theta)
            updates, state = opt.update(grad, state, theta)
        theta = optax.apply_updates(theta, updates)
        small = jnp.max(jnp.abs(updates)) <= atol + rtol * jnp.max(jnp.abs(theta))
        flat = jnp.abs(prev - value) <= rtol * jnp.abs(value) + 1e-300
        return k + 1, theta, state, value, small & flat & jnp.isfinite(value)

    init = (jnp.array(0), theta0, opt.init(theta0), jnp.array(jnp.inf, dtype=theta0.dtype),
            jnp.array(False))
    k, theta, _, _, done = jax.lax.while_loop(cond, body, init)
    if lbfgs:
        code = jnp.where(done, 0, 1)
    else:  # adam: a finished schedule counts as converged
        code = jnp.where(jnp.isfinite(loss_fn(theta)), 0, 2)
    return theta, code, k


_LM_ROUNDS = 5


def _lm_rounds(fn, theta0, args, model, ref_opts, max_steps, rtol, atol, rounds):
    """optimistix Levenberg-Marquardt in ``rounds`` restarts, for constants that go to 0.

    optimistix damps with lambda I (Levenberg), which is not scale-invariant: a log-parameter
    whose constant tends to 0 has a vanishing Jacobian column and creeps towards its bound by
    tiny steps. Between rounds (1) a Gauss-Newton step in the physical constants p (where the
    model is smooth through p = 0) moves a constant that it sends to p <= 0 next to its lower
    bound (~1e-10 of the damping scale; the optimizer can still raise it), and (2) the log
    coordinates are rescaled so that their columns match the largest nuisance column
    (Marquardt's scaling, per round). A round after a converged one with nothing changed is
    skipped. Returns (theta, code, steps, final) with final = (r, J) for one round.
    """
    st, vary = args[3], args[4]
    # normal equations: 5-10x faster per step than the default QR on tall Jacobians; the
    # internal coordinates are normalised, so J^T J stays well conditioned
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    if rounds == 1:
        sol = optx.least_squares(fn, solver, theta0, args=args, max_steps=int(max_steps),
                                 throw=False)
        info = sol.state.f_info  # residuals and Jacobian at the returned (accepted) point
        return (_clamped(sol.value, st, vary), _result_code(sol.result),
                sol.stats["num_steps"], (info.residual, info.jac.as_matrix()))
    per_round = max(int(max_steps) // rounds, 16)
    is_log = jnp.arange(theta0.shape[0]) < 3
    dref, lo = _log_bounds(st, vary)

    def rows(th):
        r = _residual_rows(th, args, model, ref_opts, clamp=False)
        return r, r

    def solve(theta, scale):
        def scaled(u, a):
            return fn(theta + scale * u, a)

        sol = optx.least_squares(scaled, solver, jnp.zeros_like(theta), args=args,
                                 max_steps=per_round, throw=False)
        return (_clamped(theta + scale * sol.value, st, vary), sol.stats["num_steps"],
                _result_code(sol.result))

    def one(carry, _):
        theta, scale, steps, code, redo = carry
        again = (steps == 0) | (code != 0) | redo
        theta, n_steps, code = jax.lax.cond(again, solve, lambda th, sc: (th, 0, code),
                                            theta, scale)
        J, r = jax.jacfwd(rows, has_aux=True)(theta)
        # Gauss-Newton step in (p for the damping constants, theta for the rest)
        p = dref * jnp.exp(theta[:3])
        Jx = J.at[:, :3].set(J[:, :3] / p)
        Jx = jnp.where(vary, Jx, 0.0)
        step = jnp.linalg.lstsq(Jx, -r)[0]
        snap = vary[:3] & (p + step[:3] <= 0.0) & (theta[:3] > lo + 1.0)
        theta = theta.at[:3].set(jnp.where(snap, lo + 1.0, theta[:3]))
        # Marquardt-like rescaling of the log coordinates
        cn = jnp.sqrt(jnp.sum(J * J, axis=0))
        ref = jnp.max(jnp.where(vary & ~is_log, cn, 0.0))
        safe = jnp.where(cn > 0.0, cn, 1.0)
        new = jnp.where(is_log & vary & (cn > 0.0), jnp.clip(ref / safe, 1.0, 1e15), 1.0)
        ratio = new / scale
        redo = jnp.any(snap) | jnp.any((ratio > 10.0) | (ratio < 0.1))
        return (theta, new, steps + n_steps, code, redo), None

    init = (theta0, jnp.ones_like(theta0), jnp.array(0), jnp.array(0), jnp.array(True))
    (theta, _, steps, code, _), _ = jax.lax.scan(one, init, None, length=rounds)
    return theta, code, steps, None


def _result_code(result):
    """0 converged, 1 step budget exhausted, 2 failed."""
    ok = result == optx.RESULTS.successful
    capped = result == optx.RESULTS.nonlinear_max_steps_reached
    return jnp.where(ok, 0, jnp.where(capped, 1, 2))


@functools.partial(jax.jit, static_argnames=("model", "optimizer", "max_steps", "rtol", "atol",
                                             "ref_opts"))
def _core(t, x, wt, p0, vary, consts, fs, *, model, optimizer, max_steps, rtol, atol,
          ref_opts):
    """One fit, pure: optimise, then covariance by the delta method. Arrays only."""
    st = _setup(p0, t, model, consts)
    args = (t, x, wt, st, vary, fs)
    L = p0.shape[0]
    theta0 = jnp.zeros(L, dtype=p0.dtype)
    fn = _materialised(functools.partial(_residual_fn, model=model, ref_opts=ref_opts), args)
    final = None
    if optimizer == "lm":
        # the reference model starts from the ansatz optimum: one round
        rounds = 1 if model == "reference" else _LM_ROUNDS
        theta, code, steps, final = _lm_rounds(fn, theta0, args, model, ref_opts, max_steps,
                                               rtol, atol, rounds)
    else:
        def loss_fn(th):
            return 0.5 * jnp.sum(fn(th, args) ** 2)

        theta, code, steps = _optax_minimise(loss_fn, theta0, optimizer, max_steps, rtol, atol)

    theta = _clamped(theta, st, vary)
    npad = t.shape[0]
    if model == "reference":
        # reuse the optimizer's last residuals and Jacobian (no further copy of the integrator
        # to compile); a constant at its lower bound has a zero column there and gets no
        # standard error
        if final is None:
            J, r = jax.jacfwd(lambda th: (fn(th, args),) * 2, has_aux=True)(theta)
        else:
            r, J = final
        r, J = r[:npad], J[:npad]
        z = ((1.0 + 0.5 * (r * st["sx"] / fs) ** 2) ** 2 - 1.0)  # invert the soft_l1 weighting
        r_plain = jnp.where(jnp.isfinite(fs), jnp.sign(r) * fs / st["sx"] * jnp.sqrt(z), r)
        curve = x + r_plain * st["sx"] / jnp.where(wt > 0.0, wt, 1.0)
    else:
        # statistics at the (clamped) optimum, without the clamp so that a constant at its
        # lower bound keeps its (tiny) derivative and the delta method stays regular
        def rows(th):
            r, curve = _residual_rows(th, args, model, ref_opts, clamp=False, with_curve=True)
            return r, (r, curve)

        J, (r, curve) = jax.jacfwd(rows, has_aux=True)(theta)
    n = jnp.sum(wt > 0.0)
    nvary = jnp.sum(vary)
    chi2_n = jnp.sum(r * r)
    s2 = chi2_n / jnp.maximum(n - nvary, 1)
    report = functools.partial(_reported, st=st, vary=vary, model=model, clamp=False)
    params = report(theta)
    G = jax.jacfwd(report)(theta)
    eye = jnp.eye(L, dtype=G.dtype)
    G = jnp.where(vary[:, None], G, eye)
    Jp = jnp.linalg.solve(G.T, J.T).T  # J G^-1
    H = Jp.T @ Jp
    # a constant at its bound with a zero Jacobian column (reference model) gets no stderr
    active = vary & (jnp.diag(H) > 0.0)
    pair = active[:, None] & active[None, :]
    H = jnp.where(pair, H, eye)
    d = jnp.sqrt(jnp.where(jnp.diag(H) > 0.0, jnp.diag(H), 1.0))
    C = jnp.linalg.inv(H / (d[:, None] * d[None, :])) / (d[:, None] * d[None, :])
    cov = jnp.where(pair, s2 * C, 0.0)
    var = jnp.diag(cov)
    stderr = jnp.where(active, jnp.sqrt(jnp.where(var >= 0.0, var, jnp.nan)), jnp.nan)
    finite = jnp.all(jnp.isfinite(params)) & jnp.isfinite(chi2_n)
    code = jnp.where(finite, code, 2)
    P = _physical(theta, st, vary, model)
    return dict(params=params, stderr=stderr, covariance=cov, code=code, steps=steps,
                chisqr=chi2_n * st["sx"] ** 2, ndata=n, nvarys=nvary, curve=curve,
                theta=theta, internal=jnp.stack(P))


class ArrayFit(NamedTuple):
    """Result of :func:`fit_arrays`: arrays only (vmappable); layout PARAMS.

    Attributes:
        params: fitted (mu, b, D, w0, offset, x0, v0); fixed entries hold their p0 value.
        stderr: standard errors (NaN for fixed entries).
        success: the optimizer converged and everything is finite.
        n_iterations: optimizer steps.
        chisqr: sum of squared (robust-weighted) residuals in data units.
        covariance: 7 x 7 covariance of params (zero rows/columns for fixed entries).
    """

    params: jax.Array
    stderr: jax.Array
    success: jax.Array
    n_iterations: jax.Array
    chisqr: jax.Array
    covariance: jax.Array


def _vary_mask(free, fit_omega0: bool, offset: bool, layout=PARAMS) -> np.ndarray:
    free = _check_free(free)
    vary = np.zeros(len(layout), dtype=bool)
    for name in free:
        vary[layout.index(name)] = True
    if layout is PARAMS:
        vary[3] = bool(fit_omega0)
        vary[4] = bool(offset)
        vary[5] = vary[6] = True
    else:
        vary[3] = True
        vary[4] = bool(offset)
    return vary


def _check_free(free) -> tuple[str, ...]:
    if isinstance(free, str):
        free = tuple(s.strip() for s in free.split(",") if s.strip())
    free = tuple(free)
    bad = [f for f in free if f not in DAMPING]
    if bad or len(set(free)) != len(free):
        raise ValueError(f"free must name distinct damping constants among {DAMPING}, "
                         f"got {free!r}")
    return free


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def fit_arrays(t, x, p0, *, free=("mu", "D"), fit_omega0: bool = False, offset: bool = True,
               m=1.0, g=9.81, model: str = "ansatz", loss: str = "linear", f_scale=None,
               optimizer: str = "lm", weights=None, max_steps: int | None = None,
               rtol: float = 1e-8, atol: float = 1e-10, max_swings: int | None = None,
               ref_rtol: float = 1e-8, ref_atol: float = 1e-10) -> ArrayFit:
    """Pure, jit/vmap-able core of :func:`fit`: one fit of x(t) from the start p0.

    No data checks, no automatic start or guesses: t[0] is the fit start (t0 of x0, v0).

    Arguments:
        t, x: 1-d arrays of equal length (the fit window); may be traced / batched by vmap.
        p0: initial (and, for the parameters that do not vary, fixed) values in the layout
            ``PARAMS`` = (mu, b, D, w0, offset, x0, v0). A free damping constant at 0 starts
            from a small positive value.
        free, fit_omega0, offset: which parameters vary (static); x0, v0 always vary.
        m, g: mass and gravitational acceleration (fixed).
        model: "ansatz" or "reference".
        loss: "linear" or "soft_l1"; ``f_scale`` (data units) defaults to 1.4826 MAD of the
            residuals at p0.
        optimizer: "lm" (optimistix Levenberg-Marquardt), "adam" or "lbfgs" (optax).
        weights: optional per-sample weights 1/sigma (0 drops a sample).
        max_steps, rtol, atol: optimizer budget and tolerances (internal coordinates).
        max_swings, ref_rtol, ref_atol: reference model only (static).

    Returns:
        An :class:`ArrayFit` (params, stderr, success, n_iterations, chisqr, covariance).
    """
    _check_choice("model", model, MODELS)
    _check_choice("loss", loss, LOSSES)
    _check_choice("optimizer", optimizer, OPTIMIZERS)
    vary = jnp.asarray(_vary_mask(free, fit_omega0, offset), dtype=bool)
    t = jnp.asarray(t, dtype=float)
    x = jnp.asarray(x, dtype=float)
    p0 = jnp.asarray(p0, dtype=float)
    wt = jnp.ones_like(x) if weights is None else jnp.asarray(weights, dtype=float)
    consts = jnp.asarray(jnp.stack([jnp.asarray(m, dtype=float), jnp.asarray(g, dtype=float)]),
                         dtype=float)
    if loss == "linear":
        fs = jnp.asarray(jnp.inf, dtype=float)
    elif f_scale is None:
        st = _setup(p0, t, model, consts)
        P = _physical(jnp.zeros(7), st, vary, model)
        r0 = _curve(t, P, st, model, _ref_opts(model, max_swings, ref_rtol, ref_atol, t, p0))
        r0 = r0 - x
        fs = jnp.asarray(_MAD * jnp.median(jnp.abs(r0 - jnp.median(r0))), dtype=float)
    else:
        fs = jnp.asarray(f_scale, dtype=float)
    out = _core(t, x, wt, p0, vary, consts, fs, model=model, optimizer=optimizer,
                max_steps=int(max_steps or _MAX_STEPS[optimizer]), rtol=float(rtol),
                atol=float(atol),
                ref_opts=_ref_opts(model, max_swings, ref_rtol, ref_atol, t, p0))
    return ArrayFit(out["params"], out["stderr"], out["code"] == 0, out["steps"],
                    out["chisqr"], out["covariance"])


def _ref_opts(model, max_swings, rtol, atol, t, p0):
    if model != "reference":
        return None
    if max_swings is None:
        try:
            span = float(np.max(np.asarray(t)) - np.asarray(t)[0])
            w0 = float(np.asarray(p0)[3])
            max_swings = int(1.15 * span * w0 / math.pi) + 8
        except (TypeError, jax.errors.ConcretizationTypeError,
                jax.errors.TracerArrayConversionError) as err:
            raise ValueError("fit_arrays(model='reference') under jit/vmap needs max_swings "
                             "(static): the number of half swings in the window plus a "
                             "margin") from err
    return (int(max_swings), float(rtol), float(atol))


def residual_function(t, x, *, free=("mu", "D"), oscillator=None, fit_omega0: bool = False,
                      offset: bool = True, model: str = "ansatz",
                      max_swings: int | None = None):
    """The residuals model(t; p) - x that :func:`fit` minimises, in physical parameters.

    For checks against other optimizers (e.g. ``scipy.optimize.least_squares``): the same
    model, window (t[0] is the start of x0, v0) and fixed constants as :func:`fit` with
    ``start="data"``.

    Arguments:
        t, x: the fit window.
        free, oscillator, fit_omega0, offset, model: as in :func:`fit`.
        max_swings: reference model budget (default from the window).

    Returns:
        (fun, jac, names): ``fun(p)`` and ``jac(p)`` take the varied parameters ``names`` (in
        the order of PARAMS, physical units) as a numpy vector and return numpy arrays
        (jitted; forward-mode Jacobian).
    """
    _check_choice("model", model, MODELS)
    vary = _vary_mask(free, fit_omega0, offset)
    osc = _osc_values(oscillator)
    names = [PARAMS[i] for i in range(7) if vary[i]]
    idx = jnp.asarray(np.flatnonzero(vary))
    base = jnp.asarray([osc["mu"], osc["b"], osc["D"], osc["w0"], 0.0, 0.0, 0.0])
    t = jnp.asarray(t, dtype=float)
    x = jnp.asarray(x, dtype=float)
    m, g = osc["m"], osc["g"]
    st = dict(t0=t[0], span=jnp.max(t) - t[0], consts=jnp.asarray([m, g]))
    if model == "reference" and max_swings is None:
        omega = _analyse(np.asarray(t), np.asarray(x)).omega if fit_omega0 else osc["w0"]
        max_swings = int(1.15 * float(st["span"]) * omega / math.pi) + 8
    ref_opts = _ref_opts(model, max_swings, 1e-10, 1e-12, t, base)

    def residuals(p):
        full = base.at[idx].set(p)
        mu, b, D, w0, off, x0, v0 = (full[i] for i in range(7))
        y = _ansatz_w(x0, v0, mu, b, D, w0, m, g) if model == "ansatz" else v0
        return _curve(t, (mu, b, D, w0, off, x0, y), st, model, ref_opts) - x

    fun = jax.jit(residuals)
    jac = jax.jit(jax.jacfwd(residuals))
    return (lambda p: np.asarray(fun(jnp.asarray(p, dtype=float))),
            lambda p: np.asarray(jac(jnp.asarray(p, dtype=float))), names)


# ----------------------------------------------------------------------------------------------
# initial guesses (numpy): frequency from zero crossings, damping from the envelope decrement


@dataclass
class _Analysis:
    offset: float
    omega: float  # angular frequency of the zero crossings
    noise: float  # sigma of the measurement noise
    ext_i: np.ndarray  # sample index of the extreme of every half cycle
    ext_t: np.ndarray
    ext_x: np.ndarray  # signed extreme, relative to the offset
    n_cross: int


def _noise_sigma(x: np.ndarray) -> float:
    if x.size < 5:
        return 0.0
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(_MAD * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _crossings(y: np.ndarray, h: float) -> np.ndarray:
    """Indices i where y changes sign between i and i+1, with hysteresis h (noise-proof)."""
    state = 0
    last_change = -1
    out = []
    sign = np.sign(y)
    for i in np.flatnonzero(np.abs(y) > h):
        s = 1 if y[i] > 0 else -1
        if state != 0 and s != state:
            # the last sign change before i
            j = i - 1
            while j > last_change and sign[j] == s:
                j -= 1
            out.append(max(j, 0))
        if s != state:
            last_change = i
        state = s
    return np.asarray(out, dtype=int)


def _frequency_fft(t: np.ndarray, y: np.ndarray) -> float:
    dt = float(np.median(np.diff(t)))
    n = 1 << int(math.ceil(math.log2(max(len(y), 8)))) + 2
    spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y)), n))
    spec[0] = 0.0
    k = int(np.argmax(spec))
    if 0 < k < len(spec) - 1:
        a, b, c = np.log(spec[k - 1: k + 2] + 1e-300)
        k = k + 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else k
    return 2.0 * math.pi * k / (n * dt)


def _despike(x: np.ndarray, width: int = 5) -> np.ndarray:
    """Running median over ``width`` samples: removes glitches of one or two samples."""
    if x.size < 3 * width:
        return x
    half = width // 2
    padded = np.concatenate([np.full(half, x[0]), x, np.full(half, x[-1])])
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, width), axis=1)


def _analyse(t: np.ndarray, x: np.ndarray) -> _Analysis:
    """Offset, frequency, noise and the extreme of every half cycle of a trace (glitches of
    one or two samples removed by a running median first)."""
    noise = _noise_sigma(x)
    x = _despike(x)
    off = float(np.median(x))
    for _ in range(2):
        y = x - off
        h = max(5.0 * noise, 1e-3 * float(np.max(np.abs(y))))
        cross = _crossings(y, h)
        ext_i = []
        for a, b in zip(cross[:-1], cross[1:], strict=True):
            seg = np.abs(y[a + 1: b + 1])
            ext_i.append(a + 1 + int(np.argmax(seg)))
        ext_i = np.asarray(ext_i, dtype=int)
        if ext_i.size >= 3:
            mids = 0.5 * (y[ext_i[:-1]] + y[ext_i[1:]])
            off += float(np.median(mids[: max(3, min(len(mids), 40))]))
    y = x - off
    if cross.size >= 4:
        tc = []
        for i in cross:  # linear interpolation of the zero between i and i+1
            y0, y1 = y[i], y[min(i + 1, len(y) - 1)]
            frac = y0 / (y0 - y1) if y1 != y0 else 0.0
            tc.append(t[i] + frac * (t[min(i + 1, len(t) - 1)] - t[i]))
        tc = np.asarray(tc)
        dtc = np.diff(tc)
        half = float(np.median(dtc))
        steps = np.maximum(np.round(dtc / half), 1.0)
        k = np.concatenate([[0.0], np.cumsum(steps)])
        slope = np.polyfit(k, tc, 1)[0]
        omega = math.pi / slope
    else:
        omega = _frequency_fft(t, y)
    return _Analysis(offset=off, omega=omega, noise=noise, ext_i=ext_i, ext_t=t[ext_i],
                     ext_x=y[ext_i], n_cross=int(cross.size))


def _nnls_small(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Non-negative least squares for a few columns, by trying every active set."""
    k = X.shape[1]
    best, best_res = np.zeros(k), float(np.sum(y * y))
    for mask in range(1, 1 << k):
        cols = [j for j in range(k) if mask >> j & 1]
        coef, *_ = np.linalg.lstsq(X[:, cols], y, rcond=None)
        if np.all(coef >= 0.0):
            full = np.zeros(k)
            full[cols] = coef
            res = float(np.sum((X @ full - y) ** 2))
            if res < best_res:
                best, best_res = full, res
    return best


def _guess_d(t_e, E, free, fixed_d, *, step: int = 2, noise: float = 0.0):
    """First estimates of the free (d0, d1, d2) from the decrement of the envelope E(t_e).

    dE/dt = -(d0 + d1 E + d2 E^2) between extremes ``step`` apart (2: one full cycle, which
    cancels an offset error), by non-negative least squares; small floors for zeros.
    """
    free_idx = [DAMPING.index(f) for f in free]
    d = np.asarray(fixed_d, dtype=float).copy()
    if len(E) <= step + 1:
        return d, False
    rate = (E[:-step] - E[step:]) / (t_e[step:] - t_e[:-step])
    Em = 0.5 * (E[:-step] + E[step:])
    ok = (Em > 5.0 * noise) & np.isfinite(rate)
    if np.sum(ok) < max(2, len(free_idx)):
        return d, False
    rate, Em = rate[ok], Em[ok]
    basis = np.stack([np.ones_like(Em), Em, Em * Em], axis=1)
    rhs = rate - basis @ np.where(np.isin(np.arange(3), free_idx), 0.0, d)
    cols = basis[:, free_idx]
    norms = np.linalg.norm(cols, axis=0)
    coef = _nnls_small(cols / norms, rhs) / norms
    mean_rate = max(float(np.mean(np.abs(rate))), 1e-300)
    floors = np.array([1e-2 * mean_rate, 1e-2 * mean_rate / np.mean(Em),
                       1e-2 * mean_rate / np.mean(Em * Em)])
    for j, c in zip(free_idx, coef, strict=True):
        d[j] = max(float(c), floors[j])
    return d, True


def _initial_state(t, y, omega, t_start):
    """x0, v0 at t_start by linear least squares of the first 1.5 periods:
    y = (a + a' s) cos(w s) + (c + c' s) sin(w s), s = t - t_start."""
    s = t - t_start
    sel = s <= 3.0 * math.pi / omega
    if np.sum(sel) < 8:
        sel = np.arange(len(s)) < min(len(s), 8)
    s, y = s[sel], y[sel]
    cw, sw = np.cos(omega * s), np.sin(omega * s)
    X = np.stack([cw, s * cw, sw, s * sw], axis=1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(coef[0]), float(omega * coef[2] + coef[1])


def _osc_values(oscillator) -> dict:
    if oscillator is None:
        oscillator = Oscillator(m=1.0, k=1.0)
    if isinstance(oscillator, dict):
        oscillator = Oscillator(**oscillator)
    if not isinstance(oscillator, Oscillator):
        raise TypeError(f"oscillator must be a dampax.Oscillator, got "
                        f"{type(oscillator).__name__}")
    vals = {}
    for name in ("m", "k", "mu", "b", "D", "g"):
        arr = np.asarray(getattr(oscillator, name), dtype=float)
        if arr.shape != ():
            raise ValueError(f"oscillator.{name}: fit needs a single oscillator, not a batch")
        vals[name] = float(arr)
    vals["w0"] = math.sqrt(vals["k"] / vals["m"])
    return vals


def _prepare(trace_or_t, x):
    """(t, x, source, trace) from a Trace or two arrays; sorted by t, non-finite dropped."""
    source, trace = "", None
    if isinstance(trace_or_t, Trace):
        if x is not None:
            raise ValueError("pass either a Trace or the arrays t and x, not both")
        trace = trace_or_t
        t, x, source = trace.t, trace.x, trace.source
    elif isinstance(trace_or_t, (str, Path)):
        trace = load_trace(trace_or_t)
        t, x, source = trace.t, trace.x, trace.source
    else:
        if x is None:
            raise ValueError("fit(t, x): x is missing (or pass a dampax.Trace)")
        t = trace_or_t
    t = np.asarray(t, dtype=float).reshape(-1)
    x = np.asarray(x, dtype=float).reshape(-1)
    if t.shape != x.shape:
        raise ValueError(f"t and x must have the same length, got {t.size} and {x.size}")
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    order = np.argsort(t, kind="stable")
    t, x = t[order], x[order]
    if t.size < 10:
        raise ValueError(f"a fit needs at least 10 finite samples, got {t.size}")
    return t, x, source


def _start_index(t, x, an: _Analysis, start) -> int:
    if start is None or start == "data":
        return 0
    if isinstance(start, (int, float)) and not isinstance(start, bool):
        i = int(np.searchsorted(t, float(start)))
        if i >= len(t) - 10:
            raise ValueError(f"start = {start} leaves fewer than 10 samples")
        return i
    if start != "auto":
        raise ValueError(f"start must be 'auto', 'data', None or a time, got {start!r}")
    y = np.abs(_despike(x) - an.offset)
    i_big = int(np.argmax(y))
    later = an.ext_i[an.ext_t > t[i_big] + 0.25 * math.pi / an.omega]
    return int(later[0]) if later.size else 0


def initial_guess(t, x, *, free=("mu", "D"), oscillator=None, fit_omega0: bool = False,
                  offset: bool = True):
    """Initial parameters for :func:`fit_arrays`, from a trace that starts at t[0].

    Offset from the midpoints of successive extremes, w0 from the zero crossings (FFT when
    there are few), (d0, d1, d2) from the envelope decrement per cycle by non-negative least
    squares, x0 and v0 from a least-squares sinusoid over the first 1.5 periods.

    Returns:
        p0 in the layout ``PARAMS`` (numpy array).
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    osc = _osc_values(oscillator)
    p0, _, _ = _guess(t, x, _check_free(free), osc, fit_omega0, offset)
    return p0


def _guess(t, x, free, osc, fit_omega0, offset, an=None):
    an = an or _analyse(t, x)
    off = an.offset if offset else 0.0
    w0 = an.omega if fit_omega0 else osc["w0"]
    m, g = osc["m"], osc["g"]
    fixed_d = _damping_d(osc["mu"], osc["b"], osc["D"], w0, m, g)
    E = np.abs(an.ext_x) if offset else np.abs(x[an.ext_i])
    d, ok = _guess_d(an.ext_t, E, free, fixed_d, noise=an.noise)
    x0, v0 = _initial_state(t, x - off, an.omega, t[0])
    if not ok:  # too few extremes: a mild decay over the window
        A = math.hypot(x0, v0 / w0)
        span = max(t[-1] - t[0], 1e-12)
        share = 0.5 * A / span / max(len(free), 1)
        for f in free:
            j = DAMPING.index(f)
            d = list(d)
            d[j] = share / [1.0, A, A * A][j]
    mu, b, D = _d_to_physical(d[0], d[1], d[2], w0, m, g)
    vals = {"mu": mu, "b": b, "D": D}
    for name in DAMPING:
        if name not in free:
            vals[name] = osc[name]
    p0 = np.array([vals["mu"], vals["b"], vals["D"], w0, off, x0, v0])
    return p0, an, ok


# ----------------------------------------------------------------------------------------------
# the result


def _bucket(n: int, minimum: int = 4096) -> int:
    """Padded length: the next power of 4 >= n, at least ``minimum``, so that traces of
    different lengths share compiled fits (compiling one takes 10-30 s; evaluating the padded
    samples costs far less)."""
    return max(minimum, 1 << (2 * int(math.ceil(math.log2(max(n, 1)) / 2))))


def _pad(t, x, n_pad):
    n = len(t)
    wt = np.zeros(n_pad)
    wt[:n] = 1.0
    tp = np.full(n_pad, t[-1])
    tp[:n] = t
    xp = np.full(n_pad, x[-1])
    xp[:n] = x
    return tp, xp, wt


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
        derived: d0, d1, d2, xc, k, A (ansatz amplitude), phi, halt_time.
        free, model, loss, optimizer, kind ("trace" or "envelope"), t_start, source.
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

    @property
    def rms(self) -> float:
        """Root mean square of the residuals (data units)."""
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={self.params[k]:.4g}" for k in self.free)
        return (f"FitResult({self.kind}, model={self.model!r}, free={self.free}, {vals}, "
                f"rms={self.rms:.3g}, bic={self.bic:.1f}, success={self.success})")

    def report(self, *, min_correl: float = 0.1) -> str:
        """A text report like lmfit's fit_report: statistics, values, correlations."""
        method = _METHOD_NAMES.get(self.optimizer, self.optimizer)
        lines = ["[[Model]]",
                 f"    {self.kind} fit, model = {self.model!r}, free damping = "
                 f"{', '.join(self.free) or 'none'}, loss = {self.loss}"
                 + (f" (f_scale = {self.f_scale:.4g})" if math.isfinite(self.f_scale) else ""),
                 ]
        if self.source:
            lines.append(f"    data: {self.source}")
        lines += [
            "[[Fit Statistics]]",
            f"    # fitting method   = {method}",
            f"    # iterations       = {self.n_iterations}",
            f"    # data points      = {self.ndata}",
            f"    # variables        = {self.nvarys}",
            f"    chi-square         = {self.chisqr:.6g}",
            f"    reduced chi-square = {self.redchi:.6g}",
            f"    Akaike info crit   = {self.aic:.6g}",
            f"    Bayesian info crit = {self.bic:.6g}",
            f"    rms residual       = {self.rms:.6g}",
            f"    success            = {self.success} ({self.message})",
        ]
        if self.kind == "trace":
            lines.append(f"    fit start t0       = {self.t_start:.6g}")
        lines.append("[[Variables]]")
        width = max(len(k) for k in self.params) + 1
        for name, value in self.params.items():
            unit = _UNITS.get(name, "")
            if name in self.varied:
                err = self.stderr[name]
                rel = abs(err / value) * 100 if value != 0 and math.isfinite(err) else math.nan
                rel_text = f" ({rel:.2f}%)" if math.isfinite(rel) else ""
                init = self.init.get(name)
                init_text = f" (init = {init:.6g})" if init is not None else ""
                lines.append(f"    {name + ':':<{width}} {value:.6g} +/- {err:.4g}{rel_text}"
                             f"{init_text} {unit}".rstrip())
            else:
                lines.append(f"    {name + ':':<{width}} {value:.6g} (fixed) {unit}".rstrip())
        if self.derived:
            lines.append("[[Derived]]")
            for name, value in self.derived.items():
                lines.append(f"    {name + ':':<{width}} {value:.6g}")
        pairs = []
        n = len(self.varied)
        for i in range(n):
            for j in range(i + 1, n):
                c = float(self.correlation[i, j])
                if math.isfinite(c) and abs(c) >= min_correl:
                    pairs.append((abs(c), f"    C({self.varied[i]}, {self.varied[j]})", c))
        lines.append(f"[[Correlations]] (unreported correlations are < {min_correl:.3f})")
        if pairs:
            w = max(len(p[1]) for p in pairs)
            for _, label, c in sorted(pairs, reverse=True):
                lines.append(f"{label:<{w}} = {c:+.4f}")
        for note in self.warnings:
            lines.append(f"[[Warning]] {note}")
        return "\n".join(lines)

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
            "success": bool(self.success), "message": self.message,
            "n_iterations": int(self.n_iterations), "warnings": list(self.warnings),
        }

    def plot(self, path, *, title: str | None = None):
        """Save a figure: data, fit and envelope A f(t) (+- xc band when mu is fitted) above,
        residuals below. Uses a bare matplotlib Figure with the Agg canvas (no pyplot state).

        Returns:
            The path written.
        """
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(10, 6.5), layout="constrained")
        FigureCanvasAgg(fig)
        ax, axr = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
        off = self.params.get("offset", 0.0)
        if self.full_t is not None and len(self.full_t) > len(self.t):
            before = self.full_t < self.t[0]
            if np.any(before):
                ax.plot(self.full_t[before], self.full_x[before], color="0.7", lw=0.6,
                        label="data before the fit start")
        marker = dict(ls="none", marker=".", ms=4) if self.kind == "envelope" or \
            len(self.t) < 400 else dict(lw=0.6)
        ax.plot(self.t, self.x, color="tab:blue", label="data", **marker)
        ax.plot(self.t, self.model_x, color="tab:red", lw=0.9, label=f"fit ({self.model})")
        if self.envelope is not None and self.kind == "trace":
            ax.plot(self.t, off + self.envelope, color="k", lw=0.8, ls="--",
                    label="envelope A f(t)")
            ax.plot(self.t, off - self.envelope, color="k", lw=0.8, ls="--")
        xc = self.derived.get("xc", 0.0)
        if self.kind == "trace" and "mu" in self.free and xc > 0:
            ax.axhspan(off - xc, off + xc, color="tab:orange", alpha=0.25,
                       label="sticking band offset +- xc")
        ax.set_ylabel("amplitude" if self.kind == "envelope" else "position")
        terms = ", ".join(f"{k} = {self.params[k]:.4g}" for k in self.free)
        what = self.source or ("maxima" if self.kind == "envelope" else "trace")
        ax.set_title(title or f"{what}: {terms}  (rms {self.rms:.3g})",
                     fontsize=9)
        ax.legend(fontsize=8, loc="upper right")
        axr.plot(self.t, self.residuals, color="tab:blue", lw=0.5,
                 **({"marker": ".", "ls": "none"} if self.kind == "envelope" else {}))
        axr.axhline(0.0, color="k", lw=0.6)
        axr.set_ylabel("data - fit")
        axr.set_xlabel("t [s]")
        fig.savefig(str(path), dpi=110)
        return Path(path)


def _finish(out, *, layout, vary, t, x, n, free, model, loss, optimizer, kind, t_start,
            source, init, osc, consts, fs, full_t=None, full_x=None, warn=(), stages=""):
    params_v = np.asarray(out["params"], dtype=float)
    stderr_v = np.asarray(out["stderr"], dtype=float)
    cov_full = np.asarray(out["covariance"], dtype=float)
    idx = [i for i in range(len(layout)) if vary[i]]
    varied = [layout[i] for i in idx]
    cov = cov_full[np.ix_(idx, idx)]
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    params = {name: float(params_v[i]) for i, name in enumerate(layout)}
    stderr = {name: float(stderr_v[i]) if vary[i] else math.nan
              for i, name in enumerate(layout)}
    curve = np.asarray(out["curve"], dtype=float)[:n]
    resid = x - curve
    ndata = int(out["ndata"])
    nvarys = int(out["nvarys"])
    chisqr = float(out["chisqr"])
    redchi = chisqr / max(ndata - nvarys, 1)
    neg2ll = ndata * math.log(max(chisqr, 1e-300) / ndata)
    aic = neg2ll + 2 * nvarys
    bic = neg2ll + math.log(ndata) * nvarys
    code = int(out["code"])
    message = {0: "converged", 1: "maximum number of steps reached",
               2: "the optimizer failed (non-finite values or divergence)"}[code]
    if stages:
        message = f"{message}; {stages}"
    m, g = consts[0], consts[1]
    if kind == "trace":
        w0 = params["w0"]
        d0, d1, d2 = _damping_d(params["mu"], params["b"], params["D"], w0, m, g)
        theta_int = np.asarray(out["internal"], dtype=float)
        derived = {"d0": d0, "d1": d1, "d2": d2, "xc": params["mu"] * g / w0 ** 2,
                   "k": m * w0 ** 2}
        A = phi = math.nan
        if model == "ansatz":
            A = math.hypot(theta_int[5], theta_int[6])
            phi = math.atan2(theta_int[6], theta_int[5])
        else:
            try:
                from ._solve import solve

                sol = solve(Oscillator(m=m, k=m * w0 ** 2, mu=params["mu"], b=params["b"],
                                       D=params["D"], g=g), params["x0"], params["v0"])
                A, phi = float(sol.amplitude), float(sol.phase)
            except ValueError:
                pass
        envelope = None
        if math.isfinite(A) and A > 0:
            envelope = A * np.asarray(decay(t - t_start, d2 * A, d1, d0 / A))
            derived["halt_time"] = t_start + float(halt_time(d2 * A, d1, d0 / A))
        derived["A"], derived["phi"] = A, phi
        fixed = {"m": m, "g": g}
        if not vary[3]:
            fixed["k"] = m * params["w0"] ** 2
    else:
        w0 = consts[2]
        d0, d1, d2 = _damping_d(params["mu"], params["b"], params["D"], w0, m, g)
        derived = {"d0": d0, "d1": d1, "d2": d2, "w0": w0}
        envelope = None
        fixed = {"m": m, "g": g, "w0": w0}
    return FitResult(
        params=params, stderr=stderr, varied=varied, covariance=cov, correlation=corr,
        residuals=resid, t=t, x=x, model_x=curve, success=code == 0, message=message,
        n_iterations=int(out["steps"]), chisqr=chisqr, redchi=redchi, aic=aic, bic=bic,
        ndata=ndata, nvarys=nvarys, free=tuple(free), model=model, loss=loss,
        optimizer=optimizer, kind=kind, t_start=float(t_start), source=source, fixed=fixed,
        derived=derived, init={k: float(v) for k, v in init.items()}, envelope=envelope,
        full_t=full_t, full_x=full_x, f_scale=float(fs), warnings=list(warn))


# ----------------------------------------------------------------------------------------------
# fit


def fit(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), model: str = "ansatz",
        fit_omega0: bool = False, offset: bool = True, start="auto", end=None,
        loss: str = "linear", optimizer: str = "lm", p0=None, max_steps: int | None = None,
        rtol: float = 1e-8, atol: float = 1e-10, max_swings: int | None = None) -> FitResult:
    """Fit the damping constants of eq. 3 to a measured (or simulated) free-decay trace.

    Arguments:
        trace_or_t: a :class:`Trace` (from :func:`load_trace`), a file path, or the times t.
        x: the positions when ``trace_or_t`` holds the times.
        oscillator: the known constants (m, k, g; the damping constants not in ``free`` stay
            at its values, usually 0). Default ``Oscillator(m=1.0, k=1.0)``.
        free: the damping constants to fit, among "mu", "b", "D".
        model: "ansatz" (closed form, fast) or "reference" (diffrax integration of eq. 3,
            started from the ansatz fit).
        fit_omega0: also fit w0 (m fixed, k = m w0^2); otherwise w0 = sqrt(k/m).
        offset: fit the equilibrium offset (else the trace is taken as centred on 0).
        start: where the fit window begins: "auto" (the first clear extreme after the largest
            excursion, which skips a hand release), "data" / None (the first sample) or a time.
        end: optional end time of the window.
        loss: "linear" or "soft_l1" (robust to outliers; scale from the MAD of a linear fit).
        optimizer: "lm" (optimistix Levenberg-Marquardt), "adam" or "lbfgs" (optax).
        p0: optional initial values (dict by parameter name) overriding the automatic guess.
        max_steps, rtol, atol: optimizer budget and tolerances.
        max_swings: reference model budget (default from the window length).

    Returns:
        A :class:`FitResult`.
    """
    _check_choice("model", model, MODELS)
    _check_choice("loss", loss, LOSSES)
    _check_choice("optimizer", optimizer, OPTIMIZERS)
    free = _check_free(free)
    osc = _osc_values(oscillator)
    t_all, x_all, source = _prepare(trace_or_t, x)
    warn = []
    an = _analyse(t_all, x_all)
    if an.n_cross < 3:
        warn.append(f"only {an.n_cross} zero crossings found: is this a free-decay "
                    "oscillation? initial guesses are rough")
    if not fit_omega0 and abs(an.omega / osc["w0"] - 1.0) > 0.03:
        warn.append(f"the data oscillate at {an.omega:.5g} rad/s but sqrt(k/m) = "
                    f"{osc['w0']:.5g} rad/s: pass fit_omega0=True or the right m and k")
    i0 = _start_index(t_all, x_all, an, start)
    i1 = len(t_all) if end is None else int(np.searchsorted(t_all, float(end), side="right"))
    t, xw = t_all[i0:i1], x_all[i0:i1]
    if t.size < 10:
        raise ValueError(f"the fit window [{t_all[i0]:g}, {end}] holds fewer than 10 samples")
    an_w = _analyse(t, xw)
    an_w.omega = an.omega if an.n_cross >= an_w.n_cross else an_w.omega
    guess, _, _ = _guess(t, xw, free, osc, fit_omega0, offset, an=an_w)
    if p0:
        unknown = set(p0) - set(PARAMS)
        if unknown:
            raise ValueError(f"p0: unknown parameters {sorted(unknown)}; use {PARAMS}")
        for k, v in p0.items():
            guess[PARAMS.index(k)] = float(v)
    for w in warn:
        warnings.warn(w, stacklevel=2)
    vary = _vary_mask(free, fit_omega0, offset)
    consts = np.array([osc["m"], osc["g"]])
    n = len(t)
    tp, xp, wt = _pad(t, xw, _bucket(n))
    steps = int(max_steps or _MAX_STEPS[optimizer])

    def run(p_start, mdl, fs, opt=optimizer):
        ref_opts = _ref_opts(mdl, max_swings, 1e-8, 1e-10, t, p_start)
        return _core(jnp.asarray(tp), jnp.asarray(xp), jnp.asarray(wt), jnp.asarray(p_start),
                     jnp.asarray(vary), jnp.asarray(consts), jnp.asarray(fs, dtype=float),
                     model=mdl, optimizer=opt, max_steps=steps, rtol=float(rtol),
                     atol=float(atol), ref_opts=ref_opts)

    stages = []
    fs = math.inf
    out = run(guess, "ansatz", fs)
    if loss == "soft_l1":
        r = xw - np.asarray(out["curve"])[:n]
        fs = float(_MAD * np.median(np.abs(r - np.median(r))))
        fs = fs if fs > 0 else float(np.std(r)) or 1.0
        stages.append(f"soft_l1 started from the linear-loss fit, f_scale = {fs:.4g}")
        out = run(np.asarray(out["params"]), "ansatz", fs)
    if model == "reference":
        stages.append(f"started from the ansatz fit ({int(out['steps'])} steps)")
        out = run(np.asarray(out["params"]), "reference", fs)
    init = {PARAMS[i]: guess[i] for i in range(7) if vary[i]}
    return _finish(out, layout=PARAMS, vary=vary, t=t, x=xw, n=n, free=free, model=model,
                   loss=loss, optimizer=optimizer, kind="trace", t_start=float(t[0]),
                   source=source, init=init, osc=osc, consts=(osc["m"], osc["g"]), fs=fs,
                   full_t=t_all, full_x=x_all, warn=warn, stages="; ".join(stages))


# ----------------------------------------------------------------------------------------------
# envelope fits


def fit_envelope(t_peaks, amplitudes=None, *, free=("mu", "D"), omega0=None, oscillator=None,
                 offset: bool = False, loss: str = "linear", optimizer: str = "lm",
                 max_steps: int | None = None, rtol: float = 1e-10,
                 atol: float = 1e-12) -> FitResult:
    """Fit the closed-form amplitude E(t) = A f(t - t_1) of the ansatz to successive maxima.

    f solves f' = -(a f^2 + b' f + c), f(0) = 1 with a = d2 A, b' = d1, c = d0 / A (eq. 20),
    so E' = -(d0 + d1 E + d2 E^2): the envelope decay of eq. 3 with Coulomb, viscous and
    quadratic damping.

    Arguments:
        t_peaks, amplitudes: times and values of the maxima (absolute values are used); or
            a :class:`Trace` (or a path) holding them, with ``amplitudes`` left out.
        free: damping constants to fit ("mu", "b", "D").
        omega0: angular frequency [rad/s] used to convert (d0, d2) to (mu, D); default
            2 pi / the median spacing of t_peaks (maxima of one sign, one per period).
        oscillator: m and g (default m = 1 kg, g = 9.81); non-free damping constants stay at
            its values.
        offset: also fit a constant added to the envelope (a zero offset of the angle).
        loss, optimizer, max_steps, rtol, atol: as in :func:`fit`.

    Returns:
        A :class:`FitResult` with params mu, b, D, A (amplitude at t_1), offset.
    """
    _check_choice("loss", loss, LOSSES)
    _check_choice("optimizer", optimizer, OPTIMIZERS)
    free = _check_free(free)
    osc = _osc_values(oscillator)
    t, E, source = _prepare(t_peaks, amplitudes)
    E = np.abs(E)
    if omega0 is None:
        omega0 = 2.0 * math.pi / float(np.median(np.diff(t)))
    omega0 = float(omega0)
    if not (math.isfinite(omega0) and omega0 > 0):
        raise ValueError(f"omega0 must be > 0, got {omega0}")
    m, g = osc["m"], osc["g"]
    fixed_d = _damping_d(osc["mu"], osc["b"], osc["D"], omega0, m, g)
    noise = float(_MAD * np.median(np.abs(np.diff(E, 2)))) / math.sqrt(6) if len(E) > 4 else 0
    d, _ = _guess_d(t, E, free, fixed_d, step=1, noise=0.2 * noise)
    mu, b, D = _d_to_physical(d[0], d[1], d[2], omega0, m, g)
    vals = {"mu": mu, "b": b, "D": D}
    for name in DAMPING:
        if name not in free:
            vals[name] = osc[name]
    guess = np.array([vals["mu"], vals["b"], vals["D"], E[0], 0.0])
    vary = _vary_mask(free, True, offset, layout=ENVELOPE_PARAMS)
    consts = np.array([m, g, omega0])
    n = len(t)
    tp, xp, wt = _pad(t, E, _bucket(n, 256))
    steps = int(max_steps or _MAX_STEPS[optimizer])

    def run(p_start, fs):
        return _core(jnp.asarray(tp), jnp.asarray(xp), jnp.asarray(wt), jnp.asarray(p_start),
                     jnp.asarray(vary), jnp.asarray(consts), jnp.asarray(fs, dtype=float),
                     model="envelope", optimizer=optimizer, max_steps=steps, rtol=float(rtol),
                     atol=float(atol), ref_opts=None)

    fs = math.inf
    out = run(guess, fs)
    stages = ""
    if loss == "soft_l1":
        r = E - np.asarray(out["curve"])[:n]
        fs = float(_MAD * np.median(np.abs(r - np.median(r)))) or 1.0
        stages = f"soft_l1 started from the linear-loss fit, f_scale = {fs:.4g}"
        out = run(np.asarray(out["params"]), fs)
    init = {ENVELOPE_PARAMS[i]: guess[i] for i in range(5) if vary[i]}
    return _finish(out, layout=ENVELOPE_PARAMS, vary=vary, t=t, x=E, n=n, free=free,
                   model="envelope", loss=loss, optimizer=optimizer, kind="envelope",
                   t_start=float(t[0]), source=source, init=init, osc=osc,
                   consts=(m, g, omega0), fs=fs, stages=stages)


# ----------------------------------------------------------------------------------------------
# model comparison


@dataclass
class ModelComparison:
    """Candidate damping models fitted to the same data, ranked by an information criterion.

    Attributes:
        results: candidate (tuple of free terms) -> FitResult, best first.
        criterion: "bic" or "aic" (the ranking).
        table: one dict per candidate, best first: free, aic, bic, delta (criterion minus the
            best), chisqr, rms, nvarys, success.
    """

    results: dict
    criterion: str
    table: list

    @property
    def best(self) -> FitResult:
        """The fit of the best-ranked candidate."""
        return next(iter(self.results.values()))

    @property
    def ranking(self) -> list:
        """Candidates (tuples of free terms), best first."""
        return list(self.results)

    @property
    def supported(self) -> tuple:
        """Damping terms of the best-ranked model."""
        return tuple(self.best.free)

    def evidence(self) -> dict:
        """Per damping term: the criterion change when it is removed from / added to the best
        model (positive = the data support the best model's choice), where such a candidate
        was fitted."""
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
                         f"{'yes' if row['success'] else 'no':>3}")
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
                "supported": list(self.supported)}


def _rank(results: dict, criterion: str) -> ModelComparison:
    _check_choice("criterion", criterion, ("aic", "bic"))

    def key(item):
        r = item[1]
        return (not r.success, getattr(r, criterion))

    ordered = dict(sorted(results.items(), key=key))
    best = getattr(next(iter(ordered.values())), criterion)
    table = [dict(free=tuple(k), aic=r.aic, bic=r.bic,
                  delta=getattr(r, criterion) - best, chisqr=r.chisqr, rms=r.rms,
                  nvarys=r.nvarys, success=r.success) for k, r in ordered.items()]
    return ModelComparison(results=ordered, criterion=criterion, table=table)


def compare_models(trace=None, x=None, *, candidates=CANDIDATES, criterion: str = "bic",
                   envelope=None, **fit_kwargs) -> ModelComparison:
    """Fit every candidate set of damping terms and rank them by BIC (or AIC).

    Arguments:
        trace: a Trace, a path or the times (then ``x``); or None with ``envelope``.
        candidates: tuples of free damping terms.
        criterion: "bic" (default) or "aic".
        envelope: (t_peaks, amplitudes) to compare envelope models instead
            (:func:`compare_envelope_models`).
        **fit_kwargs: passed to :func:`fit` (or :func:`fit_envelope`).

    Returns:
        A :class:`ModelComparison` (``.best``, ``.table``, ``.report()``).
    """
    if envelope is not None:
        if trace is not None:
            raise ValueError("pass either a trace or envelope=(t_peaks, amplitudes)")
        return compare_envelope_models(*envelope, candidates=candidates, criterion=criterion,
                                       **fit_kwargs)
    if trace is None:
        raise ValueError("compare_models needs a trace (or envelope=(t_peaks, amplitudes))")
    if "free" in fit_kwargs:
        raise ValueError("compare_models sets free itself; pass candidates=")
    results = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for cand in candidates:
            results[tuple(_check_free(cand))] = fit(trace, x, free=cand, **fit_kwargs)
    return _rank(results, criterion)


def compare_envelope_models(t_peaks, amplitudes=None, *, candidates=CANDIDATES,
                            criterion: str = "bic", **kwargs) -> ModelComparison:
    """:func:`compare_models` for a table of maxima (:func:`fit_envelope` per candidate)."""
    if "free" in kwargs:
        raise ValueError("compare_envelope_models sets free itself; pass candidates=")
    results = {tuple(_check_free(c)): fit_envelope(t_peaks, amplitudes, free=c, **kwargs)
               for c in candidates}
    return _rank(results, criterion)


# ----------------------------------------------------------------------------------------------
# synthetic example

#: the documented truth of ``dampax fit --example`` (:func:`example_trace`)
EXAMPLE = dict(m=0.2, k=15.0, mu=0.002, b=0.0, D=0.02, x0=0.05, v0=0.0, noise=2e-4,
               rate=200.0, t_end=25.0, seed=5)


def example_trace(**overrides) -> tuple[Trace, dict]:
    """A synthetic free decay with known constants, for ``dampax fit --example``.

    Generated by the reference integrator (``solve(method="reference")``) from (x0, v0) at
    t = 0, sampled at ``rate`` up to ``t_end`` with Gaussian noise of ``noise`` [m] (fixed
    seed), offset 0: the truth is ``EXAMPLE`` (m = 0.2 kg, k = 15 N/m, mu = 0.002,
    D = 0.02 kg/m, x0 = 5 cm, v0 = 0, noise 0.2 mm, 200 samples/s for 25 s; the block would
    halt at 29.4 s, so the trace ends while it still moves).

    Returns:
        (trace, truth).
    """
    from ._solve import solve

    truth = {**EXAMPLE, **overrides}
    osc = Oscillator(m=truth["m"], k=truth["k"], mu=truth["mu"], b=truth["b"], D=truth["D"])
    t = np.arange(0.0, truth["t_end"], 1.0 / truth["rate"])
    w0 = math.sqrt(truth["k"] / truth["m"])
    swings = int(1.2 * truth["t_end"] * w0 / math.pi) + 8
    sol = solve(osc, truth["x0"], truth["v0"], method="reference", t_end=float(t[-1]) + 0.01,
                max_swings=swings)
    x = np.asarray(sol.x(jnp.asarray(t)))
    rng = np.random.default_rng(truth["seed"])
    x = x + truth["noise"] * rng.standard_normal(t.size)
    return Trace(t=t, x=x, source="dampax example (reference integrator)",
                 time_column="t", position_column="x", n_rows=t.size), truth


# ----------------------------------------------------------------------------------------------
# command line: dampax fit


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dampax fit``."""
    parser.add_argument("path", nargs="?", help="text file with the trace (time and position "
                        "columns), or with a table of maxima for --envelope")
    parser.add_argument("--example", action="store_true",
                        help="fit a synthetic trace with known constants (m = 0.2 kg, "
                             "k = 15 N/m, mu = 0.002, D = 0.02 kg/m, noise 0.2 mm)")
    read = parser.add_argument_group("reading the file")
    read.add_argument("--time", metavar="COL", help="time column, name or index (default: 0)")
    read.add_argument("--position", metavar="COL",
                      help="position column, name or index (default: 1)")
    read.add_argument("--rate", metavar="HZ|auto",
                      help="rebuild time from the sample index: a rate [1/s], or 'auto' for "
                           "buffered time stamps")
    read.add_argument("--delimiter", help="column separator (default: detected)")
    read.add_argument("--scale", type=float, default=1.0,
                      help="factor applied to the positions (default: %(default)s)")
    osc = parser.add_argument_group("oscillator (fixed constants)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=1.0,
                     help="stiffness [N/m] (default: %(default)s; use --fit-omega0 when "
                          "unknown)")
    osc.add_argument("--g", type=float, default=9.81, help="(default: %(default)s)")
    model = parser.add_argument_group("model and fit")
    model.add_argument("--free", default="mu,D",
                       help="damping constants to fit, comma list of mu, b, D "
                            "(default: %(default)s)")
    model.add_argument("--model", default="ansatz", choices=MODELS,
                       help="(default: %(default)s)")
    model.add_argument("--fit-omega0", action="store_true",
                       help="also fit w0 (k = m w0^2); needed when k/m is not known exactly")
    model.add_argument("--no-offset", action="store_true",
                       help="do not fit the equilibrium offset (envelope fits have none)")
    model.add_argument("--loss", default="linear", choices=LOSSES,
                       help="soft_l1 for traces with outliers (default: %(default)s)")
    model.add_argument("--optimizer", default="lm", choices=OPTIMIZERS,
                       help="(default: %(default)s)")
    model.add_argument("--start", default="auto",
                       help="fit start: auto (first extreme after the largest excursion), "
                            "data (first sample) or a time [s] (default: %(default)s)")
    model.add_argument("--end", type=float, default=None, help="fit end time [s]")
    model.add_argument("--envelope", action="store_true",
                       help="the file holds successive maxima (t, amplitude): envelope fit")
    model.add_argument("--omega0", type=float, default=None,
                       help="--envelope: angular frequency (default: from the peak spacing)")
    model.add_argument("--no-compare", action="store_true",
                       help="skip the ranking of candidate damping models")
    out = parser.add_argument_group("output")
    out.add_argument("--out", metavar="DIR", default="fit",
                     help="folder for fit.json and fit.png (default: %(default)s)")


def _parse_rate(text):
    if text is None or text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--rate must be a number or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--rate must be > 0, got {text!r}")
    return value


def _parse_start(text):
    if text in ("auto", "data"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--start must be auto, data or a time, got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    """Fit damping constants to a measured trace; print the report and the model ranking."""
    import time as _time

    prog = "dampax"
    free = _check_free(args.free)
    if not free:
        raise ValueError("--free: name at least one of mu, b, D")
    if args.example == bool(args.path):
        raise ValueError("give a PATH or --example (one of them)")
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out: {str(out_dir)!r} exists and is not a folder")
    start = _parse_start(args.start)
    truth = None
    if args.example:
        print(f"{prog} fit --example: generating the synthetic trace with the reference "
              "integrator ...")
        trace, truth = example_trace()
        osc = Oscillator(m=truth["m"], k=truth["k"])
    else:
        trace = load_trace(args.path, time=args.time, position=args.position,
                           rate=_parse_rate(args.rate), delimiter=args.delimiter,
                           scale=args.scale)
        osc = Oscillator(m=args.m, k=args.k, g=args.g)
    print(f"{prog} fit: {trace!r}")
    if trace.n_dropped:
        print(f"{prog}: note: {trace.n_dropped} unreadable rows were dropped", file=sys.stderr)
    began = _time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if args.envelope:
            kw = dict(omega0=args.omega0, oscillator=osc, offset=False, loss=args.loss,
                      optimizer=args.optimizer)
            result = fit_envelope(trace, free=free, **kw)
            comparison = None if args.no_compare else compare_envelope_models(trace, **kw)
        else:
            kw = dict(oscillator=osc, fit_omega0=args.fit_omega0, offset=not args.no_offset,
                      start=start, end=args.end, loss=args.loss, optimizer=args.optimizer)
            result = fit(trace, free=free, model=args.model, **kw)
            comparison = None if args.no_compare else compare_models(trace, model="ansatz",
                                                                     **kw)
    for w in {str(w.message) for w in caught}:
        print(f"{prog}: warning: {w}", file=sys.stderr)
    elapsed = _time.perf_counter() - began
    print()
    print(result.report())
    if truth is not None:
        print()
        print("  truth vs estimate (synthetic example):")
        for name in ("mu", "D"):
            est, err = result.params[name], result.stderr[name]
            print(f"    {name:<3} true {truth[name]:.6g}   fitted {est:.6g} +/- {err:.2g}   "
                  f"({(est - truth[name]) / err:+.2f} stderr)")
        print(f"    noise true {truth['noise']:.3g}   rms residual {result.rms:.3g}")
    if comparison is not None:
        print()
        if args.model != "ansatz" and not args.envelope:
            print("(ranking with the ansatz model)")
        print(comparison.report())
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {"fit": result.to_dict(), "ranking": comparison.to_dict() if comparison else None,
               "truth": truth, "trace": {"source": trace.source, "n": len(trace),
                                         "n_dropped": trace.n_dropped, "rate": trace.rate}}
    (out_dir / "fit.json").write_text(json.dumps(summary, indent=2))
    result.plot(out_dir / "fit.png")
    print()
    print(f"  {elapsed:.1f} s (compilation included); written: {out_dir / 'fit.json'}, "
          f"{out_dir / 'fit.png'}")
    return 0
