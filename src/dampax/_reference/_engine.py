"""The integration loop: steps, swings and sticking of one trajectory, in one flat loop.

Every iteration evaluates one DOP853 step (`_stepping.rk_step`) from the loop's state:
- in stepping mode, a trial step of the controller's size (accepted or rejected by its error);
  an accepted step that ends with s v > 0 is stored as a row and the state moves on;
- an accepted step that crossed the velocity zero switches to locating mode: the next
  `_events.NEWTON_ITERATIONS` iterations re-take the step from its start to Newton iterates of
  the zero; the last stores the row up to the turning point and either halts (the block sticks)
  or starts the next swing from (x*, 0) with the opposite sign.

So every iteration costs the same, and under `jax.vmap` a lane that locates a turning point
does not make the others compute a second step. The loop ends when the trajectory halts,
reaches t_end, fails, or runs out of its budget: a trajectory costs the steps its motion
takes, and nothing after its halt. The stored rows (`_sampling`: one per accepted step) are
a buffer written once per row (`equinox.internal.while_loop` buffers: reverse-mode
differentiable through recursive checkpointing without copying the table).
"""

from __future__ import annotations

import functools

import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._solution import RESULTS, first_failure, input_checks
from ._events import NEWTON_ITERATIONS, hermite_root, newton_update
from ._sampling import WIDTH, hermite_row
from ._stepping import error_norm, ode_args, rk_step, step_factor

# Largest step, in units of 1/w: a step never spans two velocity zeros (a swing lasts about
# pi/w), and the guess for the turning point stays close.
DTMAX_W0 = 1.0
# First trial step, in units of 1/w (the controller shrinks it if needed).
DT0_W0 = 0.25
# The loop's kind per adjoint: reverse mode needs the checkpointed loop, forward mode the
# plain one; "direct" (both) a bounded one.
_KINDS = {"recursive": "checkpointed", "forward": "lax", "direct": "bounded"}


