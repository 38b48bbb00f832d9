"""The fits' Levenberg-Marquardt (``_fit._lm``) against optimistix's, whose algorithm it
writes out, and against scipy's least_squares optimum."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

from dampax._fit._lm import (
    GIVE_UP_AFTER,
    GIVE_UP_EARLY,
    GIVE_UP_EARLY_FACTOR,
    LEAVE_AFTER,
    levenberg_marquardt,
)

T = np.linspace(0.0, 4.0, 60)
DATA = 2.0 * np.exp(-0.7 * T) * np.cos(3.0 * T + 0.4) + 0.01 * np.random.default_rng(
    0).standard_normal(T.size)


def _residuals(p):
    return p[0] * jnp.exp(-p[1] * T) * jnp.cos(p[2] * T + p[3]) - DATA


def _rosenbrock(p):
    return jnp.stack([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])


def _with_rounding(p):
    """The residuals of an integrating model: their cost moves by ~1e-12 of itself as the
    parameters move (step sizes change), a noise no derivative sees."""
    return _residuals(p) + 1e-12 * jax.lax.stop_gradient(
        jnp.sin(1e9 * jnp.sum(p) + jnp.arange(T.size)))


def _sd(fn, y):
    """The standard errors of a least-squares optimum y of fn (s2 (J^T J)^-1)."""
    J, r = np.asarray(jax.jacfwd(fn)(y)), np.asarray(fn(y))
    return np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * np.sum(r * r) / (r.size - y.size))


@pytest.mark.parametrize("fn, y0", [(_residuals, [1.5, 0.5, 2.9, 0.0]),
                                    (_rosenbrock, [-1.2, 1.0])])
def test_same_path_as_optimistix_and_scipys_optimum(fn, y0):
    """Same iterates as optimistix's LevenbergMarquardt (normal equations, Cholesky): after
    as many steps, the same point to rounding; ours stops no later (where the Gauss-Newton
    decrement is below 1e-10 noise variances; a zero-residual problem, Rosenbrock's, has no
    noise and stops where optimistix does); the optimum is scipy's."""
    y0 = jnp.asarray(y0, dtype=float)
    ours = jax.jit(lambda y: levenberg_marquardt(fn, y, rtol=1e-10, atol=1e-12,
                                                 max_steps=200))(y0)
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    ref = optx.least_squares(lambda y, _: fn(y), solver, y0, max_steps=200, throw=False)
    assert bool(ours.converged) and ref.result == optx.RESULTS.successful
    steps = int(ours.steps)
    assert steps <= int(ref.stats["num_steps"])
    assert (steps == int(ref.stats["num_steps"])) == (fn is _rosenbrock)
    same = optx.least_squares(lambda y, _: fn(y), solver, y0, max_steps=steps, throw=False)
    np.testing.assert_allclose(ours.value, same.value, rtol=1e-9, atol=1e-12)
    sp = least_squares(lambda y: np.asarray(fn(jnp.asarray(y))), np.asarray(y0),
                       xtol=1e-14, ftol=1e-14, gtol=1e-14)
    np.testing.assert_allclose(ours.value, sp.x, rtol=1e-7, atol=1e-10)
    # the residuals and Jacobian returned are those of the returned point
    np.testing.assert_allclose(ours.residual, fn(ours.value), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ours.jac, jax.jacfwd(fn)(ours.value), rtol=1e-10, atol=1e-12)


