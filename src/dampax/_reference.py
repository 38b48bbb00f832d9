"""Reference solution of eq. 3 by diffrax, swing by swing (docs/DESIGN.md section 2.6).

Inside a swing sgn(v) = s is constant, so the equation of motion

    x' = v,   v' = -(k/m) x - (k3/m) x^3 - s mu g - (b/m) v - (D/m) s v^2

is smooth and an adaptive Runge--Kutta method integrates it to full accuracy. A swing ends at
the velocity zero: a `diffrax.Event` (cond = s v, `direction=False` so that a swing starting at
v = 0 does not end at once) stops the solve in the step that crosses it, and Newton's method
on a re-taken Runge--Kutta step finds it. There the block sticks for good when |x| <= xc =
mu m g / k (|k x + k3 x^3| <= mu m g with a cubic stiffness), or the next swing starts with
v = 0 and s = -sgn(x). sgn(v) is never smoothed.

The swings run in a fixed-length `jax.lax.scan` (reverse-mode differentiable; under `jax.vmap`
the elements may use different numbers of swings). Each scan slot is one `diffeqsolve`
("segment") that ends at a velocity zero, at `t_end`, or after `max_steps_per_swing` solver
steps; in the last case the same swing continues in the next slot. Every accepted step end is
stored as a knot, the turning point as the swing's last one. The dense output x(t), v(t) is the
degree-9 Hermite interpolant of the knot interval around t (x and its first four derivatives,
from eq. 3 with the swing's sign, at both ends): about 1e-11 A0 at rtol = 1e-10, as accurate
as the knots, and a tenth of the cost of re-taking a Dopri8 step. The interval is found by a
binary search per time, or, for sorted times on a uniform grid (an error map's samples), by
merging the knots into the grid in one pass.

Derivatives: the starting guess of Newton's method is held fixed (`stop_gradient`); the swing's
end time is t* - v(t*)/a(t*) on the re-taken step, whose first derivative is exact (implicit
function theorem), and the turning point x(t*) then carries the total derivative.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math

import diffrax as dfx
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._oscillator import Oscillator, check_count, check_finite, check_real, is_concrete
from ._solution import RESULTS, AbstractSolution, first_failure, input_checks

Array = jax.Array

_SOLVERS = {"dopri8": dfx.Dopri8, "dopri5": dfx.Dopri5, "tsit5": dfx.Tsit5}
_ROOT_FINDERS = ("newton", "optx-newton", "optx-bisection")
_ADJOINTS = ("recursive", "forward", "direct")

# Largest step, in units of 1/w0: a step never spans two velocity zeros (a swing lasts about
# pi/w0), and the guess for the turning point stays close.
_DTMAX_W0 = 1.0
# First trial step of every segment, in units of 1/w0 (the controller shrinks it if needed).
_DT0_W0 = 0.25
# Default t_end in undamped periods: 25 periods are about 50 swings, within max_swings = 64.
_DEFAULT_PERIODS = 25.0
# Newton steps (re-taken Runge--Kutta steps) held fixed before the last, differentiable one.
_NEWTON_ITERS = 1


def _vector_field(t, y, args):
    """Right-hand side of eq. 3 inside a swing with constant sgn(v) = s; y = (x, v).

    v' = -((k + k3 x^2)/m) x - s mu g - (b/m + (D/m) s v) v: the cubic stiffness enters as
    k/m + (k3/m) x^2, which is exactly k/m when k3 = 0.
    """
    del t
    s, w2, fric, bm, dm, k3m = args
    x, v = y
    # lax, not jnp operators: the stages are unrolled, and lax keeps tracing cheap.
    mul, add = jax.lax.mul, jax.lax.add
    spring = mul(add(w2, mul(k3m, mul(x, x))), x)
    drag = add(add(spring, mul(s, fric)), mul(add(bm, mul(mul(dm, s), v)), v))
    return v, jax.lax.neg(drag)


def _event_cond(t, y, args, **kwargs):
    """s v: positive inside the swing, zero at its end."""
    del t, kwargs
    return args[0] * y[1]


def _lincomb(weights, ks):
    """sum_i w_i k_i for a list of (x, v) pairs; zero weights skipped."""
    pairs = [(float(w), k) for w, k in zip(weights, ks, strict=False) if w != 0.0]
    out = []
    for i in range(2):
        acc = None
        for w, k in pairs:
            term = jax.lax.mul(k[i], jnp.asarray(w, dtype=k[i].dtype))
            acc = term if acc is None else jax.lax.add(acc, term)
        out.append(acc)
    return tuple(out)


def _stages(tableau, vf, t0, y0, h, *, last: bool):
    """Stage derivatives of an explicit Runge--Kutta step, unrolled in Python.

    With ``last=False`` the final stage is skipped: for the first-same-as-last tableaux used
    here it is f(y1) and not needed for y1.
    """
    ks = [vf(t0, y0)]
    rows = list(zip(tableau.c, tableau.a_lower, strict=True))
    if not last:
        rows = rows[:-1]
    mul, add = jax.lax.mul, jax.lax.add
    for c_i, a_i in rows:
        incr = _lincomb(a_i, ks)
        y_i = (add(y0[0], mul(h, incr[0])), add(y0[1], mul(h, incr[1])))
        k = vf(add(t0, mul(h, jnp.asarray(float(c_i), dtype=h.dtype))), y_i)
        ks.append(k)
    return ks


# The solver below implements diffrax's solver interface (init/step/func) as of diffrax 0.7;
# pyproject.toml pins diffrax < 0.8. Fail at import, with the fix, if the interface moved.
_STEP_ARGS = ("self", "terms", "t0", "t1", "y0", "args", "solver_state", "made_jump")
_FOUND = tuple(inspect.signature(dfx.AbstractSolver.step).parameters)
if _FOUND != _STEP_ARGS:
    raise ImportError(
        f"dampax needs diffrax's solver interface of diffrax 0.7, step{_STEP_ARGS[1:]}; "
        f"diffrax {dfx.__version__} has step{_FOUND[1:]}: install 'diffrax>=0.7.1,<0.8'")


class _UnrolledERK(dfx.AbstractAdaptiveSolver):
    """A diffrax explicit Runge--Kutta method (Dopri8, Dopri5, Tsit5) with unrolled stages.

    Same tableau, error estimate and dense interpolation as the diffrax solver, but the stages
    are written out instead of looped over (diffrax loops, which suits large systems): several
    times faster for this 2-dimensional system, and differentiable in forward and reverse mode
    with any adjoint. The first stage is evaluated afresh every step (no first-same-as-last
    reuse), so the solver has no state.
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
        incr = _lincomb(tableau.b_sol, ks)
        y1 = (y0[0] + h * incr[0], y0[1] + h * incr[1])
        err = _lincomb(tableau.b_error, ks)
        y_error = (h * err[0], h * err[1])
        k = tuple(h * jnp.stack([k_j[i] for k_j in ks]) for i in range(2))
        dense_info = dict(y0=y0, y1=y1, k=k)
        return y1, y_error, dense_info, None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _restep(solver_name, args, t0, y0, t1):
    """One Runge--Kutta step of the named method from (t0, y0) to t1: the dense output."""
    tableau = _SOLVERS[solver_name].tableau
    h = t1 - t0
    ks = _stages(tableau, lambda t, y: _vector_field(t, y, args), t0, y0, h, last=False)
    incr = _lincomb(tableau.b_sol, ks)
    return y0[0] + h * incr[0], y0[1] + h * incr[1]