def integrate(osc, x0, v0, t_end, *, rtol, atol, max_swings: int, rows: int, adjoint: str):
    """Integrate one trajectory (all inputs scalars).

    Returns:
        A dict: the final loop state (t, x, v, halted, t_halt, x_halt, n_swings, ...), the
        rows table (rows, 12: `_sampling`) and its fill n_rows, the turning points (t, x) of
        shape (max_swings, 2), NaN-padded, the result (a RESULTS member), and the input check
        ok_in.
    """
    # out of the domain (non-finite or non-positive m, k, g, negative mu, b, D, a non-finite
    # state, t_end not > 0): integrate a harmless stand-in (at rest) and flag it
    checks = (*input_checks(osc, x0, v0),
              (~(jnp.isfinite(t_end) & (t_end > 0.0)), RESULTS.invalid_t_end))
    ok_in = ~functools.reduce(jnp.logical_or, [failed for failed, _ in checks])
    osc = jax.tree_util.tree_map(lambda a: jnp.where(ok_in, a, 1.0), osc)
    x0, v0, t_end = (jnp.where(ok_in, x0, 0.0), jnp.where(ok_in, v0, 0.0),
                     jnp.where(ok_in, t_end, 1.0))
    params = ode_args(osc, 0.0)[1:]
    w0 = osc.omega0
    # the fastest the motion can get: with a hardening spring (k3 > 0) the tangent stiffness
    # k + 3 k3 x^2 is at most k + 6 k3 E0/k (|x|^2 <= 2 E0/k), so w_hi = w0 sqrt(1 + 6 k3 E0/k^2)
    # bounds the local frequency (exactly w0 when k3 <= 0)
    k3_hard = jnp.maximum(osc.k3, 0.0)
    w_hi = w0 * jnp.sqrt(1.0 + 6.0 * k3_hard * osc.energy(x0, v0) / (osc.k * osc.k))
    dtmax = DTMAX_W0 / w_hi
    zero = jnp.zeros((), dtype=float)

    rest0 = (v0 == 0.0) & osc.sticks(x0)
    s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))
    state = dict(
        t=zero, x=x0, v=v0, s=s0, h=DT0_W0 / w_hi, locating=jnp.array(False),
        it=jnp.array(0), t_guess=zero, halted=rest0, t_halt=zero, x_halt=x0,
        finished=jnp.array(False), failed=jnp.array(False), budget=jnp.array(False),
        n_rows=jnp.array(0), n_swings=jnp.where(rest0, 0, 1),
        n_turns=jnp.array(0), rows=jnp.full((rows, WIDTH), jnp.inf),
        turns=jnp.full((max_swings, 2), jnp.nan),
    )

    def _step(x, v, h, args):
        x1, v1, err5, err3 = rk_step(x, v, h, args)
        return x1, v1, error_norm(x, v, x1, v1, err5, err3, h, rtol, atol)

    def _no_step(x, v, h, args):
        return jnp.full_like(x, jnp.nan), jnp.full_like(v, jnp.nan), jnp.full_like(h, jnp.nan)

    def running(c):
        return ~(c["halted"] | c["finished"] | c["failed"] | c["budget"])

    def body(c):
        t, x, v, s = c["t"], c["x"], c["v"], c["s"]
        locating = c["locating"]
        args = (s,) + params
        remaining = t_end - t
        h = jnp.where(locating, c["t_guess"] - t, jnp.minimum(c["h"], remaining))
        # A branch of its own, so that its outputs are stored: used directly, XLA fused the
        # chain of stages into every consumer of x1, v1 and err (each select of the state),
        # about twenty copies of the step (jax.lax.optimization_barrier is dropped before
        # fusion on CPU). The predicate is unbatched (`unvmap_any`), so this stays a real
        # branch under vmap; it is true in every iteration the loop runs.
        x1, v1, err = jax.lax.cond(eqxi.unvmap_any(running(c)), _step, _no_step,
                                   x, v, h, args)
        # the step sizes are chosen, not differentiated: derivatives are those of the
        # numerical solution for the steps it took (and the controller's power of a
        # vanishing or infinite error would give NaN cotangents)
        err = jax.lax.stop_gradient(err)
        finite = jnp.isfinite(x1) & jnp.isfinite(v1) & jnp.isfinite(err)

        # stepping mode
        accepted = ~locating & finite & (err <= 1.0)
        crossed = accepted & (s * v1 <= 0.0)
        plain = accepted & ~crossed
        last = plain & (h >= remaining)
        h_next = jnp.minimum(h * step_factor(jnp.where(finite, err, jnp.inf)), dtmax)
        h_next = jax.lax.stop_gradient(
            jnp.where(locating, c["h"], jnp.where(plain & last, c["h"], h_next)))
        tiny = ~locating & ~accepted & (h_next <= 1e-13 * jnp.maximum(t, 1.0 / w_hi))

        # locating mode: the re-taken step ended at the iterate t_guess; Newton's update
        dt = newton_update(x1, v1, args)
        final = locating & (c["it"] == NEWTON_ITERATIONS - 1)
        t_sw = c["t_guess"] + dt
        x_sw = x1 + v1 * dt
        guess = hermite_root(t, x, v, t + h, x1, v1, args, crossed)
        t_guess = jax.lax.stop_gradient(
            jnp.where(crossed, guess, jnp.where(locating, c["t_guess"] + dt, c["t_guess"])))
        stick = final & osc.sticks(x_sw)  # |k x + k3 x^3| <= mu m g
        reverse = final & ~stick
        failed = (locating & ~finite) | (~locating & ~finite & (h <= 0.0)) | tiny

        # the stored row: the polynomial of the accepted step, or of the step up to the
        # turning point (`_sampling.hermite_row`, built here once per step)
        store = plain | final
        t_b = jnp.where(plain, jnp.where(last, t_end, t + h), t_sw)
        x_b, v_b = jnp.where(plain, x1, x_sw), jnp.where(plain, v1, 0.0)
        row = hermite_row(t, t_b, x, v, x_b, v_b, args)
        n_rows = c["n_rows"]
        full = store & (n_rows >= rows)
        new_rows = eqxi.buffer_at_set(c["rows"], jnp.minimum(n_rows, rows - 1), row,
                                      pred=store & ~full)
        # the turning point (the rest point last): at most max_swings of them
        n_turns = c["n_turns"]
        new_turns = eqxi.buffer_at_set(c["turns"], jnp.minimum(n_turns, max_swings - 1),
                                       jnp.stack([t_sw, x_sw]), pred=final & (n_turns < max_swings))
        too_many = reverse & (c["n_swings"] >= max_swings)
        return dict(
            t=jnp.where(plain, t_b, jnp.where(final, t_sw, t)),
            x=jnp.where(plain, x1, jnp.where(final, x_sw, x)),
            v=jnp.where(plain, v1, jnp.where(final, 0.0, v)),
            s=jnp.where(reverse, -jnp.sign(x_sw), s),
            h=h_next,
            locating=crossed | (locating & ~final),
            it=jnp.where(locating & ~final, c["it"] + 1, 0),
            t_guess=t_guess,
            halted=c["halted"] | stick,
            t_halt=jnp.where(stick, t_sw, c["t_halt"]),
            x_halt=jnp.where(stick, x_sw, c["x_halt"]),
            finished=c["finished"] | last,
            failed=c["failed"] | failed,
            budget=c["budget"] | full | too_many,
            n_rows=n_rows + jnp.where(store & ~full, 1, 0),
            n_swings=c["n_swings"] + jnp.where(reverse, 1, 0),
            n_turns=n_turns + jnp.where(final, 1, 0),
            rows=new_rows,
            turns=new_turns,
        )

    # iterations: every stored row, the re-taken steps of every turning point, and rejections
    max_steps = 2 * rows + (NEWTON_ITERATIONS + 1) * max_swings + 64
    final = eqxi.while_loop(running, body, state, max_steps=max_steps,
                            buffers=lambda c: (c["rows"], c["turns"]), kind=_KINDS[adjoint])
    out_of_steps = running(final)  # the loop's iteration cap
    result = first_failure(*checks, (final["failed"], RESULTS.solver_failed),
                           (final["budget"] | out_of_steps, RESULTS.max_swings_reached))
    return dict(final, ok_in=ok_in, result=result)