def test_stops_where_the_cost_is_rounding():
    """A cost with rounding in it (an integrating model's): optimistix's trust-region test
    rejects step after step there (24 steps, 13 without the rounding), ours stops once the
    Gauss-Newton decrement is below 1e-10 noise variances, at scipy's optimum of the clean
    problem to 1e-5 standard errors."""
    y0 = jnp.asarray([1.5, 0.5, 2.9, 0.0])
    ours = jax.jit(lambda y: levenberg_marquardt(_with_rounding, y, rtol=1e-10, atol=1e-12,
                                                 max_steps=200))(y0)
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    ref = optx.least_squares(lambda y, _: _with_rounding(y), solver, y0, max_steps=200,
                             throw=False)
    assert bool(ours.converged)
    assert int(ours.steps) + 10 <= int(ref.stats["num_steps"])
    sp = least_squares(lambda y: np.asarray(_residuals(jnp.asarray(y))), np.asarray(y0),
                       xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert np.max(np.abs(np.asarray(ours.value) - sp.x) / _sd(_residuals, sp.x)) < 1e-5


T_LONG = np.linspace(0.0, 40.0, 6000)
DATA_LONG = 2.0 * np.exp(-0.07 * T_LONG) * np.cos(3.0 * T_LONG + 0.4) + \
    0.01 * np.random.default_rng(1).standard_normal(T_LONG.size)


def _long(p):
    return p[0] * jnp.exp(-p[1] * T_LONG) * jnp.cos(p[2] * T_LONG + p[3]) - DATA_LONG


def _long_with_rounding(p):
    """6,000 rows whose cost moves by 2e-12 of itself as the parameters move (an integrating
    model's, whose step sizes change): 6e-9 noise variances, far above 1e-10."""
    return _long(p) * (1.0 + 1e-12 * jax.lax.stop_gradient(jnp.sin(1e9 * jnp.sum(p))))


def test_stops_where_the_cost_is_rounding_of_itself():
    """Where the cost's own rounding exceeds 1e-10 noise variances (many rows), the stop
    holds once the Gauss-Newton decrement is below 1e-12 of the cost: as many steps as the
    clean problem takes (or one more), not a run of rejected steps (30 against 5 with the
    first rule alone); the optimum is scipy's of the clean problem to 1e-4 standard errors."""
    y0 = jnp.asarray([1.8, 0.06, 3.0, 0.3])

    def run(fn):
        return jax.jit(lambda y: levenberg_marquardt(fn, y, rtol=1e-10, atol=1e-12,
                                                     max_steps=200))(y0)

    clean, noisy = run(_long), run(_long_with_rounding)
    assert bool(clean.converged) and bool(noisy.converged)
    assert int(noisy.steps) <= int(clean.steps) + 1
    sp = least_squares(lambda y: np.asarray(_long(jnp.asarray(y))), np.asarray(y0),
                       xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert np.max(np.abs(np.asarray(noisy.value) - sp.x) / _sd(_long, sp.x)) < 1e-4


def test_budget_under_vmap_and_a_start_that_is_not_finite():
    """A traced budget stops the loop (not converged, finite); under vmap each lane keeps
    its own; a NaN start is reported as not finite."""
    starts = jnp.asarray([[1.5, 0.5, 2.9, 0.0], [1.5, 0.5, 2.9, jnp.nan]])
    budgets = jnp.asarray([3, 200])
    out = jax.vmap(lambda y, b: levenberg_marquardt(_residuals, y, rtol=1e-10, atol=1e-12,
                                                    max_steps=200, budget=b))(starts, budgets)
    assert list(np.asarray(out.steps)) == [3, 1]  # the NaN start: accepted once, not finite
    assert not bool(out.converged[0]) and bool(out.finite[0])
    assert not bool(out.converged[1]) and not bool(out.finite[1])


def test_give_up_stops_a_fit_far_above_and_leaves_the_others_unchanged():
    """``give_up``: Rosenbrock from (-1.2, 1) takes more than GIVE_UP_AFTER steps; with a
    bound below its cost at that step it stops there (finite, not converged), and at
    GIVE_UP_EARLY where its cost there is above GIVE_UP_EARLY_FACTOR times the bound; with a
    bound above (or inf) it follows the same iterates to the same optimum (scipy's) as
    without."""
    y0 = jnp.asarray([-1.2, 1.0])

    def run(give_up):
        return jax.jit(lambda y, g: levenberg_marquardt(
            _rosenbrock, y, rtol=1e-10, atol=1e-12, max_steps=200, give_up=g))(y0, give_up)

    plain = jax.jit(lambda y: levenberg_marquardt(_rosenbrock, y, rtol=1e-10, atol=1e-12,
                                                  max_steps=200))(y0)
    assert int(plain.steps) > GIVE_UP_AFTER and bool(plain.converged)
    at = {k: jax.jit(lambda y, k=k: levenberg_marquardt(
        _rosenbrock, y, rtol=1e-10, atol=1e-12, max_steps=200, budget=k))(y0)
        for k in (GIVE_UP_EARLY, GIVE_UP_AFTER)}
    cost = {k: float(jnp.sum(a.residual ** 2)) for k, a in at.items()}
    # still far from the optimum (cost 0) after 16 steps, farther after 8
    assert cost[GIVE_UP_AFTER] > 1e-6
    assert cost[GIVE_UP_EARLY] / GIVE_UP_EARLY_FACTOR < cost[GIVE_UP_AFTER]
    for k, bound in ((GIVE_UP_EARLY, 0.5 * cost[GIVE_UP_EARLY] / GIVE_UP_EARLY_FACTOR),
                     (GIVE_UP_AFTER, math.sqrt(cost[GIVE_UP_EARLY] / GIVE_UP_EARLY_FACTOR *
                                               cost[GIVE_UP_AFTER]))):
        stopped = run(bound)
        assert int(stopped.steps) == k
        assert not bool(stopped.converged) and bool(stopped.finite)
        np.testing.assert_array_equal(stopped.value, at[k].value)
    for bound in (2.0 * cost[GIVE_UP_AFTER], jnp.inf):
        went_on = run(bound)
        assert int(went_on.steps) == int(plain.steps) and bool(went_on.converged)
        np.testing.assert_array_equal(went_on.value, plain.value)
    np.testing.assert_allclose(plain.value, [1.0, 1.0], rtol=1e-8)


def _towards_zero(y):
    """A decay whose rate the data want below 0 (they grow slowly): the rate p = exp(y[1])
    (log coordinates, as the fits' damping constants) creeps towards 0 by damped steps."""
    return y[0] * jnp.exp(-jnp.exp(y[1]) * T) - (1.0 + 0.02 * T)


def test_leave_stops_where_the_newton_step_crosses_the_bound():
    """``leave``: where the undamped Gauss-Newton step from LEAVE_AFTER accepted points in a
    row would send p = exp(y[1]) below 0 (y[1] falls by 1 or more, linearised), the loop
    stops, not converged, after LEAVE_AFTER steps; without it the creep runs its whole
    budget (400 steps, p = exp(-17.7) and still falling)."""
    y0 = jnp.asarray([1.0, jnp.log(0.3)])

    def leave(y, newton):
        return newton[1] >= 1.0

    creep = jax.jit(lambda y: levenberg_marquardt(_towards_zero, y, rtol=1e-10, atol=1e-12,
                                                  max_steps=400))(y0)
    left = jax.jit(lambda y: levenberg_marquardt(_towards_zero, y, rtol=1e-10, atol=1e-12,
                                                 max_steps=400, leave=leave))(y0)
    assert not bool(left.converged) and bool(left.finite)
    assert int(left.steps) == LEAVE_AFTER and int(creep.steps) == 400
    # where it stopped, the Gauss-Newton step (A^-1 g, from the returned J and r) crosses
    J, r = np.asarray(left.jac), np.asarray(left.residual)
    assert np.linalg.solve(J.T @ J, J.T @ r)[1] >= 1.0


@pytest.mark.parametrize("p", [1, 3, 7])
def test_spd_solve_matches_numpy(p):
    """The jnp Cholesky solve of the damped and Gauss-Newton steps against numpy's LAPACK, on
    a Gram matrix with column scales 1e-4 .. 1e3; a matrix that is not positive definite
    gives NaN (as LAPACK's factor)."""
    from dampax._fit._lm import spd_solve

    rng = np.random.default_rng(p)
    J = rng.standard_normal((50, p)) * np.geomspace(1e-4, 1e3, p)
    A, g = J.T @ J, rng.standard_normal(p)
    x = np.asarray(jax.jit(spd_solve)(A, g))
    np.testing.assert_allclose(x, np.linalg.solve(A, g), rtol=1e-9,
                               atol=1e-12 * np.abs(np.linalg.solve(A, g)).max())
    assert np.all(np.isnan(np.asarray(spd_solve(-np.eye(p), np.ones(p)))))


def test_the_steps_make_no_lapack_call_under_a_wide_vmap():
    """The damped and Gauss-Newton steps of 8,192 fits vmapped in one program make no LAPACK
    call. As LAPACK's Cholesky (``potrf``), a batch that large is split by jaxlib across XLA's
    intra-op threads and waited for on them: two such calls side by side hung
    ``dp.fit_arrays`` vmapped over 4,096 traces on a 2-core machine, in one thread (seen in
    gdb: both threads in ``CholeskyFactorization`` -> ``ParallelBatchMap``)."""
    from dampax._fit._lm import _damped_step, gauss_newton

    def both(A, g):
        return _damped_step(A, g, 1.0), gauss_newton(A, g)

    A, g = np.zeros((8192, 7, 7)), np.zeros((8192, 7))
    assert "lapack" not in jax.jit(jax.vmap(both)).lower(A, g).as_text()


def test_the_small_factorizations_do_not_grow_with_the_parameters():
    """The Cholesky solve and the Householder R run in loops of p turns, not unrolled: their
    programs hold as many operations for 7 parameters as for 2 (every fit's program holds
    them; a kept program loads in time proportional to its size, issue 36)."""
    from dampax._fit._linalg import householder_r
    from dampax._fit._lm import spd_solve

    def ops(fn, *shapes):
        return jax.jit(fn).lower(*(np.ones(s) for s in shapes)).as_text().count(" = ")

    assert ops(spd_solve, (7, 7), (7,)) == ops(spd_solve, (2, 2), (2,))
    assert ops(householder_r, (300, 7)) == ops(householder_r, (300, 2))