def _hermite_root(t_a, y_a, t_b, y_b, args, mask):
    """Zero of v on [t_a, t_b] of the cubic Hermite interpolant of (v, v') at both ends.

    A starting guess for Newton's method; v(t_a) and v(t_b) have opposite signs (or
    v(t_b) = 0) where ``mask`` holds.
    """
    h = t_b - t_a
    v_a, v_b = y_a[1], y_b[1]
    d_a = _vector_field(t_a, y_a, args)[1] * h
    d_b = _vector_field(t_b, y_b, args)[1] * h
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


@contextlib.contextmanager
def _without_runtime_checks():
    """Trace diffrax's solve without equinox's run-time checks (host callbacks).

    diffrax checks the sign of dt0 against t0 and t1 with ``eqx.error_if``; with a traced t0,
    t1 that becomes a host callback, and JAX does not write a program with host callbacks to
    its persistent compilation cache, so every process would compile the reference again.
    Here dt0 > 0 and t1 >= t0 by construction (and the solve runs with ``throw=False``), so
    the checks are off while the solve is traced. Equinox reads the setting from this module
    attribute at trace time (equinox < 0.14, as pinned); without it nothing changes.
    """
    import equinox._errors as errors

    before = getattr(errors, "EQX_ON_ERROR", None)
    if before is None:
        yield
        return
    errors.EQX_ON_ERROR = "off"
    try:
        yield
    finally:
        errors.EQX_ON_ERROR = before


def _ode_args(osc: Oscillator, s):
    """Arguments of `_vector_field`: (s, k/m, mu g, b/m, D/m, k3/m)."""
    return (jnp.asarray(s, dtype=float), osc.k / osc.m, osc.mu * osc.g, osc.b / osc.m,
            osc.D / osc.m, osc.k3 / osc.m)


