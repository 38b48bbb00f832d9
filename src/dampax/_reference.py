"""Reference solution of eq. 3 by diffrax, swing by swing (DESIGN section 2.6).

Inside a swing sgn(v) = s is constant, so the equation of motion

    x' = v,   v' = -(k/m) x - s mu g - (b/m) v - (D/m) s v^2

is smooth and an adaptive Runge--Kutta method integrates it to full accuracy. A swing ends
at the velocity zero, located by a `diffrax.Event` (cond = s v, root-found on the dense
interpolation) and then polished by Newton steps on a re-taken Runge--Kutta step. There the
block sticks for good when |x| <= xc = mu m g / k, or the next swing starts with v = 0 and
s = -sgn(x). The sign function is never smoothed.

The swings run in a fixed-length `jax.lax.scan` (reverse-mode differentiable, vmappable with
different numbers of swings per element). Each scan slot is one `diffeqsolve` ("segment") that
ends at a velocity zero, at `t_end`, or after `max_steps_per_swing` solver steps; in the last
case the same swing continues in the next slot. Every accepted step endpoint is stored, and the
dense output x(t), v(t) re-takes one Runge--Kutta step from the step start before t, so it is as
accurate between the steps as at them (the step is no longer than the accepted one).

Derivatives: the event time from the root finder is held fixed (`stop_gradient`); the swing's
end time is t* - v(t*)/a(t*) on the re-taken step, whose first derivative is the exact one
(implicit function theorem), and the turning point x(t*) then carries the total derivative.
"""

from __future__ import annotations

import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._oscillator import Oscillator, check_finite, is_concrete

Array = jax.Array

_SOLVERS = {"dopri8": dfx.Dopri8, "dopri5": dfx.Dopri5, "tsit5": dfx.Tsit5}
_ROOT_FINDERS = ("newton", "bisection")
_ADJOINTS = ("recursive", "forward", "direct")

# Largest step, in units of 1/w0: a step never spans two velocity zeros (a swing lasts about
# pi/w0), and the dense interpolation the event root finder works on stays accurate.
_DTMAX_W0 = 1.0
# First trial step of every segment, in units of 1/w0 (the controller shrinks it if needed).
_DT0_W0 = 0.25
# Default t_end in undamped periods: 25 periods are about 50 swings, within max_swings=64.
_DEFAULT_PERIODS = 25.0

_UNROLL = False
_STATUS_OK = 0
_STATUS_BUDGET = 1
_STATUS_SOLVER = 2


def _vector_field(t, y, args):
    """Right-hand side of eq. 3 inside a swing with constant sgn(v) = s."""
    del t
    s, w2, fric, bm, dm = args
    x, v = y[0], y[1]
    return jnp.stack([v, -w2 * x - s * fric - bm * v - dm * s * v * v])


def _event_cond(t, y, args, **kwargs):
    """s v: positive inside the swing, zero at its end."""
    del t, kwargs
    return args[0] * y[1]


def _stages(tableau, vf, t0, y0, h, *, last: bool):
    """Stage derivatives k_i of an explicit Runge--Kutta step, unrolled in Python."""
    ks = [vf(t0, y0)]
    rows = zip(tableau.c, tableau.a_lower) if last else zip(tableau.c[:-1], tableau.a_lower[:-1])
    for c_i, a_i in rows:
        incr = sum(float(a) * k for a, k in zip(a_i, ks) if a != 0.0)
        ks.append(vf(t0 + float(c_i) * h, y0 + h * incr))
    return ks


def _combine(weights, ks):
    return sum(float(w) * k for w, k in zip(weights, ks) if w != 0.0)


class _UnrolledERK(dfx.AbstractAdaptiveSolver):
    """An explicit Runge--Kutta method of diffrax (Dopri8, Dopri5, Tsit5) with unrolled stages.

    Same tableau, error estimate and dense interpolation as the diffrax solver, but the stages
    are written out instead of looped over: faster to run and to compile for this 2-dimensional
    system, and differentiable in forward and reverse mode with any adjoint. The first stage is
    evaluated afresh every step (no first-same-as-last reuse), so the solver has no state.
    """

    name: str = eqx.field(static=True)
    term_structure = dfx.AbstractTerm

    @property
    def interpolation_cls(self):
        return _SOLVERS[self.name].interpolation_cls

    def order(self, terms):
        return _SOLVERS[self.name]().order(terms)

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        tableau = _SOLVERS[self.name].tableau
        h = t1 - t0
        ks = _stages(tableau, lambda t, y: terms.vf(t, y, args), t0, y0, h, last=True)
        y1 = y0 + h * _combine(tableau.b_sol, ks)
        y_error = h * _combine(tableau.b_error, ks)
        dense_info = dict(y0=y0, y1=y1, k=h * jnp.stack(ks))
        return y1, y_error, dense_info, None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _restep(solver_name, args, t0, y0, t1):
    """One Runge--Kutta step of the named solver from (t0, y0) to t1: the dense output.

    The step's last stage (first-same-as-last) is not needed for y1 and is skipped.
    """
    tableau = _SOLVERS[solver_name].tableau
    h = t1 - t0
    ks = _stages(tableau, lambda t, y: _vector_field(t, y, args), t0, y0, h, last=False)
    return y0 + h * _combine(tableau.b_sol, ks)


