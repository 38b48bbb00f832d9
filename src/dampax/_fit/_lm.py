"""Levenberg-Marquardt in one small loop: optimistix's algorithm, written out for the fits.

The fits ran ``optimistix.least_squares`` with ``LevenbergMarquardt(linear_solver=
lx.Normal(lx.Cholesky()))``. Its generality (pytrees, linear operators, a closure-converted
function, an implicit adjoint, a verbose hook) costs tracing and compiling: a cold default fit
compiled the optimiser around each model three times (the ansatz's batch of starts, its single
fit, the exact model's fit), 4-6 s each on 2 cores (issue 36: a first fit in a fresh process
took 15 s against a goal of 8 s). This module runs the same iteration on flat arrays with an
explicit Jacobian (the fit models materialise it anyway), so a program holds the model, its
Jacobian and a 7 x 7 Cholesky solve, nothing more.

The iteration (optimistix 0.1: ``AbstractGaussNewton.step`` with ``ClassicalTrustRegion`` and
``DampedNewtonDescent``):

- evaluate r, J at the candidate y_eval; the predicted reduction of the last step is
  0.5 (|J d + r|^2 - |r|^2) with (r, J) at the accepted y, d = y_eval - y; the actual one
  0.5 |r_eval|^2 - 0.5 |r|^2;
- accept when actual <= 0.01 predicted (always on the first step); a good step (actual <
  0.99 predicted < 0) multiplies the step size by 3.5, a rejected one by 0.25;
- on acceptance: stop when max |d| / (atol + rtol |y_eval|) < 1 and max |r_eval - r| /
  (atol + rtol |r_eval|) < 1 (Cauchy termination, max norm);
- also stop (unlike optimistix) where the accepted point is resolved: the undamped
  Gauss-Newton step would lower the cost by less than 1e-10 noise variances
  (:func:`resolved`; the trust-region test is rounding there);
- the next candidate: y - (J^T J + lambda I)^-1 J^T r with lambda = 1 / step size (the
  normal equations of [J; sqrt(lambda) I] d = [r; 0], Cholesky);
- ``give_up`` (traced, optional): after :data:`GIVE_UP_AFTER` steps, a fit whose accepted
  |r|^2 is still above it stops, not converged (the halt search's fits far above the
  optimum: ``_halts``), after :data:`GIVE_UP_EARLY` steps one above
  :data:`GIVE_UP_EARLY_FACTOR` times it. A fit that goes on follows the same path as without
  it;
- ``leave`` (optional): stop, not converged, where the undamped Gauss-Newton step from the
  last :data:`LEAVE_AFTER` accepted points sends a coordinate past its bound (``_core``'s
  rounds: a damping constant that goes to 0 in log coordinates).

The returned point is the last accepted one, with its residuals and Jacobian (the fit's
statistics reuse them). ``budget`` (traced) stops earlier than the loop's static
``max_steps``: one compiled fit serves every budget.

:func:`optax_minimise` runs the optax optimizers (adam, L-BFGS) on the fit's sum of squares.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

#: optimistix's ClassicalTrustRegion constants
LOW_CUTOFF, HIGH_CUTOFF, LOW_CONSTANT, HIGH_CONSTANT = 0.01, 0.99, 0.25, 3.5
#: the step after which a fit with ``give_up`` stops where its cost is above it
GIVE_UP_AFTER = 16
#: ... and an earlier step where it stops above GIVE_UP_EARLY_FACTOR times that bound: the halt
#: search's held fits that end near the optimum lay at most 3.5e3 bands up after 8 steps, 385
#: after 16 (benchmarks/README.md, issue 36, ninth session: 1,341 held fits), so 10x the
#: 16-step bound (1e5 bands and more) keeps its margin (28x against 26x); the example's far
#: held fits stop 8 steps sooner
GIVE_UP_EARLY, GIVE_UP_EARLY_FACTOR = 8, 10.0
#: accepted points in a row at which ``leave`` holds before the loop stops: a creep lasts
#: 20-100 steps; at 3 the first steps of the global starts' far starts placed constants at
#: their bound that the data wanted (2 of 200 draws of fit_calibration.py then failed)
LEAVE_AFTER = 10


class LMSolution(NamedTuple):
    """The outcome of :func:`levenberg_marquardt`.

    Attributes:
        value: the last accepted point.
        converged: the termination criterion held (else the budget ran out, or no finite
            point was reached: see ``finite``).
        finite: the returned point is finite.
        steps: the steps made (function evaluations).
        residual, jac: the residuals and the Jacobian at ``value``.
    """

    value: jax.Array
    converged: jax.Array
    finite: jax.Array
    steps: jax.Array
    residual: jax.Array
    jac: jax.Array


def rows_and_jacobian(fn, y):
    """(fn(y), its Jacobian), by one forward-mode pass."""
    J, r = jax.jacfwd(lambda th: (fn(th),) * 2, has_aux=True)(y)
    return r, J


def _damped_step(A, g, step_size):
    """(J^T J + lambda I)^-1 J^T r with lambda = 1 / step_size (optimistix's damped Newton
    step: lambda the largest float where the step size is below eps), from A = J^T J and
    g = J^T r."""
    eps = jnp.finfo(g.dtype).eps
    pred = step_size > eps
    lam = jnp.where(pred, 1.0 / jnp.where(pred, step_size, 1.0), jnp.finfo(g.dtype).max)
    return spd_solve(A + lam * jnp.eye(A.shape[0], dtype=A.dtype), g)


#: the accepted point is the optimum when the undamped Gauss-Newton step would lower the cost
#: by less than this share of one noise variance (:func:`resolved`)
GN_DECREMENT = 1e-10
#: ... or by less than this share of the cost itself: the most an integrating model's cost
#: can be resolved (it moves by ~1e-13 of itself as the integrator's steps change with the
#: parameters; the trust region's test of a smaller reduction is a coin flip)
COST_RESOLUTION = 1e-12


def gauss_newton(A, g):
    """(J^T J)^-1 J^T r from A = J^T J and g = J^T r (a ridge of 1e3 eps of A's largest
    diagonal entry keeps it defined): minus the undamped Gauss-Newton step."""
    ridge = 1e3 * jnp.finfo(A.dtype).eps * jnp.max(jnp.abs(jnp.diag(A)))
    return spd_solve(A + ridge * jnp.eye(A.shape[0], dtype=A.dtype), g)


def spd_solve(A, g):
    """A^-1 g for a small symmetric positive definite A (p x p), by the Cholesky factor
    A = L L^T and two triangular substitutions written in jnp (p steps each, no LAPACK).

    LAPACK's ``potrf`` under a wide ``jax.vmap`` (dp.fit_arrays over 4,096 traces) is split
    by jaxlib across XLA's intra-op threads and waited for on one of them: the damped and the
    Gauss-Newton steps, two such calls side by side in one program, held both threads of a
    2-core machine and hung for ever (``_linalg``'s note). A non-positive pivot gives NaN,
    as LAPACK's factor does.
    """
    p = A.shape[-1]
    idx = jnp.arange(p)

    # each in a loop of p turns, not unrolled: the same arithmetic in a far smaller program
    # (every fit's program holds two of these solves; a kept program loads in time
    # proportional to its size)
    def column(j, LS):  # column j of L, and the trailing matrix less its outer product
        L, S = LS
        d = S[j, j]
        c = jnp.where(idx >= j, S[:, j] / jnp.sqrt(jnp.where(d > 0.0, d, jnp.nan)), 0.0)
        return L.at[:, j].set(c), S - c[:, None] * c[None, :]

    L, _ = jax.lax.fori_loop(0, p, column, (jnp.zeros_like(A), A))

    def forward(i, yr):  # L y = g
        y, r = yr
        yi = r[i] / L[i, i]
        return y.at[i].set(yi), r - L[:, i] * yi

    def backward(k, xr):  # L^T x = y
        x, r = xr
        i = p - 1 - k
        xi = r[i] / L[i, i]
        return x.at[i].set(xi), r - L[i, :] * xi

    y, _ = jax.lax.fori_loop(0, p, forward, (jnp.zeros_like(g), g))
    x, _ = jax.lax.fori_loop(0, p, backward, (jnp.zeros_like(g), y))
    return x


def resolved(r, g, newton):
    """Whether no step can lower the cost 0.5 |r|^2 by more than it can be resolved: the
    undamped Gauss-Newton decrement 0.5 g^T (J^T J)^-1 g (g = J^T r: the most the local
    quadratic model can gain) is below :data:`GN_DECREMENT` times the noise variance per
    row, 0.5 |r|^2 / (rows - parameters) (rows: the nonzero residuals, so padding and
    satisfied pins are not counted), or below :data:`COST_RESOLUTION` times the cost. There
    the parameters lie within sqrt(2 x 1e-10) = 1.4e-5 standard errors of the model's
    optimum (sqrt(1e-12 rows) of them by the second rule: 7e-5 at 5,000 rows), and the
    trust-region test no longer decides anything: the actual reduction is rounding (an
    integrating model's cost moves by ~1e-13 of itself as its step sizes change), so
    optimistix's rule rejected step after step and shrank the step size 4x each time until
    it met the step tolerance: 10-20 wasted Jacobians of the exact model per fit (issue 36:
    28 steps of which 22 rejected at the optimum, on the example trace; with the first rule
    alone a held fit of the example's profile still made 19 rejected steps from a point at
    2.1e-10 noise variances). NaN (a singular J^T J) resolves nothing.

    Arguments:
        r: the residuals at the point; g = J^T r there and ``newton`` = (J^T J)^-1 g
            (:func:`gauss_newton`).
    """
    p = g.shape[0]
    decrement = 0.5 * g @ newton
    rows, cost = jnp.sum(r != 0.0), 0.5 * jnp.sum(r * r)
    s2 = cost / jnp.maximum(rows - p, 1)
    return (rows > p) & (decrement <= jnp.maximum(GN_DECREMENT * s2, COST_RESOLUTION * cost))


class _State(NamedTuple):
    k: Any
    y: Any
    r: Any
    J: Any
    y_eval: Any
    step_size: Any
    first: Any
    done: Any
    stopped: Any  # done without converging (give_up, leave)
    leaving: Any  # accepted points in a row where leave held


def levenberg_marquardt(fn, y0, *, rtol: float, atol: float, max_steps: int,
                        budget=None, give_up=None, leave=None) -> LMSolution:
    """Minimise 0.5 |fn(y)|^2 from ``y0`` (the module docstring's iteration).

    Arguments:
        fn: residuals of a flat parameter vector (jax-traceable, forward-differentiable).
        y0: the start.
        rtol, atol: the termination tolerances.
        max_steps: the loop's static bound.
        budget: a traced bound (at most ``max_steps``), or None.
        give_up: a traced bound on |fn(y)|^2 after :data:`GIVE_UP_AFTER` steps (above it the
            loop stops, not converged), or None.
        leave: optional ``leave(y, newton) -> bool``, with ``y - newton`` the undamped
            Gauss-Newton step from the accepted point: where it holds at :data:`LEAVE_AFTER`
            accepted points in a row the loop stops, not converged (a coordinate that the
            model sends past its bound, which damped steps only approach: ``_core``'s
            rounds move it there and start again).

    Returns:
        :class:`LMSolution`.
    """
    r0 = jax.eval_shape(fn, y0)
    limit = max_steps if budget is None else jnp.minimum(budget, max_steps)
    zero_r = jnp.zeros(r0.shape, r0.dtype)
    init = _State(jnp.array(0), y0, zero_r, jnp.zeros(r0.shape + y0.shape, y0.dtype), y0,
                  jnp.array(1.0, dtype=y0.dtype), jnp.array(True), jnp.array(False),
                  jnp.array(False), jnp.array(0))
    give_up = jnp.inf if give_up is None else give_up

    def cond(s: _State):
        return (s.k < limit) & ~s.done

    def body(s: _State):
        r_eval, J_eval = rows_and_jacobian(fn, s.y_eval)
        d = s.y_eval - s.y
        predicted = 0.5 * (jnp.sum((s.J @ d + s.r) ** 2) - jnp.sum(s.r ** 2))
        actual = 0.5 * jnp.sum(r_eval ** 2) - 0.5 * jnp.sum(s.r ** 2)
        accept = (actual <= LOW_CUTOFF * predicted) | s.first
        good = (actual < HIGH_CUTOFF * predicted) & (predicted < 0) & ~s.first
        mul = jnp.where(accept, jnp.where(good, HIGH_CONSTANT, 1.0), LOW_CONSTANT)
        y_scale = atol + rtol * jnp.abs(s.y_eval)
        f_scale = atol + rtol * jnp.abs(r_eval)
        small = (jnp.max(jnp.abs(d) / y_scale) < 1) & \
            (jnp.max(jnp.abs(r_eval - s.r) / f_scale) < 1)
        y = jnp.where(accept, s.y_eval, s.y)
        r = jnp.where(accept, r_eval, s.r)
        J = jnp.where(accept, J_eval, s.J)
        step_size = mul * s.step_size
        A, g = J.T @ J, J.T @ r  # the normal equations of the step and of the stop
        y_eval = y - _damped_step(A, g, step_size)
        newton = gauss_newton(A, g)
        rr = jnp.sum(r * r)
        gave_up = ((s.k + 1 == GIVE_UP_AFTER) & (rr > give_up)) | \
            ((s.k + 1 == GIVE_UP_EARLY) & (rr > GIVE_UP_EARLY_FACTOR * give_up))
        leaving = s.leaving
        if leave is not None:
            leaving = jnp.where(accept, jnp.where(leave(y, newton), leaving + 1, 0), leaving)
        left = leaving >= LEAVE_AFTER
        done = accept & small | resolved(r, g, newton) | ~jnp.all(jnp.isfinite(y)) | \
            gave_up | left
        return _State(s.k + 1, y, r, J, y_eval, step_size, jnp.array(False), done,
                      gave_up | left, leaving)

    s = jax.lax.while_loop(cond, body, init)
    finite = jnp.all(jnp.isfinite(s.y))
    return LMSolution(s.y, s.done & finite & ~s.stopped, finite, s.k, s.r, s.J)


def optax_minimise(loss_fn, theta0, optimizer, max_steps, rtol, atol):
    """Minimise loss_fn with optax adam (decaying rate) or L-BFGS; (theta, steps, ok): ok
    L-BFGS converged, adam's loss finite (its finished schedule counts as converged)."""
    import optax  # (imported here: a tenth of a second that the default optimizer never uses)

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
        flat_loss = jnp.abs(prev - value) <= rtol * jnp.abs(value) + 1e-300
        return k + 1, theta, state, value, small & flat_loss & jnp.isfinite(value)

    init = (jnp.array(0), theta0, opt.init(theta0), jnp.array(jnp.inf, dtype=theta0.dtype),
            jnp.array(False))
    k, theta, _, _, done = jax.lax.while_loop(cond, body, init)
    return theta, k, done if lbfgs else jnp.isfinite(loss_fn(theta))
