"""`ReferenceSolution`: the reference's result and its dense output (x, v, energy at any t)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._models._solution import RESULTS, AbstractSolution
from .._oscillator import Oscillator, check_count, is_concrete
from ._sampling import sample

Array = jax.Array


def _bad_input(result):
    """True where the reference's result says its input is out of the domain."""
    return ((result == RESULTS.invalid_constants) | (result == RESULTS.nonfinite_state)
            | (result == RESULTS.invalid_t_end) | (result == RESULTS.unconfined))


def _batched(single, sol, *args):
    """``single(one_solution, *args)`` over the batch shape of ``sol`` (vmapped per axis)."""
    fn = single
    for _ in sol.batch_shape:
        fn = jax.vmap(fn, in_axes=(0,) + (None,) * len(args))
    return fn(sol, *args)


def mask_samples(sol, t, x, v):
    """The dense output's values where the motion was integrated; the rest position after the
    halt; NaN before 0, beyond the integrated interval, and for input out of the domain."""
    resting = sol.halted & (t >= sol.halt_time)
    moving = (t >= 0.0) & ~resting & (t <= sol.t_cover) & jnp.isfinite(t)
    x = jnp.where(moving, x, jnp.where(resting, sol.halt_position, jnp.nan))
    v = jnp.where(moving, v, jnp.where(resting, 0.0, jnp.nan))
    bad = _bad_input(sol.result)
    return jnp.where(bad, jnp.nan, x), jnp.where(bad, jnp.nan, v)


def from_engine(out, osc, x0, v0, t_end):
    """The `ReferenceSolution` (no samples) of an engine's output dict (`_engine.integrate`'s;
    elementwise, so also of a batch of them)."""
    ok_in = out["ok_in"]
    halted = out["halted"] & ok_in
    return ReferenceSolution(
        osc=osc, x0=x0, v0=v0, t_end=t_end, halted=halted,
        halt_time=jnp.where(halted, out["t_halt"], jnp.where(ok_in, jnp.inf, jnp.nan)),
        halt_position=jnp.where(halted, out["x_halt"], jnp.nan),
        result=out["result"], n_swings=out["n_swings"],
        swing_times=out["turns"][..., 0], turning_x=out["turns"][..., 1],
        t_cover=jnp.where(halted, jnp.inf, out["t"]), rows=out["rows"],
        n_rows=out["n_rows"],
    )


def with_samples(sol, ts=None, xs=None, vs=None):
    """``sol`` with its samples replaced: sample times ts and x, v there (None: none)."""
    return ReferenceSolution(**{f: getattr(sol, f) for f in FIELDS}, ts=ts, xs=xs, vs=vs)


def sample_single(sol, t, grid=None):
    """(x, v) of one (unbatched) trajectory at the times t (any shape)."""
    u = t.reshape(-1)
    x, v = sample(sol.rows, sol.n_rows, u, grid)
    x, v = mask_samples(sol, u, x, v)
    return x.reshape(t.shape), v.reshape(t.shape)


@jax.jit
def _evaluate(sol, t, grid):
    """(x, v) at the times t (any shape), for a solution with any batch shape."""
    return _batched(sample_single, sol, t, grid)


def uniform(t) -> tuple[float, float] | None:
    """(start, step) when t is a concrete, 1-D, increasing uniform grid of >= 3 points."""
    if not is_concrete(t) or jnp.ndim(t) != 1 or jnp.shape(t)[0] < 3:
        return None
    a = np.asarray(t, dtype=float)
    d = np.diff(a)
    step = (a[-1] - a[0]) / (a.size - 1)
    if not (np.isfinite(step) and step > 0.0 and np.all(np.abs(d - step) <= 1e-9 * step)):
        return None
    return float(a[0]), float(step)


# the fields of a solution without the samples of `solve_reference(ts=...)`
FIELDS = ("osc", "x0", "v0", "t_end", "halted", "halt_time", "halt_position", "result",
          "n_swings", "swing_times", "turning_x", "t_cover", "rows", "n_rows")


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
            (max_swings, or the table of steps) ran out, or ``RESULTS.solver_failed`` when the
            integration failed, before t_end or the halt: the solution then covers only
            [0, t_cover]. ``valid`` is ``result == RESULTS.successful``.
        n_swings: number of swings (intervals of motion with constant sgn(v)).
        swing_times: end times of the swings, i.e. the turning points (v = 0, t > 0), the rest
            point last when the block halts. Length max_swings, NaN-padded.
        turning_x: positions at those turning points, NaN-padded.
        t_cover: end of the integrated interval (t_end when complete; inf once halted).
        rows, n_rows: the stored steps, one per accepted step in time order (inf-padded),
            each as its start, 1/h and the ten coefficients of its interpolating polynomial
            (`_sampling.hermite_row`), and how many there are.
        ts, xs, vs: the sample times given to `solve_reference(ts=...)` and x, v there
            (None without ts).

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
    rows: Array
    n_rows: Array
    ts: Array | None = None
    xs: Array | None = None
    vs: Array | None = None

    @property
    def model(self) -> str:
        """"reference" (the registry name)."""
        return "reference"

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape (() for a single trajectory)."""
        return jnp.shape(self.halt_time)

    def _stored(self, t):
        """True, False or a traced boolean: whether t is the ``ts`` of the solve (the same
        array, or the same values; under jit the values are compared at run time)."""
        if self.ts is None or jnp.shape(t) != self.ts.shape:
            return False
        if t is self.ts:
            return True
        if is_concrete(t) and is_concrete(self.ts):
            return bool(np.array_equal(np.asarray(t, dtype=float), np.asarray(self.ts)))
        return jnp.all(jnp.asarray(t, dtype=float) == self.ts)

    def state(self, t, *, grid=None) -> tuple[Array, Array]:
        """Position and velocity at time(s) t, evaluated together.

        The dense output evaluates the polynomial of the stored step around each t (Hermite,
        degree 9, as accurate as the steps). Sorted times are merged with the steps in one
        pass, others found by a binary search; times given to the solve as ``ts`` return the
        values filled there.

        Arguments:
            t: scalar or array of times. Before 0, or after the integrated interval while
                the block still moves, the result is NaN; after the halt it is the rest
                position.
            grid: optional (start, step) such that t[i] = start + i step (1-D t), e.g. under
                jit where t cannot be inspected. Values are the same either way.

        Returns:
            (x(t), v(t)), each shaped like t (batch shape in front for a batched solution).
        """
        stored = self._stored(t)
        if stored is True:
            return self.xs, self.vs
        t = jnp.asarray(t, dtype=float)
        if grid is None:
            grid = uniform(t)
        if grid is not None:
            if t.ndim != 1:
                raise ValueError(f"grid needs 1-D times, got t of shape {t.shape}")
            grid = tuple(jnp.asarray(g, dtype=float) for g in grid)
        bare = with_samples(self)  # no samples
        if stored is False:
            return _evaluate(bare, t, grid)
        return jax.lax.cond(stored, lambda: (self.xs, self.vs),
                            lambda: _evaluate(bare, t, grid))

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

