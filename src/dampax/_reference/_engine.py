"""The integration loop: steps, swings and sticking of one trajectory, in one flat loop.

Every iteration evaluates one DOP853 step (`_stepping.rk_step`) of the controller's size from
the loop's state, accepted or rejected by its error. An accepted step is stored as a row, its
interpolating polynomial (`_sampling.hermite_row`); when it ended with s v <= 0 it crossed the
swing's velocity zero, which is found on that polynomial (`_events.turning_point`), and the
block either sticks there for good or the next swing starts from (x*, 0) with the opposite
sign. No step is re-taken, so every iteration costs the same, and under `jax.vmap` no lane
waits for another's root finding. The loop ends when the trajectory halts, reaches t_end,
fails, or runs out of its budget: a trajectory costs the steps its motion takes, and nothing
after its halt. The rows are a buffer written once each (`equinox.internal.while_loop`
buffers: reverse-mode differentiable through recursive checkpointing without copying the
table).
"""

from __future__ import annotations

import functools

import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._models._solution import RESULTS, first_failure, input_checks
from ._events import turning_point
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


def domain_input(osc, x0, v0, t_end):
    """(checks, ok_in, osc, x0, v0, t_end, w_hi) of one trajectory: the input checks; input
    out of the domain (non-finite or non-positive m, k, g, negative mu, b, D, a non-finite
    state, t_end not > 0) replaced by a harmless stand-in (at rest) and flagged by ok_in; and
    the fastest the motion can get, w_hi: with a hardening spring (k3 > 0) the tangent
    stiffness k + 3 k3 x^2 is at most k + 6 k3 E0/k (|x|^2 <= 2 E0/k), so w_hi = w0 sqrt(1 +
    6 k3 E0/k^2) bounds the local frequency (exactly w0 when k3 <= 0). Shared by the engines
    (this one and ``_diffrax``)."""
    checks = (*input_checks(osc, x0, v0),
              (~(jnp.isfinite(t_end) & (t_end > 0.0)), RESULTS.invalid_t_end))
    ok_in = ~functools.reduce(jnp.logical_or, [failed for failed, _ in checks])
    osc = jax.tree_util.tree_map(lambda a: jnp.where(ok_in, a, 1.0), osc)
    x0, v0, t_end = (jnp.where(ok_in, x0, 0.0), jnp.where(ok_in, v0, 0.0),
                     jnp.where(ok_in, t_end, 1.0))
    k3_hard = jnp.maximum(osc.k3, 0.0)
    w_hi = osc.omega0 * jnp.sqrt(1.0 + 6.0 * k3_hard * osc.energy(x0, v0) / (osc.k * osc.k))
    return checks, ok_in, osc, x0, v0, t_end, w_hi


def decide(c, h, remaining, x1, v1, err, dtmax, w_hi) -> dict:
    """What a step of size h from the state c decides (both engines: this loop and the fused
    kernel's): accepted or not, whether it crossed the swing's velocity zero, whether it was
    the last, the next step size, and failure (non-finite, or a step size that vanished)."""
    # the step sizes are chosen, not differentiated: derivatives are those of the numerical
    # solution for the steps it took (and the controller's power of a vanishing or infinite
    # error would give NaN cotangents)
    err = jax.lax.stop_gradient(err)
    finite = jnp.isfinite(x1) & jnp.isfinite(v1) & jnp.isfinite(err)
    accepted = finite & (err <= 1.0)
    crossed = accepted & (c["s"] * v1 <= 0.0)
    plain = accepted & ~crossed
    last = plain & (h >= remaining)
    h_next = jnp.minimum(h * step_factor(jnp.where(finite, err, jnp.inf)), dtmax)
    h_next = jax.lax.stop_gradient(jnp.where(last, c["h"], h_next))
    tiny = ~accepted & (h_next <= 1e-13 * jnp.maximum(c["t"], 1.0 / w_hi))
    return dict(h=h, x1=x1, v1=v1, accepted=accepted, crossed=crossed, plain=plain, last=last,
                h_next=h_next, failed=(~finite & (h <= 0.0)) | tiny)