def _derivatives(args, x, v):
    """x and its first four time derivatives inside a swing (eq. 3 with the swing's sign s).

    The cubic stiffness enters through the secant k/m + (k3/m) x^2 (in the acceleration), the
    tangent k/m + 3 (k3/m) x^2 (in the third and fourth derivatives) and the last term
    6 (k3/m) x v^2 of the fourth: all exactly the linear spring's when k3 = 0.
    """
    s, w2, fric, bm, dm, k3m = args
    drag = bm + 2.0 * dm * s * v  # d(b v/m + D s v^2/m)/dv
    w2s = w2 + k3m * (x * x)
    w2t = w2 + 3.0 * k3m * (x * x)
    a = -(w2s * x + s * fric + (bm + dm * s * v) * v)
    jerk = -(w2t * v + drag * a)
    snap = -(w2t * a + drag * jerk + 2.0 * dm * s * a * a + 6.0 * k3m * x * v * v)
    return x, v, a, jerk, snap


# Hermite interpolation with x and its first four derivatives at both knots: the polynomial is
# sum_k c_k th^k (th in [0, 1]); c_0..c_4 are the left knot's Taylor coefficients and c_5..c_9
# = _HERMITE9 @ (r_0..r_4), r_m being what the right knot's m-th derivative (times h^m) asks
# beyond the Taylor part.
_HERMITE9 = ((126.0, -56.0, 10.5, -1.0, 1.0 / 24.0),
             (-420.0, 196.0, -38.5, 23.0 / 6.0, -1.0 / 6.0),
             (540.0, -260.0, 53.0, -5.5, 0.25),
             (-315.0, 155.0, -32.5, 3.5, -1.0 / 6.0),
             (70.0, -35.0, 7.5, -5.0 / 6.0, 1.0 / 24.0))


def _hermite(h, th, y_a, y_b, args):
    """(x, v) at t_a + th h of the Hermite interpolant of a swing's motion on [t_a, t_b].

    The degree-9 polynomial matches x and its first four derivatives (eq. 3 with the swing's
    sign) at both knots, so its error is at most h^10 max|x^(10)| / (10! 4^5): about 1e-11 A0
    for the largest steps that rtol = 1e-10 takes (w0 h = 0.7), 1e-13 for typical ones
    (w0 h = 0.3). The dense output is as accurate as the knots.
    """
    da = _derivatives(args, *y_a)
    db = _derivatives(args, *y_b)
    hk = [1.0, h, h * h, h * h * h, h * h * h * h]
    c = [hk[k] * da[k] / math.factorial(k) for k in range(5)]
    r = [hk[m] * db[m] - sum(math.perm(k, m) * c[k] for k in range(m, 5)) for m in range(5)]
    c += [sum(w * r_m for w, r_m in zip(row, r, strict=True)) for row in _HERMITE9]
    x, dx = c[9], 9.0 * c[9]
    for k in range(8, -1, -1):
        x = c[k] + th * x
        if k > 0:
            dx = k * c[k] + th * dx
    h_safe = jnp.where(h > 0.0, h, 1.0)
    return x, jnp.where(h > 0.0, dx / h_safe, y_a[1])


def _knots(sol: ReferenceSolution):
    """The stored knots of one (unbatched) trajectory as one table, for the dense output.

    Returns K, the columns (t, x, v, s) of the knots in time order (slot after slot; t = inf
    for the padding after each slot's knots), gathered a column at a time. (Knots as columns:
    as rows, the stack interleaved four arrays element by element, a copy that cost as much as
    the dense output's arithmetic.)
    """
    S = jnp.broadcast_to(sol.seg_s[:, None], sol.seg_ts.shape)
    return jnp.stack([sol.seg_ts, sol.seg_xs, sol.seg_vs, S]).reshape(4, -1)


def _search_left(K, t):
    """Flat index of the last knot <= t for every t (a binary search per time)."""
    T = K[0]
    real = jnp.isfinite(T)
    # padding takes the previous knot's time and index: non-decreasing, searchable
    filled = jax.lax.associative_scan(jnp.maximum, jnp.where(real, T, -jnp.inf))
    last = jax.lax.associative_scan(jnp.maximum, jnp.where(real, jnp.arange(T.shape[0]), 0))
    n = T.shape[0]
    return last[jnp.clip(jnp.searchsorted(filled, t, side="right") - 1, 0, n - 1)]


