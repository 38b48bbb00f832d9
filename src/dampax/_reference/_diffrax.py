"""The reference by diffrax (issue 35, item 3): eq. 3 swing by swing with diffrax's Dopri8 and
its events, behind the same call (``solve(..., method="reference", engine="diffrax")``).

The design card's reference integrator, kept as a second, independent engine: inside a swing
sgn(v) = s is constant and ``diffrax.diffeqsolve`` integrates the smooth motion (Dopri8, PID
step control with the same rtol and atol, the largest step 1/w as in ``_engine``) until its
event s v <= 0 (a down-crossing) ends the solve at the step that crosses the velocity zero.
Every accepted step diffrax saves (``SaveAt(steps=True)``) becomes a row of the same table as
dampax's engine (``_sampling.hermite_row``: the degree-9 Hermite polynomial of its ends, as
accurate as the step), and the turning point is found on the crossing step's polynomial
(``_events.turning_point``): diffrax's own root find on its dense output (Dopri8's
interpolant) put the turning point 1e-9 to 1e-8 A0 off at rtol = 1e-10, and every swing
restarted from there (undamped motion over 4 periods: 4.7e-8 A0 from the exact solution,
against 1.7e-10 this way), and that root find (closure-converted by optimistix) failed inside
the error map's ``shard_map`` (docs/DESIGN.md, pitfalls). There the block sticks for good if
|k x + k3 x^3| <= mu_s m g, else the next swing starts from (x*, 0) with the opposite sign. The
solution is a ``ReferenceSolution`` like any other: x(ts), v(ts), the energy, the turning
points, jit, vmap and both modes of differentiation (``adjoint``: diffrax's
``RecursiveCheckpointAdjoint``, ``ForwardMode`` or ``DirectAdjoint``).

The steps are diffrax's (its Runge-Kutta tableau, its error control, its loop): the tests
compare the two engines as independent numbers on every platform (where scipy's integrator
cannot run, a GPU). Slower: one ``diffeqsolve`` per swing of the budget (``jax.lax.scan``
over ``max_swings``; a finished motion runs short dummy solves).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._models._solution import RESULTS, first_failure
from ._engine import DT0_W0, DTMAX_W0, domain_input
from ._events import turning_point
from ._sampling import WIDTH, hermite_row
from ._stepping import acceleration, ode_args

#: steps of a swing's budget: diffrax's Dopri8 takes more steps per swing than dampax's DOP853
#: at the same tolerances (its error norm is an RMS); at least this many, or twice dampax's
MIN_STEPS_PER_SWING = 32


def _adjoint(dfx, adjoint: str):
    return {"recursive": dfx.RecursiveCheckpointAdjoint, "forward": dfx.ForwardMode,
            "direct": dfx.DirectAdjoint}[adjoint]()


def _vector_field(t, y, args):
    return jnp.stack([y[1], acceleration(y[0], y[1], args)])


def _swing_rows(sol, args):
    """(rows, n, turn) of one swing's saved steps (t0 first, inf-padded): a row per step, the
    number of steps, and the velocity zero on the last step's polynomial, (t*, x*)."""
    saved = jnp.isfinite(sol.ts)
    # the padding made finite (its rows are dropped; inf there gave NaN cotangents)
    ts, x, v = (jnp.where(saved, a, 0.0) for a in (sol.ts, sol.ys[:, 0], sol.ys[:, 1]))
    ok = saved[1:]
    safe = [jnp.where(ok, a[1:], a[:-1]) for a in (ts, x, v)]
    rows = hermite_row(ts[:-1], safe[0], x[:-1], v[:-1], safe[1], safe[2], args)
    n = jnp.sum(ok)
    j = jnp.maximum(n - 1, 0)
    turn = turning_point(rows[j], ts[j], safe[0][j] - ts[j], v[j], safe[2][j], n > 0)
    return jnp.where(ok[:, None], rows, jnp.inf), n, turn