def next_state(c, d, t_end, rows: int, max_swings: int) -> dict:
    """The loop's state after the step ``d`` (:func:`decide`, with the turning point t_sw,
    x_sw and whether the block sticks there or reverses): both engines' update, the row
    table's and the turning points' writes aside."""
    t, x, v = c["t"], c["x"], c["v"]
    plain, crossed, last, stick = d["plain"], d["crossed"], d["last"], d["stick"]
    full = d["accepted"] & (c["n_rows"] >= rows)
    return dict(
        t=jnp.where(plain, jnp.where(last, t_end, t + d["h"]),
                    jnp.where(crossed, d["t_sw"], t)),
        x=jnp.where(plain, d["x1"], jnp.where(crossed, d["x_sw"], x)),
        v=jnp.where(plain, d["v1"], jnp.where(crossed, 0.0, v)),
        s=jnp.where(d["reverse"], -jnp.sign(d["x_sw"]), c["s"]), h=d["h_next"],
        halted=c["halted"] | stick,
        t_halt=jnp.where(stick, d["t_sw"], c["t_halt"]),
        x_halt=jnp.where(stick, d["x_sw"], c["x_halt"]),
        finished=c["finished"] | last, failed=c["failed"] | d["failed"],
        budget=c["budget"] | full | (d["reverse"] & (c["n_swings"] >= max_swings)),
        n_rows=c["n_rows"] + jnp.where(d["accepted"] & ~full, 1, 0),
        n_swings=c["n_swings"] + jnp.where(d["reverse"], 1, 0),
        n_turns=c["n_turns"] + jnp.where(crossed, 1, 0))


def integrate(osc, x0, v0, t_end, *, rtol, atol, max_swings: int, rows: int, adjoint: str):
    """Integrate one trajectory (all inputs scalars).

    Returns:
        A dict: the final loop state (t, x, v, halted, t_halt, x_halt, n_swings, ...), the
        rows table (rows, 12: `_sampling`) and its fill n_rows, the turning points (t, x) of
        shape (max_swings, 2), NaN-padded, the result (a RESULTS member), and the input check
        ok_in.
    """
    checks, ok_in, osc, x0, v0, t_end, w_hi = domain_input(osc, x0, v0, t_end)
    params = ode_args(osc, 0.0)[1:]
    dtmax = DTMAX_W0 / w_hi
    zero = jnp.zeros((), dtype=float)

    rest0 = (v0 == 0.0) & osc.sticks(x0)
    s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))
    state = dict(
        t=zero, x=x0, v=v0, s=s0, h=DT0_W0 / w_hi, halted=rest0, t_halt=zero, x_halt=x0,
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
        args = (s,) + params
        remaining = t_end - t
        h = jnp.minimum(c["h"], remaining)
        # A branch of its own, so that its outputs are stored: used directly, XLA fused the
        # chain of stages into every consumer of x1, v1 and err (each select of the state),
        # about twenty copies of the step (jax.lax.optimization_barrier is dropped before
        # fusion on CPU). The predicate is unbatched (`unvmap_any`), so this stays a real
        # branch under vmap; it is true in every iteration the loop runs.
        x1, v1, err = jax.lax.cond(eqxi.unvmap_any(running(c)), _step, _no_step,
                                   x, v, h, args)
        d = decide(c, h, remaining, x1, v1, err, dtmax, w_hi)

        # the stored row: the polynomial of the accepted step (`_sampling.hermite_row`, built
        # here once per step); after a crossing it holds up to the turning point, found on it
        # branches of their own (outputs stored), as the step: the row's ten coefficients and
        # the Newton iterates on them were otherwise fused into every select that reads them
        live = eqxi.unvmap_any(running(c))
        row = jax.lax.cond(live, hermite_row, lambda *a: jnp.full(x.shape + (WIDTH,), jnp.inf),
                           t, t + h, x, v, x1, v1, args)
        d["t_sw"], d["x_sw"] = jax.lax.cond(live, turning_point, lambda *a: (t, x),
                                            row, t, h, v, v1, d["crossed"])
        d["stick"] = d["crossed"] & osc.sticks(d["x_sw"])  # |k x + k3 x^3| <= mu_s m g
        d["reverse"] = d["crossed"] & ~d["stick"]
        n_rows = c["n_rows"]
        new_rows = eqxi.buffer_at_set(c["rows"], jnp.minimum(n_rows, rows - 1), row,
                                      pred=d["accepted"] & (n_rows < rows))
        # the turning point (the rest point last): at most max_swings of them
        n_turns = c["n_turns"]
        new_turns = eqxi.buffer_at_set(c["turns"], jnp.minimum(n_turns, max_swings - 1),
                                       jnp.stack([d["t_sw"], d["x_sw"]]),
                                       pred=d["crossed"] & (n_turns < max_swings))
        return dict(next_state(c, d, t_end, rows, max_swings), rows=new_rows, turns=new_turns)

    # iterations: every stored row, the re-taken steps of every turning point, and rejections
    max_steps = 2 * rows + 64
    final = eqxi.while_loop(running, body, state, max_steps=max_steps,
                            buffers=lambda c: (c["rows"], c["turns"]), kind=_KINDS[adjoint])
    out_of_steps = running(final)  # the loop's iteration cap
    result = first_failure(*checks, (final["failed"], RESULTS.solver_failed),
                           (final["budget"] | out_of_steps, RESULTS.max_swings_reached))
    return dict(final, ok_in=ok_in, result=result)