def _state_at(sol: ReferenceSolution, K, t, left):
    """(x, v) of one (unbatched) trajectory at a scalar time t from its knot table K, given
    the flat index ``left`` of the last knot at or before t (`_search_left`, `_grid_left`)."""
    n, width = K.shape[1], sol.seg_ts.shape[-1]
    before = t < 0.0
    resting = sol.halted & (t >= sol.halt_time)
    beyond = (~resting) & (t > sol.t_cover)
    moving = ~(before | resting | beyond)
    t_safe = jnp.where(moving, t, 0.0)
    left = jnp.clip(left, 0, n - 1)
    # the interval's right knot: the next entry when it is a knot of the same slot; at a
    # slot's last knot (t = t_end) the knot itself
    nxt = jnp.minimum(left + 1, n - 1)
    row_a, row_b = K[:, left], K[:, nxt]
    same = (nxt % width != 0) & jnp.isfinite(row_b[0]) & (nxt != left)
    row_b = jnp.where(same, row_b, row_a)
    ok = jnp.isfinite(row_a[0])
    t_a = jnp.where(ok, row_a[0], t_safe)
    h = jnp.where(same, row_b[0] - t_a, 0.0)
    th = jnp.where(h > 0.0, (t_safe - t_a) / jnp.where(h > 0.0, h, 1.0), 0.0)
    y_a = (jnp.where(ok, row_a[1], 0.0), jnp.where(ok, row_a[2], 0.0))
    y_b = (jnp.where(ok, row_b[1], 0.0), jnp.where(ok, row_b[2], 0.0))
    args = (row_a[3],) + _ode_args(sol.osc, 0.0)[1:]
    x, v = _hermite(h, th, y_a, y_b, args)
    x = jnp.where(moving, x, jnp.where(resting, sol.halt_position, jnp.nan))
    v = jnp.where(moving, v, jnp.where(resting, 0.0, jnp.nan))
    # input out of the domain: nothing was integrated (see _solve_single)
    bad = _bad_input(sol.result)
    return jnp.where(bad, jnp.nan, x), jnp.where(bad, jnp.nan, v)


def _bad_input(result):
    """True where the reference's result says its input is out of the domain."""
    return ((result == RESULTS.invalid_constants) | (result == RESULTS.nonfinite_state)
            | (result == RESULTS.invalid_t_end))


def _grid_left(K, start, step, n: int):
    """For the grid t_i = start + i step (i < n): the flat index of the last knot <= t_i.

    One pass over the knots (each goes to the first grid point at or after it, a scatter-max)
    and a running maximum over the grid: O(knots + n), no search per sample. A knot within
    rounding of a grid point may land on either side of it; the interpolant is continuous
    there, so that changes nothing.
    """
    T = K[0]
    pos = jnp.ceil((T - start) / step)
    pos = jnp.where(jnp.isfinite(T) & (pos < n), jnp.maximum(pos, 0.0), n).astype(int)
    first = jnp.full((n,), -1).at[pos].max(jnp.arange(T.shape[0]), mode="drop")
    return jax.lax.associative_scan(jnp.maximum, first)


def _batched(single, sol, *args):
    """``single(one_solution, *args)`` over the batch shape of ``sol`` (vmapped per axis)."""
    fn = single
    for _ in sol.batch_shape:
        fn = jax.vmap(fn, in_axes=(0,) + (None,) * len(args))
    return fn(sol, *args)


@jax.jit
def _evaluate(sol: ReferenceSolution, t):
    """(x, v) at the times t (any shape), for a solution with any batch shape."""

    def single(s, tt):
        K = _knots(s)
        u = tt.reshape(-1)
        t_safe = jnp.where(jnp.isfinite(u), u, 0.0)
        x, v = jax.vmap(lambda a, i: _state_at(s, K, a, i))(u, _search_left(K, t_safe))
        return x.reshape(tt.shape), v.reshape(tt.shape)

    return _batched(single, sol, t)


@jax.jit
def _evaluate_grid(sol: ReferenceSolution, t, start, step):
    """(x, v) at the sorted times t (1-D) of a uniform grid t_i ~ start + i step, for a solution
    with any batch shape: the knots are merged into the grid in one pass (`_grid_left`)."""

    def single(s, t, start, step):
        K = _knots(s)
        left = _grid_left(K, start, step, t.shape[0])
        return jax.vmap(lambda a, i: _state_at(s, K, a, i))(t, left)

    return _batched(single, sol, t, start, step)


def _uniform(t) -> tuple[float, float] | None:
    """(start, step) when t is a concrete, 1-D, increasing uniform grid of >= 3 points."""
    if not is_concrete(t) or jnp.ndim(t) != 1 or jnp.shape(t)[0] < 3:
        return None
    a = np.asarray(t, dtype=float)
    d = np.diff(a)
    step = (a[-1] - a[0]) / (a.size - 1)
    if not (np.isfinite(step) and step > 0.0 and np.all(np.abs(d - step) <= 1e-9 * step)):
        return None
    return float(a[0]), float(step)


