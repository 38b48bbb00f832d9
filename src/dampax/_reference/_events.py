"""The end of a swing: where the velocity vanishes, and whether the block sticks there.

A step whose end has s v <= 0 crossed the swing's velocity zero. The step's interpolating
polynomial (`_sampling.hermite_row`: degree 9, x and four derivatives matched at both ends,
as accurate as the step) holds the motion inside it, so the zero is found on that polynomial
by Newton's method, from the root of the linear interpolant of v: no step is re-taken, and
under `jax.vmap` no lane waits for another's root finding. The iterates are held fixed
(`stop_gradient`) but for one last Newton update th* - p'(th*)/p''(th*), which has the exact
first derivative (implicit function theorem on the polynomial, whose coefficients carry the
derivatives of the step's ends); the turning point x(t*) carries the total derivative.

At the turning point the block sticks for good when the spring cannot overcome static
friction, |k x + k3 x^3| <= mu_s m g (`Oscillator.sticks`; mu_s = mu unless given);
otherwise the next swing starts with v = 0 and s = -sgn(x), sliding with mu.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Newton iterations on the polynomial before the last, differentiable update: the linear
# guess is within a few percent of the step, and Newton converges quadratically
NEWTON_ITERATIONS = 5


def _derivatives(c, th):
    """p(th), p'(th), p''(th) of the polynomial sum_k c[k] th^k (c: a list of 10)."""
    p, d1, d2 = c[9], 9.0 * c[9], 72.0 * c[9]
    for k in range(8, -1, -1):
        p = c[k] + th * p
        if k > 0:
            d1 = k * c[k] + th * d1
        if k > 1:
            d2 = k * (k - 1) * c[k] + th * d2
    return p, d1, d2


def _newton(c, th, mask):
    _, d1, d2 = _derivatives(c, th)
    ok = mask & (d2 != 0.0)
    return jnp.where(ok, -d1 / jnp.where(ok, d2, 1.0), 0.0)


def turning_point(row, t_a, h, v_a, v_b, mask):
    """The velocity zero inside a step and the position there, from the step's polynomial.

    Arguments:
        row: the step's (t_a, 1/h, c_0..c_9) (`_sampling.hermite_row`), stacked on the last
            axis.
        t_a, h: the step's start and length.
        v_a, v_b: the velocity at its ends (opposite signs, or v_b = 0, where ``mask``).
        mask: where the step crossed the zero (elsewhere the outputs are harmless numbers).

    Returns:
        (t*, x(t*)).
    """
    return turning_point_of([row[..., 2 + k] for k in range(10)], t_a, h, v_a, v_b, mask)


def turning_point_of(c, t_a, h, v_a, v_b, mask):
    """:func:`turning_point` of a step given by its ten coefficients c_0..c_9 (a list)."""
    denom = jnp.where(mask & (v_a != v_b), v_a - v_b, 1.0)
    th = jax.lax.stop_gradient(jnp.clip(jnp.where(mask, v_a / denom, 0.0), 0.0, 1.0))
    c_fixed = [jax.lax.stop_gradient(ck) for ck in c]
    for _ in range(NEWTON_ITERATIONS):
        th = jnp.clip(th + _newton(c_fixed, th, mask), 0.0, 1.0)
    dth = _newton(c, th, mask)
    p, d1, _ = _derivatives(c, th)
    return t_a + (th + dth) * h, p + d1 * dth