def integrate(osc, x0, v0, t_end, *, rtol, atol, max_swings: int, rows: int, adjoint: str):
    """Integrate one trajectory with diffrax (the arguments and the returned dict as
    ``_engine.integrate``'s; a swing's budget is twice dampax's, at least
    :data:`MIN_STEPS_PER_SWING` steps, and the table as long as the budgets)."""
    import diffrax as dfx

    checks, ok_in, osc, x0, v0, t_end, w_hi = domain_input(osc, x0, v0, t_end)
    params = ode_args(osc, 0.0)[1:]
    per_swing = max(2 * (rows // max_swings), MIN_STEPS_PER_SWING)
    term = dfx.ODETerm(_vector_field)
    control = dfx.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX_W0 / w_hi)
    event = dfx.Event(lambda t, y, args, **kw: args[0] * y[1], direction=False)
    rest0 = (v0 == 0.0) & osc.sticks(x0)
    s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))

    def swing(c, _):
        done = c["halted"] | c["finished"] | c["failed"]
        args = (c["s"],) + params
        # a finished motion: a short dummy solve (its rows and turn are not kept)
        t0 = jnp.where(done, t_end - 0.5 * DT0_W0 / w_hi, c["t"])
        sol = dfx.diffeqsolve(term, dfx.Dopri8(), t0, t_end, DT0_W0 / w_hi,
                              jnp.stack([c["x"], c["v"]]), args=args,
                              stepsize_controller=control, event=event,
                              saveat=dfx.SaveAt(t0=True, steps=True), max_steps=per_swing,
                              throw=False, adjoint=_adjoint(dfx, adjoint))
        block, n, (t_sw, x_sw) = _swing_rows(sol, args)
        turned = sol.result == dfx.RESULTS.event_occurred
        reached = sol.result == dfx.RESULTS.successful
        t1 = jnp.where(turned, t_sw, sol.ts[n])
        x1 = jnp.where(turned, x_sw, sol.ys[n, 0])
        stick = turned & osc.sticks(x1)
        reverse = turned & ~stick
        live = ~done
        new = dict(t=jnp.where(live, t1, c["t"]), x=jnp.where(live, x1, c["x"]),
                   v=jnp.where(live, jnp.where(turned, 0.0, sol.ys[n, 1]), c["v"]),
                   s=jnp.where(live & reverse, -jnp.sign(x1), c["s"]),
                   halted=c["halted"] | (live & stick),
                   t_halt=jnp.where(live & stick, t1, c["t_halt"]),
                   x_halt=jnp.where(live & stick, x1, c["x_halt"]),
                   finished=c["finished"] | (live & reached),
                   failed=c["failed"] | (live & ~turned & ~reached),
                   n_swings=c["n_swings"] + jnp.where(live & reverse, 1, 0))
        kept = (jnp.where(live, block, jnp.inf), jnp.where(live, n, 0),
                jnp.where(live & turned, jnp.stack([t1, x1]), jnp.nan))
        return new, kept

    zero = jnp.zeros((), dtype=jnp.float64)
    init = dict(t=zero, x=x0, v=v0, s=s0, halted=rest0, t_halt=zero, x_halt=x0,
                finished=jnp.array(False), failed=jnp.array(False),
                n_swings=jnp.where(rest0, 0, 1))
    final, (blocks, counts, turns) = jax.lax.scan(swing, init, None, length=max_swings)
    # the rows in time order (each swing's block is inf-padded: the real rows sort first)
    table = blocks.reshape(-1, WIDTH)
    table = table[jnp.argsort(jax.lax.stop_gradient(table[:, 0]), stable=True)]
    turns = turns[jnp.argsort(jnp.where(jnp.isfinite(turns[:, 0]), 0, 1), stable=True)]
    # a swing's step budget spent, or the swings' before t_end or the halt: the budget ran out;
    # diffrax stopped for another reason: it failed
    budget = jnp.any(counts >= per_swing) & ~final["finished"] & ~final["halted"]
    over = ~(final["halted"] | final["finished"] | final["failed"])
    result = first_failure(*checks, (final["failed"] & ~budget, RESULTS.solver_failed),
                           (over | budget, RESULTS.max_swings_reached))
    return dict(final, rows=table, n_rows=jnp.sum(counts), turns=turns, ok_in=ok_in,
                result=result)