class ReferenceSolution(AbstractSolution):
    """Numerical reference solution of eq. 3 (see `solve_reference`).

    Attributes:
        osc: the Oscillator that was solved.
        x0, v0: the initial state.
        t_end: end of the requested interval [0, t_end].
        halted: True when the block stuck for good within [0, t_end].
        halt_time: time of the final stop (0 for a start at rest inside the band); inf when the
            block does not stop within [0, t_end] (always for mu = 0; for mu > 0 `halted` is
            then False and the block was still moving at t_end).
        halt_position: position of the final stop; NaN where it does not stop.
        result: ``RESULTS.successful``; ``RESULTS.max_swings_reached`` when the budget
            (max_swings x max_steps_per_swing) ran out, or ``RESULTS.solver_failed`` when the
            ODE solver failed, before t_end or the halt: the solution then covers only
            [0, t_cover]. ``valid`` is ``result == RESULTS.successful``.
        n_swings: number of swings (intervals of motion with constant sgn(v)).
        swing_times: end times of the swings, i.e. the turning points (v = 0, t > 0), the rest
            point last when the block halts. Length max_swings, NaN-padded.
        turning_x: positions at those turning points, NaN-padded.
        t_cover: end of the integrated interval (t_end when complete; inf once halted).
        seg_t0, seg_n, seg_s, seg_ts, seg_xs, seg_vs: per scan slot its start time (inf if
            unused), the number of knots, sgn(v), and the knots: the stored step times and
            states, the turning point last when the slot ends at one (inf-padded); the dense
            output interpolates between them.

    Array attributes may carry leading batch axes (a batched solve); the methods then evaluate
    every trajectory.
    """

    osc: Oscillator
    x0: Array
    v0: Array
    t_end: Array
    halted: Array
    halt_time: Array
    halt_position: Array
    result: RESULTS
    n_swings: Array
    swing_times: Array
    turning_x: Array
    t_cover: Array
    seg_t0: Array
    seg_n: Array
    seg_s: Array
    seg_ts: Array
    seg_xs: Array
    seg_vs: Array
    solver_name: str = eqx.field(static=True, default="dopri8")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape (() for a single trajectory)."""
        return jnp.shape(self.halt_time)

    def state(self, t, *, grid=None) -> tuple[Array, Array]:
        """Position and velocity at time(s) t, evaluated together.

        The dense output interpolates between the stored solver steps (Hermite, degree 9,
        as accurate as the steps). For sorted times on a uniform grid the steps are merged
        into the grid in one pass instead of a binary search per time: detected for a
        concrete 1-D t, or stated with ``grid`` (under jit).

        Arguments:
            t: scalar or array of times. Before 0, or after the integrated interval while
                the block still moves, the result is NaN; after the halt it is the rest
                position.
            grid: optional (start, step) such that t[i] = start + i step (1-D t), e.g. under
                jit where t cannot be inspected. Values are the same either way.

        Returns:
            (x(t), v(t)), each shaped like t (batch shape in front for a batched solution).
        """
        t = jnp.asarray(t, dtype=float)
        if grid is None:
            grid = _uniform(t)
        if grid is None:
            return _evaluate(self, t)
        if t.ndim != 1:
            raise ValueError(f"grid needs 1-D times, got t of shape {t.shape}")
        return _evaluate_grid(self, t, *(jnp.asarray(g, dtype=float) for g in grid))

    def x(self, t) -> Array:
        """Position at time(s) t (see `state`).

        Arguments:
            t: scalar or array of times (NaN before 0 and beyond the integrated interval, the
                rest position after the halt).

        Returns:
            x(t), shaped like t (batch shape in front for a batched solution).
        """
        return self.state(t)[0]

    def v(self, t) -> Array:
        """Velocity at time(s) t (see `state`).

        Arguments:
            t: scalar or array of times (see `x`).

        Returns:
            v(t), shaped like t (batch shape in front for a batched solution).
        """
        return self.state(t)[1]

    def energy(self, t, *, grid=None) -> Array:
        """Mechanical energy k x^2/2 + m v^2/2 at time(s) t (eq. 4).

        Arguments:
            t: scalar or array of times (see `x`).
            grid: optional (start, step) of a uniform grid t (see `state`).

        Returns:
            E(t), shaped like t (batch shape in front for a batched solution).
        """
        return self.energy_of(*self.state(t, grid=grid))

    def _x_energy(self, t, grid=None):
        x, v = self.state(t, grid=grid)
        return x, self.energy_of(x, v)

    def energy_of(self, x, v) -> Array:
        """Energy (eq. 4) of states x, v shaped like the output of `state`."""
        shape = self.batch_shape + (1,) * (jnp.ndim(x) - len(self.batch_shape))
        osc = jax.tree_util.tree_map(
            lambda a: jnp.reshape(jnp.broadcast_to(a, self.batch_shape), shape), self.osc)
        return osc.energy(x, v)

    def turning_points(self, n: int) -> tuple[Array, Array]:
        """The first n turning points (t_n, x_n): v = 0 at t_n > 0, the rest point last.

        A start at rest is not counted. Entries after the halt (or beyond what was integrated)
        are NaN.

        Arguments:
            n: number of turning points (static Python int).

        Returns:
            (t_n, x_n), each of shape (n,) (batch shape in front for a batched solution).
        """
        n = check_count("n", n)
        length = self.swing_times.shape[-1]

        def pick(a):
            if n <= length:
                return a[..., :n]
            pad = jnp.full(a.shape[:-1] + (n - length,), jnp.nan, dtype=a.dtype)
            return jnp.concatenate([a, pad], axis=-1)

        return pick(self.swing_times), pick(self.turning_x)


def _solve_single(osc, x0, v0, t_end, *, rtol, atol, max_swings, max_steps_per_swing,
                  solver_name, root_finder, adjoint):
    """Unbatched core of `solve_reference` (all inputs scalars)."""
    # out of the domain (non-finite or non-positive m, k, g, negative mu, b, D, a non-finite
    # state, t_end not > 0): integrate a harmless stand-in (at rest, one step) and flag it
    checks = (*input_checks(osc, x0, v0),
              (~(jnp.isfinite(t_end) & (t_end > 0.0)), RESULTS.invalid_t_end))
    ok_in = ~functools.reduce(jnp.logical_or, [failed for failed, _ in checks])
    osc_in, x0_in, v0_in, t_end_in = osc, x0, v0, t_end
    osc = jax.tree_util.tree_map(lambda a: jnp.where(ok_in, a, 1.0), osc)
    x0, v0, t_end = (jnp.where(ok_in, x0, 0.0), jnp.where(ok_in, v0, 0.0),
                     jnp.where(ok_in, t_end, 1.0))
    solver = _UnrolledERK(solver_name)
    w0 = osc.omega0
    zero = jnp.zeros((), dtype=float)
    term = dfx.ODETerm(_vector_field)
    if root_finder == "optx-newton":
        rf = optx.Newton(rtol=1e-10, atol=1e-12)
    elif root_finder == "optx-bisection":
        rf = optx.Bisection(rtol=1e-10, atol=1e-12, expand_if_necessary=True)
    else:
        rf = None
    event = dfx.Event(_event_cond, root_finder=rf, direction=False)
    # the fastest the motion can get: with a hardening spring (k3 > 0) the tangent stiffness
    # k + 3 k3 x^2 is at most k + 6 k3 E0/k (|x|^2 <= 2 E0/k), so w_hi = w0 sqrt(1 + 6 k3 E0/k^2)
    # bounds the local frequency (exactly w0 when k3 <= 0)
    k3_hard = jnp.maximum(osc.k3, 0.0)
    w_hi = w0 * jnp.sqrt(1.0 + 6.0 * k3_hard * osc.energy(x0, v0) / (osc.k * osc.k))
    controller = dfx.PIDController(rtol=rtol, atol=atol, dtmax=_DTMAX_W0 / w_hi)
    adj = {"recursive": dfx.RecursiveCheckpointAdjoint(), "forward": dfx.ForwardMode(),
           "direct": dfx.DirectAdjoint()}[adjoint]
    saveat = dfx.SaveAt(t0=True, steps=True)

    rest0 = (v0 == 0.0) & osc.sticks(x0)
    s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))
    carry0 = dict(
        t=zero, x=x0, v=v0, s=s0, active=(~rest0) & (t_end > 0.0), halted=rest0,
        t_halt=zero, x_halt=x0, failed=jnp.array(False), n_swings=jnp.where(rest0, 0, 1),
    )

    def body(c, _):
        active = c["active"]
        t0 = c["t"]
        args = _ode_args(osc, c["s"])
        with _without_runtime_checks():
            sol = dfx.diffeqsolve(
                term, solver, t0, jnp.where(active, t_end, t0), _DT0_W0 / w_hi,
                (c["x"], c["v"]), args, saveat=saveat, stepsize_controller=controller,
                adjoint=adj, event=event, max_steps=max_steps_per_swing, throw=False,
            )
        fired = active & (sol.result == dfx.RESULTS.event_occurred)
        capped = active & (sol.result == dfx.RESULTS.max_steps_reached)
        failed = active & ~(fired | capped | (sol.result == dfx.RESULTS.successful))

        # Stored points: t0 and every accepted step end. After an event the last one is past
        # the velocity zero (the crossing step's end or, with an optx root finder, diffrax's
        # interpolated event state): it is dropped, the turning point replaces it.
        ts, (xs, vs) = sol.ts, sol.ys
        n_fin = jnp.sum(jnp.isfinite(ts))
        last = jnp.maximum(n_fin - 1, 0)
        n_seg = jnp.maximum(jnp.where(fired, n_fin - 1, n_fin), 1)
        keep = jnp.arange(ts.shape[0]) < n_seg
        t_p = ts[n_seg - 1]
        y_p = (xs[n_seg - 1], vs[n_seg - 1])

        # Turning point: Newton on the re-taken step from the last stored point. The guess and
        # all but the last Newton step are held fixed; the last one carries the derivative.
        if rf is None:
            t_guess = _hermite_root(t_p, y_p, ts[last], (xs[last], vs[last]), args, fired)
        else:
            t_guess = jnp.where(fired, ts[last], t_p)

        def newton(t_g):
            y = _restep(solver_name, args, t_p, y_p, t_g)
            a = _vector_field(t_g, y, args)[1]
            ok = fired & (a != 0.0)
            return y, jnp.where(ok, -y[1] / jnp.where(ok, a, 1.0), 0.0)

        t_guess = jax.lax.stop_gradient(t_guess)
        for _ in range(_NEWTON_ITERS):
            t_guess = jax.lax.stop_gradient(t_guess + newton(t_guess)[1])
        y_new, dt = newton(t_guess)
        t_sw = t_guess + dt
        x_sw = y_new[0] + y_new[1] * dt

        stick = fired & osc.sticks(x_sw)  # |k x + k3 x^3| <= mu m g
        reverse = fired & ~stick
        new = dict(
            t=jnp.where(active, jnp.where(fired, t_sw, t_p), t0),
            x=jnp.where(active, jnp.where(fired, x_sw, y_p[0]), c["x"]),
            v=jnp.where(active, jnp.where(fired, 0.0, y_p[1]), c["v"]),
            s=jnp.where(reverse, -jnp.sign(x_sw), c["s"]),
            active=active & (reverse | capped),
            halted=c["halted"] | stick,
            t_halt=jnp.where(stick, t_sw, c["t_halt"]),
            x_halt=jnp.where(stick, x_sw, c["x_halt"]),
            failed=c["failed"] | failed,
            n_swings=c["n_swings"] + jnp.where(reverse, 1, 0),
        )
        # the turning point is the swing's last knot (its end point for the dense output)
        end = fired & (jnp.arange(ts.shape[0]) == n_seg)
        out = dict(
            seg_t0=jnp.where(active, t0, jnp.inf),
            seg_n=jnp.where(active, n_seg + fired, 0),
            seg_s=c["s"],
            seg_ts=jnp.where(keep, ts, jnp.where(end, t_sw, jnp.inf)),
            seg_xs=jnp.where(keep, xs, jnp.where(end, x_sw, jnp.inf)),
            seg_vs=jnp.where(keep, vs, jnp.where(end, 0.0, jnp.inf)),
            fired=fired,
            t_sw=jnp.where(fired, t_sw, 0.0),
            x_sw=jnp.where(fired, x_sw, 0.0),
        )
        return new, out

    out_shape = jax.eval_shape(body, carry0, None)[1]

    def skip(c, _):
        # Every element of the (vmapped) batch is done: no solve. What an inactive slot of
        # `body` would give.
        out = {key: jnp.full(out_shape[key].shape, jnp.inf, out_shape[key].dtype)
               for key in ("seg_t0", "seg_ts", "seg_xs", "seg_vs")}
        out.update(seg_n=jnp.zeros((), out_shape["seg_n"].dtype), seg_s=c["s"],
                   fired=jnp.zeros((), dtype=bool), t_sw=zero, x_sw=zero)
        return c, out

    def slot(c, _):
        # unvmap_any keeps the predicate unbatched under vmap (as diffrax does), so this stays
        # a real branch: slots after every element has finished cost nothing.
        return jax.lax.cond(eqxi.unvmap_any(c["active"]), body, skip, c, None)

    final, out = jax.lax.scan(slot, carry0, None, length=max_swings)

    result = first_failure(*checks, (final["failed"], RESULTS.solver_failed),
                           (final["active"], RESULTS.max_swings_reached))
    halted = final["halted"] & ok_in
    slot = jnp.where(out["fired"], jnp.cumsum(out["fired"]) - 1, max_swings)
    nan_row = jnp.full((max_swings,), jnp.nan)
    return ReferenceSolution(
        osc=osc_in, x0=x0_in, v0=v0_in, t_end=t_end_in, halted=halted,
        halt_time=jnp.where(halted, final["t_halt"], jnp.where(ok_in, jnp.inf, jnp.nan)),
        halt_position=jnp.where(halted, final["x_halt"], jnp.nan),
        result=result, n_swings=final["n_swings"],
        swing_times=nan_row.at[slot].set(out["t_sw"], mode="drop"),
        turning_x=nan_row.at[slot].set(out["x_sw"], mode="drop"),
        t_cover=jnp.where(halted, jnp.inf, final["t"]),
        seg_t0=out["seg_t0"], seg_n=out["seg_n"], seg_s=out["seg_s"], seg_ts=out["seg_ts"],
        seg_xs=out["seg_xs"], seg_vs=out["seg_vs"], solver_name=solver_name,
    )


def _solve_batched(osc, x0, v0, t_end, **kw):
    """`_solve_single` over the broadcast shape of all inputs (vmapped when not scalar)."""
    leaves = jax.tree_util.tree_leaves((osc, x0, v0, t_end))
    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in leaves))
    if shape == ():
        return _solve_single(osc, x0, v0, t_end, **kw)
    size = math.prod(shape)

    def flat(a):
        return jnp.broadcast_to(a, shape).reshape(size)

    args = jax.tree_util.tree_map(flat, (osc, x0, v0, t_end))
    sol = jax.vmap(lambda o, a, b, c: _solve_single(o, a, b, c, **kw))(*args)
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), sol)


_solve_jit = jax.jit(_solve_batched, static_argnames=(
    "rtol", "atol", "max_swings", "max_steps_per_swing", "solver_name", "root_finder",
    "adjoint"))


def solve_reference(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                    atol: float = 1e-12, max_swings: int = 64, max_steps_per_swing: int = 64,
                    solver: str = "dopri8", root_finder: str = "newton",
                    adjoint: str = "recursive") -> ReferenceSolution:
    """Integrate eq. 3 swing by swing with diffrax: the reference for the analytic models.

    Arguments:
        osc: the Oscillator. Its fields, x0, v0 and t_end broadcast together; a non-scalar
            shape solves every element (vmapped) and gives a batched solution.
        x0: initial position [m].
        v0: initial velocity [m/s].
        t_end: end of the time interval [s]; default 25 undamped periods (50 pi / w0), about
            50 swings. May be traced.
        rtol, atol: tolerances of the PID step-size controller (static): 0 < rtol < 1,
            atol >= 0, both finite.
        max_swings: scan slots (static). A slot holds one swing, or the part of a swing that
            fits in `max_steps_per_swing` steps (the swing then continues in the next slot).
        max_steps_per_swing: solver steps (accepted and rejected) per slot (static). Every
            accepted step is stored for the dense output, so memory grows with
            max_swings * max_steps_per_swing; a swing takes about 10 steps at rtol = 1e-10.
        solver: "dopri8" (default), "dopri5" or "tsit5" (diffrax's tableaux, unrolled).
        root_finder: how the velocity zero is found. "newton" (default): the event stops the
            solve after the crossing step, then Newton's method on re-taken Runge--Kutta steps
            (plain jnp: works under jit, vmap, grad and shard_map). "optx-newton" /
            "optx-bisection": diffrax root-finds the event on its dense interpolation with
            optimistix first (Bisection being the one that works under shard_map), followed
            by the same Newton step.
        adjoint: "recursive" (default; reverse mode, jax.grad), "forward" (jax.jacfwd) or
            "direct" (both; slower). No single diffrax adjoint serves both modes well.

    Returns:
        A `ReferenceSolution`. Called eagerly it raises ValueError when x0, v0 or t_end is not
        finite, t_end is not positive, or the budget ran out before t_end or the halt (naming
        max_swings and max_steps_per_swing); under jit it returns valid = False instead.
    """
    if solver not in _SOLVERS:
        raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {solver!r}")
    if root_finder not in _ROOT_FINDERS:
        raise ValueError(f"root_finder must be one of {_ROOT_FINDERS}, got {root_finder!r}")
    if adjoint not in _ADJOINTS:
        raise ValueError(f"adjoint must be one of {_ADJOINTS}, got {adjoint!r}")
    if jnp.asarray(0.0, dtype=float).dtype != jnp.float64:
        raise ValueError("solve_reference needs float64: call "
                         "jax.config.update('jax_enable_x64', True) first")
    rtol = check_real("rtol", rtol, low=0.0, low_open=True, high=1.0, high_open=True,
                      hint=" (the relative tolerance of the step-size controller)")
    atol = check_real("atol", atol, low=0.0,
                      hint=" (the absolute tolerance of the step-size controller)")
    if int(max_swings) < 1 or int(max_steps_per_swing) < 2:
        raise ValueError("max_swings must be >= 1 and max_steps_per_swing >= 2, got "
                         f"{max_swings} and {max_steps_per_swing}")
    check_finite("x0", x0)
    check_finite("v0", v0)
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    if t_end is None:
        t_end = _DEFAULT_PERIODS * 2.0 * math.pi / osc.omega0
    else:
        check_finite("t_end", t_end)
        if is_concrete(t_end) and np.any(np.asarray(t_end, dtype=float) <= 0):
            raise ValueError(f"t_end must be > 0, got {t_end!r}")
        t_end = jnp.asarray(t_end, dtype=float)
    sol = _solve_jit(osc, x0, v0, t_end, rtol=rtol, atol=atol,
                     max_swings=int(max_swings), max_steps_per_swing=int(max_steps_per_swing),
                     solver_name=solver, root_finder=root_finder, adjoint=adjoint)
    if is_concrete(sol.result._value) and sol.message:
        budget = bool(np.any(np.asarray(sol.result == RESULTS.max_swings_reached)))
        raise ValueError(sol.message + (f" (now max_swings = {max_swings}, max_steps_per_swing"
                                        f" = {max_steps_per_swing})" if budget else ""))
    return sol