class ReferenceSolution(eqx.Module):
    """Numerical reference solution of eq. 3 (see `solve_reference`).

    Attributes:
        osc: the Oscillator that was solved.
        x0, v0: the initial state.
        t_end: end of the requested interval [0, t_end].
        halted: True when the block stuck for good at or before t_end.
        halt_time: time of the final stop (0 for a start at rest inside the band); inf when the
            block does not stop within [0, t_end] (always for mu = 0; for mu > 0 check `halted`).
        halt_position: position of the final stop; NaN where it does not stop within [0, t_end].
        valid: False when the budget (max_swings, max_steps_per_swing) ran out or the solver
            failed before t_end or the halt; the solution then covers only part of [0, t_end].
        n_swings: number of swings (intervals of motion with constant sgn(v)) that were used.
        swing_times: end times of the swings, i.e. the turning points (v = 0, t > 0); the last
            one is the rest point when the block halts. Length max_swings, NaN-padded.
        turning_x: positions at those turning points, NaN-padded.
        status: 0 ok, 1 budget ran out, 2 the ODE solver failed.
        seg_t0, seg_n, seg_s, seg_ts, seg_ys: per scan slot its start time (inf if unused), the
            number of stored step points, the sign of v, and the step times and states (inf
            padded); used by the dense output.
        t_cover: the end of the integrated interval (inf once halted).

    Every array attribute may carry leading batch axes (a batched solve); the methods then
    evaluate every trajectory.
    """

    osc: Oscillator
    x0: Array
    v0: Array
    t_end: Array
    halted: Array
    halt_time: Array
    halt_position: Array
    valid: Array
    n_swings: Array
    swing_times: Array
    turning_x: Array
    status: Array
    seg_t0: Array
    seg_n: Array
    seg_s: Array
    seg_ts: Array
    seg_ys: Array
    t_cover: Array
    solver_name: str = eqx.field(static=True, default="dopri8")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape of a batched solution (() for a single trajectory)."""
        return jnp.shape(self.halt_time)

    def _map(self, fn, *xs):
        """Apply ``fn(single_solution, *xs)`` over the batch axes of ``self``."""
        for _ in self.batch_shape:
            fn = jax.vmap(fn, in_axes=(0,) + (None,) * len(xs))
        return fn(self, *xs)

    def _state_single(self, t):
        """(x, v) of one trajectory at a scalar time t."""
        t = jnp.asarray(t, dtype=float)
        args_static = _ode_args(self.osc, 0.0)
        before = t < 0.0
        resting = self.halted & (t >= self.halt_time)
        beyond = (~resting) & (t > self.t_cover)
        moving = ~(before | resting | beyond)
        first_t = self.seg_t0[0]
        t_safe = jnp.where(moving, t, jnp.where(jnp.isfinite(first_t), first_t, 0.0))
        i = jnp.searchsorted(self.seg_t0, t_safe, side="right") - 1
        i = jnp.clip(i, 0, self.seg_t0.shape[0] - 1)
        ts_i = self.seg_ts[i]
        n_i = jnp.maximum(self.seg_n[i], 1)
        j = jnp.clip(jnp.searchsorted(ts_i, t_safe, side="right") - 1, 0, n_i - 1)
        tj = ts_i[j]
        tj = jnp.where(jnp.isfinite(tj), tj, t_safe)
        yj = jnp.where(jnp.isfinite(self.seg_ys[i, j]), self.seg_ys[i, j], 0.0)
        args = (self.seg_s[i],) + args_static[1:]
        y = _restep(self.solver_name, args, tj, yj, t_safe)
        nan = jnp.nan
        x = jnp.where(moving, y[0], jnp.where(resting, self.halt_position, nan))
        v = jnp.where(moving, y[1], jnp.where(resting, 0.0, nan))
        return x, v

    def _eval(self, t, which):
        t = jnp.asarray(t, dtype=float)

        def single(sol, tt):
            flat = tt.reshape(-1)
            x, v = jax.vmap(sol._state_single)(flat)
            if which == "x":
                out = x
            elif which == "v":
                out = v
            else:
                out = sol.osc.energy(x, v)
            return out.reshape(tt.shape)

        return self._map(single, t)

    def x(self, t) -> Array:
        """Position at time(s) t.

        Arguments:
            t: scalar or array of times; NaN before 0, and after the end of the integrated
                interval unless the block has stuck (then its rest position).

        Returns:
            x(t), shaped like t (with the solution's batch shape in front when batched).
        """
        return self._eval(t, "x")

    def v(self, t) -> Array:
        """Velocity at time(s) t.

        Arguments:
            t: scalar or array of times (see `x`).

        Returns:
            v(t), shaped like t (with the batch shape in front when batched).
        """
        return self._eval(t, "v")

    def energy(self, t) -> Array:
        """Mechanical energy k x^2/2 + m v^2/2 at time(s) t.

        Arguments:
            t: scalar or array of times (see `x`).

        Returns:
            E(t), shaped like t (with the batch shape in front when batched).
        """
        return self._eval(t, "energy")

    def turning_points(self, n: int) -> tuple[Array, Array]:
        """The first n turning points (t_n, x_n): v = 0 at t_n > 0, the rest point last.

        A start at rest is not counted; after the halt (or beyond what was integrated) the
        entries are NaN.

        Arguments:
            n: number of turning points (static Python int).

        Returns:
            (t_n, x_n), each of shape (n,) (with the batch shape in front when batched).
        """
        n = int(n)
        length = self.swing_times.shape[-1]

        def pick(a):
            if n <= length:
                return a[..., :n]
            pad = jnp.full(a.shape[:-1] + (n - length,), jnp.nan, dtype=a.dtype)
            return jnp.concatenate([a, pad], axis=-1)

        return pick(self.swing_times), pick(self.turning_x)


def _ode_args(osc: Oscillator, s):
    """Arguments of `_vector_field`: (s, k/m, mu g, b/m, D/m)."""
    return (jnp.asarray(s, dtype=float), osc.k / osc.m, osc.mu * osc.g, osc.b / osc.m,
            osc.D / osc.m)


def _solve_single(osc, x0, v0, t_end, *, rtol, atol, max_swings, max_steps_per_swing,
                  solver_name, root_finder, adjoint):
    """Unbatched core of `solve_reference` (all inputs scalars)."""
    solver = _UnrolledERK(solver_name) if _UNROLL else _SOLVERS[solver_name]()
    w0 = osc.omega0
    xc = osc.xc
    zero = jnp.zeros((), dtype=float)
    term = dfx.ODETerm(_vector_field)
    if root_finder == "newton":
        rf = optx.Newton(rtol=1e-10, atol=1e-12)
    else:
        rf = optx.Bisection(rtol=1e-10, atol=1e-12)
    event = dfx.Event(_event_cond, root_finder=rf, direction=False)
    controller = dfx.PIDController(rtol=rtol, atol=atol, dtmax=_DTMAX_W0 / w0)
    adj = {"recursive": dfx.RecursiveCheckpointAdjoint(), "forward": dfx.ForwardMode(),
           "direct": dfx.DirectAdjoint()}[adjoint]
    saveat = dfx.SaveAt(t0=True, steps=True)

    rest0 = (v0 == 0.0) & (jnp.abs(x0) <= xc)
    s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))
    active0 = (~rest0) & (t_end > 0.0)
    carry0 = dict(
        t=zero, x=x0, v=v0, s=s0, active=active0, halted=rest0, t_halt=zero,
        x_halt=x0, failed=jnp.array(False), n_swings=jnp.where(rest0, 0, 1),
    )

    def body(c, _):
        active = c["active"]
        t0 = c["t"]
        t1 = jnp.where(active, t_end, t0)
        args = _ode_args(osc, c["s"])
        y0 = jnp.stack([c["x"], c["v"]])
        sol = dfx.diffeqsolve(
            term, solver, t0, t1, _DT0_W0 / w0, y0, args, saveat=saveat,
            stepsize_controller=controller, adjoint=adj, event=event,
            max_steps=max_steps_per_swing, throw=False,
        )
        ts = sol.ts
        ys = sol.ys
        fired = active & (sol.result == dfx.RESULTS.event_occurred)
        capped = active & (sol.result == dfx.RESULTS.max_steps_reached)
        okay = (sol.result == dfx.RESULTS.successful) | (sol.result == dfx.RESULTS.event_occurred)
        failed = active & ~(okay | (sol.result == dfx.RESULTS.max_steps_reached))
        # Stored points: t0 and every accepted step end. After an event diffrax appends the
        # interpolated event state; drop it, the polished turning point replaces it.
        n_fin = jnp.sum(jnp.isfinite(ts))
        n_seg = jnp.where(fired, n_fin - 1, n_fin)
        n_seg = jnp.maximum(n_seg, 1)
        keep = jnp.arange(ts.shape[0]) < n_seg
        ts = jnp.where(keep, ts, jnp.inf)
        ys = jnp.where(keep[:, None], ys, jnp.inf)
        t_p = ts[n_seg - 1]
        y_p = ys[n_seg - 1]

        # Turning point: Newton on the re-taken step from the last stored point. The root
        # finder's time and one Newton step are held fixed; the last Newton step carries the
        # derivative (implicit function theorem).
        t_star = jax.lax.stop_gradient(jnp.where(fired, sol.ts[n_fin - 1], t_p))
        t_star = jnp.maximum(t_star, jax.lax.stop_gradient(t_p))

        def newton(t_guess):
            y = _restep(solver_name, args, t_p, y_p, t_guess)
            a = _vector_field(t_guess, y, args)[1]
            a_safe = jnp.where(fired & (a != 0.0), a, 1.0)
            dt = jnp.where(fired & (a != 0.0), -y[1] / a_safe, 0.0)
            return y, dt

        _, dt1 = newton(t_star)
        t_new = jax.lax.stop_gradient(t_star + dt1)
        y_new, dt2 = newton(t_new)
        t_sw = t_new + dt2
        x_sw = y_new[0] + y_new[1] * dt2

        stick = fired & (jnp.abs(x_sw) <= xc)
        reverse = fired & ~stick
        # Continue the same swing after a full step budget, from the last stored point.
        t_next = jnp.where(fired, t_sw, t_p)
        x_next = jnp.where(fired, x_sw, y_p[0])
        v_next = jnp.where(fired, 0.0, y_p[1])
        s_next = jnp.where(reverse, -jnp.sign(x_sw), c["s"])
        still = active & (reverse | capped) & ~failed
        new = dict(
            t=jnp.where(active, t_next, t0),
            x=jnp.where(active, x_next, c["x"]),
            v=jnp.where(active, v_next, c["v"]),
            s=jnp.where(active, s_next, c["s"]),
            active=still,
            halted=c["halted"] | stick,
            t_halt=jnp.where(stick, t_sw, c["t_halt"]),
            x_halt=jnp.where(stick, x_sw, c["x_halt"]),
            failed=c["failed"] | failed,
            n_swings=c["n_swings"] + jnp.where(reverse, 1, 0),
        )
        out = dict(
            seg_t0=jnp.where(active, t0, jnp.inf),
            seg_n=jnp.where(active, n_seg, 0),
            seg_s=c["s"],
            seg_ts=ts,
            seg_ys=ys,
            fired=fired,
            t_sw=jnp.where(fired, t_sw, 0.0),
            x_sw=jnp.where(fired, x_sw, 0.0),
        )
        return new, out

    final, out = jax.lax.scan(body, carry0, None, length=max_swings)

    exhausted = final["active"]
    valid = ~exhausted & ~final["failed"]
    status = jnp.where(final["failed"], _STATUS_SOLVER,
                       jnp.where(exhausted, _STATUS_BUDGET, _STATUS_OK))
    halted = final["halted"]
    halt_time = jnp.where(halted, final["t_halt"], jnp.inf)
    halt_position = jnp.where(halted, final["x_halt"], jnp.nan)
    t_cover = jnp.where(halted, jnp.inf, final["t"])

    fired = out["fired"]
    slot = jnp.where(fired, jnp.cumsum(fired) - 1, max_swings)
    nan_row = jnp.full((max_swings,), jnp.nan)
    swing_times = nan_row.at[slot].set(out["t_sw"], mode="drop")
    turning_x = nan_row.at[slot].set(out["x_sw"], mode="drop")

    seg_ts = out["seg_ts"]
    seg_ys = out["seg_ys"]
    return ReferenceSolution(
        osc=osc, x0=x0, v0=v0, t_end=t_end, halted=halted, halt_time=halt_time,
        halt_position=halt_position, valid=valid, n_swings=final["n_swings"],
        swing_times=swing_times, turning_x=turning_x, status=status,
        seg_t0=out["seg_t0"], seg_n=out["seg_n"], seg_s=out["seg_s"], seg_ts=seg_ts,
        seg_ys=seg_ys, t_cover=t_cover, solver_name=solver_name,
    )


_STATIC = ("rtol", "atol", "max_swings", "max_steps_per_swing", "solver_name", "root_finder",
           "adjoint")


@jax.jit
def _default_t_end(osc):
    return _DEFAULT_PERIODS * 2.0 * math.pi / osc.omega0


def _solve_batched(osc, x0, v0, t_end, **kw):
    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in jax.tree_util.tree_leaves(
        (osc, x0, v0, t_end))))
    if shape == ():
        return _solve_single(osc, x0, v0, t_end, **kw)
    size = int(np.prod(shape))

    def flat(a):
        return jnp.broadcast_to(a, shape).reshape(size)

    osc_f, x0_f, v0_f, t_end_f = jax.tree_util.tree_map(flat, (osc, x0, v0, t_end))
    sol = jax.vmap(lambda o, a, b, c: _solve_single(o, a, b, c, **kw))(osc_f, x0_f, v0_f,
                                                                       t_end_f)
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), sol)


_solve_jit = jax.jit(_solve_batched, static_argnames=_STATIC)


def solve_reference(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                    atol: float = 1e-12, max_swings: int = 64, max_steps_per_swing: int = 64,
                    solver: str = "dopri8", root_finder: str = "newton",
                    adjoint: str = "recursive") -> ReferenceSolution:
    """Integrate eq. 3 swing by swing with diffrax; the reference for the analytic models.

    Arguments:
        osc: the Oscillator (fields may be arrays: every combination is solved, broadcast with
            x0, v0 and t_end).
        x0: initial position [m].
        v0: initial velocity [m/s].
        t_end: end of the time interval [s]; default 25 undamped periods (50 pi / w0), about
            50 swings. May be traced.
        rtol, atol: tolerances of the PID step-size controller.
        max_swings: number of scan slots (static). A slot holds one swing, or part of a swing
            that needs more than `max_steps_per_swing` steps (it continues in the next slot).
        max_steps_per_swing: solver steps (accepted and rejected) per slot (static). Every
            accepted step is stored for the dense output, so memory grows with
            max_swings * max_steps_per_swing; a swing takes about 10 steps at rtol = 1e-10.
        solver: "dopri8" (default), "dopri5" or "tsit5".
        root_finder: event root finder, "newton" (default) or "bisection" (the one that works
            under `jax.shard_map`).
        adjoint: "recursive" (default, reverse mode: jax.grad), "forward" (jax.jacfwd) or
            "direct" (both, slower). A diffrax limitation: no single fast adjoint supports
            both reverse and forward mode.

    Returns:
        A `ReferenceSolution`. Called eagerly, raises ValueError when x0 or v0 is not finite,
        when t_end is not positive, or when the budget ran out before t_end or the halt
        (naming max_swings / max_steps_per_swing); under jit it returns valid = False instead.
    """
    if solver not in _SOLVERS:
        raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {solver!r}")
    if root_finder not in _ROOT_FINDERS:
        raise ValueError(f"root_finder must be one of {_ROOT_FINDERS}, got {root_finder!r}")
    if adjoint not in _ADJOINTS:
        raise ValueError(f"adjoint must be one of {_ADJOINTS}, got {adjoint!r}")
    if int(max_swings) < 1 or int(max_steps_per_swing) < 2:
        raise ValueError("max_swings must be >= 1 and max_steps_per_swing >= 2")
    check_finite("x0", x0)
    check_finite("v0", v0)
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    if t_end is None:
        t_end = _default_t_end(osc)
    else:
        check_finite("t_end", t_end)
        if is_concrete(t_end) and np.any(np.asarray(t_end, dtype=float) <= 0):
            raise ValueError(f"t_end must be > 0, got {t_end!r}")
        t_end = jnp.asarray(t_end, dtype=float)
    sol = _solve_jit(osc, x0, v0, t_end, rtol=float(rtol), atol=float(atol),
                     max_swings=int(max_swings), max_steps_per_swing=int(max_steps_per_swing),
                     solver_name=solver, root_finder=root_finder, adjoint=adjoint)
    if is_concrete(sol.status):
        status = np.asarray(sol.status)
        if np.any(status == _STATUS_BUDGET):
            raise ValueError(
                "solve_reference ran out of its budget before t_end or the halt: increase "
                f"max_swings (now {max_swings}) or max_steps_per_swing (now "
                f"{max_steps_per_swing}), or shorten t_end")
        if np.any(status == _STATUS_SOLVER):
            raise ValueError("solve_reference: the ODE solver failed (non-finite state or step "
                             "size too small); check the parameters")
    return sol
