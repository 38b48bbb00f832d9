"""One Runge--Kutta step of eq. 3 inside a swing, its error and the step-size control.

Inside a swing sgn(v) = s is constant, so

    x' = v,   v' = -((k + k3 x^2)/m) x - s mu g - (b/m + (D/m) s v) v

is smooth, and DOP853 (Hairer's 8th-order Dormand--Prince pair, `_tableau`) integrates it to
full accuracy. The 2-dimensional system is written out stage by stage with `jax.lax`
arithmetic (no loop over stages, no pytree machinery): one step is about 400 floating-point
operations, and it vectorizes across a `jax.vmap` batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _tableau as tab

# Step-size control (as scipy's DOP853): safety factor, limits of the change per step, and the
# exponent -1/(error estimator order + 1).
SAFETY = 0.9
MIN_FACTOR = 0.2
MAX_FACTOR = 10.0
EXPONENT = -1.0 / 8.0


def ode_args(osc, s):
    """Arguments of `vector_field`: (s, k/m, mu g, b/m, D/m, k3/m)."""
    return (jnp.asarray(s, dtype=float), osc.k / osc.m, osc.mu * osc.g, osc.b / osc.m,
            osc.D / osc.m, osc.k3 / osc.m)


def acceleration(x, v, args):
    """v' of eq. 3 inside a swing with sgn(v) = s (args from `ode_args`)."""
    s, w2, fric, bm, dm, k3m = args
    mul, add = jax.lax.mul, jax.lax.add
    spring = mul(add(w2, mul(k3m, mul(x, x))), x)
    return jax.lax.neg(add(add(spring, mul(s, fric)), mul(add(bm, mul(mul(dm, s), v)), v)))


def derivatives(args, x, v):
    """x and its first four time derivatives inside a swing (eq. 3 with the swing's sign s).

    The cubic stiffness enters through the secant k/m + (k3/m) x^2 (in the acceleration), the
    tangent k/m + 3 (k3/m) x^2 (in the third and fourth derivatives) and the last term
    6 (k3/m) x v^2 of the fourth: all exactly the linear spring's when k3 = 0.
    """
    s, w2, fric, bm, dm, k3m = args
    drag = bm + 2.0 * dm * s * v  # d(b v/m + D s v^2/m)/dv
    w2t = w2 + 3.0 * k3m * (x * x)
    a = acceleration(x, v, args)
    jerk = -(w2t * v + drag * a)
    snap = -(w2t * a + drag * jerk + 2.0 * dm * s * a * a + 6.0 * k3m * x * v * v)
    return x, v, a, jerk, snap


def _combine(weights, ks):
    """sum_i w_i k_i over the stages with a nonzero weight, for both components."""
    out = []
    for comp in range(2):
        acc = None
        for w, k in zip(weights, ks, strict=False):
            if w == 0.0:
                continue
            term = jax.lax.mul(k[comp], jnp.asarray(w, dtype=k[comp].dtype))
            acc = term if acc is None else jax.lax.add(acc, term)
        out.append(acc)
    return out


def rk_step(x, v, h, args):
    """One DOP853 step of length h from (x, v).

    Returns:
        (x1, v1, err5, err3): the 8th-order solution and the two error estimators (without the
        factor h; see `error_norm`).
    """

    def f(xi, vi):
        return vi, acceleration(xi, vi, args)

    mul, add = jax.lax.mul, jax.lax.add
    ks = [f(x, v)]
    for row in tab.A:
        incr = _combine(row, ks)
        ks.append(f(add(x, mul(h, incr[0])), add(v, mul(h, incr[1]))))
    incr = _combine(tab.B, ks)
    x1, v1 = add(x, mul(h, incr[0])), add(v, mul(h, incr[1]))
    ks.append(f(x1, v1))
    return x1, v1, _combine(tab.E5, ks), _combine(tab.E3, ks)


def error_norm(x0, v0, x1, v1, err5, err3, h, rtol, atol):
    """DOP853's error norm of a step (scipy's `_estimate_error_norm`): <= 1 accepts it."""
    s5 = s3 = 0.0
    for y0, y1, e5, e3 in ((x0, x1, err5[0], err3[0]), (v0, v1, err5[1], err3[1])):
        scale = atol + rtol * jnp.maximum(jnp.abs(y0), jnp.abs(y1))
        s5 = s5 + (e5 / scale) ** 2
        s3 = s3 + (e3 / scale) ** 2
    denom = s5 + 0.01 * s3
    safe = jnp.where(denom > 0.0, denom, 1.0)
    return jnp.where(denom > 0.0, jnp.abs(h) * s5 / jnp.sqrt(2.0 * safe), 0.0)


def step_factor(err):
    """The factor for the next step size from a step's error norm (accepted or not)."""
    safe = jnp.where(err > 0.0, err, 1.0)
    grow = jnp.where(err > 0.0, SAFETY * safe ** EXPONENT, MAX_FACTOR)
    return jnp.clip(grow, MIN_FACTOR, MAX_FACTOR)
