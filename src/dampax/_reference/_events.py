"""The end of a swing: where the velocity vanishes, and whether the block sticks there.

A step whose end has s v <= 0 crossed the swing's velocity zero. A cubic Hermite interpolant
of (v, v') at the step's ends gives the first guess; Newton's method on re-taken Runge--Kutta
steps from the step's start refines it (`_engine` runs each re-taken step as one iteration
of its loop, so that under `jax.vmap` no lane waits for another's root finding). The guess
and every Newton iterate but the last are held fixed (`stop_gradient`): the swing's end
t* - v(t*)/a(t*) of the last one then has the exact first derivative (implicit function
theorem), and the turning point x(t*) carries the total derivative.

At the turning point the block sticks for good when the spring cannot overcome static
friction, |k x + k3 x^3| <= mu m g (`Oscillator.sticks`); otherwise the next swing starts
with v = 0 and s = -sgn(x).
"""

from __future__ import annotations

import jax.numpy as jnp

from ._stepping import acceleration

# Newton iterations (re-taken steps) per turning point: the last one carries the derivative.
NEWTON_ITERATIONS = 2


def hermite_root(t_a, x_a, v_a, t_b, x_b, v_b, args, mask):
    """Zero of v on [t_a, t_b] of the cubic Hermite interpolant of (v, v') at both ends.

    A starting guess for Newton's method; v(t_a) and v(t_b) have opposite signs (or
    v(t_b) = 0) where ``mask`` holds.
    """
    h = t_b - t_a
    d_a = acceleration(x_a, v_a, args) * h
    d_b = acceleration(x_b, v_b, args) * h
    c2 = -3.0 * v_a - 2.0 * d_a + 3.0 * v_b - d_b
    c3 = 2.0 * v_a + d_a - 2.0 * v_b + d_b
    denom = jnp.where(mask & (v_a != v_b), v_a - v_b, 1.0)
    th = jnp.clip(jnp.where(mask, v_a / denom, 0.0), 0.0, 1.0)
    for _ in range(4):
        p = v_a + th * (d_a + th * (c2 + th * c3))
        dp = d_a + th * (2.0 * c2 + th * 3.0 * c3)
        ok = mask & (dp != 0.0)
        th = jnp.clip(th - jnp.where(ok, p / jnp.where(ok, dp, 1.0), 0.0), 0.0, 1.0)
    return t_a + th * h


def newton_update(x1, v1, args):
    """The Newton step -v/a for the velocity zero, from the state of a re-taken step."""
    a = acceleration(x1, v1, args)
    ok = a != 0.0
    return jnp.where(ok, -v1 / jnp.where(ok, a, 1.0), 0.0)
