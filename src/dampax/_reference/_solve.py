"""`solve_reference`: eq. 3 integrated swing by swing with exact stick-slip (DESIGN.md 2.6)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._models._solution import RESULTS
from .._oscillator import Oscillator, check_finite, check_real, is_concrete
from ._engine import _KINDS, integrate
from ._solution import FIELDS, ReferenceSolution, sample_single

# Default t_end in undamped periods: 25 periods are about 50 swings.
DEFAULT_PERIODS = 25.0
# max_swings when neither it nor a concrete t_end and oscillator are given (under jit).
DEFAULT_SWINGS = 64
# The budget sizes are rounded up to these steps (x 2^n), so that nearby windows share one
# compiled program.
_QUANTA = (16, 24, 32, 48)


def _round_up(n: int) -> int:
    """n rounded up to 16, 24, 32, 48, 64, 96, ... (at most 1.5x)."""
    scale = 1
    while True:
        for q in _QUANTA:
            if n <= q * scale:
                return q * scale
        scale *= 4


def rows_per_swing(rtol: float) -> int:
    """Table rows per swing budgeted at a tolerance: DOP853 takes about 5 steps per swing at
    rtol = 1e-10 and the count grows as rtol^(-1/8); the budget is twice that, plus the
    turning point's row."""
    steps = 5.0 * (1e-10 / rtol) ** 0.125
    return max(8, math.ceil(2.0 * steps) + 2)


def default_swings(osc, x0, v0, t_end) -> int:
    """max_swings for a concrete window: the swings of the fastest motion in [0, t_end]
    (w_hi t_end / pi, w_hi the frequency bound of `_engine`) with a margin, rounded up."""
    w0 = np.sqrt(np.asarray(osc.k, dtype=float) / np.asarray(osc.m, dtype=float))
    k3 = np.maximum(np.asarray(osc.k3, dtype=float), 0.0)
    k = np.asarray(osc.k, dtype=float)
    energy = np.asarray(osc.energy(jnp.asarray(x0), jnp.asarray(v0)), dtype=float)
    w_hi = w0 * np.sqrt(1.0 + 6.0 * k3 * energy / (k * k))
    swings = np.asarray(t_end, dtype=float) * w_hi / math.pi
    swings = np.where(np.isfinite(swings), swings, 0.0)
    return _round_up(int(math.ceil(1.1 * float(np.max(swings)))) + 4)


def _solve_single(osc, x0, v0, t_end, ts, *, rtol, atol, max_swings, rows, adjoint):
    """Unbatched core of `solve_reference` (all inputs scalars)."""
    out = integrate(osc, x0, v0, t_end, rtol=rtol, atol=atol, max_swings=max_swings,
                    rows=rows, adjoint=adjoint)
    ok_in = out["ok_in"]
    halted = out["halted"] & ok_in
    sol = ReferenceSolution(
        osc=osc, x0=x0, v0=v0, t_end=t_end, halted=halted,
        halt_time=jnp.where(halted, out["t_halt"], jnp.where(ok_in, jnp.inf, jnp.nan)),
        halt_position=jnp.where(halted, out["x_halt"], jnp.nan),
        result=out["result"], n_swings=out["n_swings"],
        swing_times=out["turns"][:, 0], turning_x=out["turns"][:, 1],
        t_cover=jnp.where(halted, jnp.inf, out["t"]), rows=out["rows"],
        n_rows=out["n_rows"],
    )
    if ts is None:
        return sol
    xs, vs = sample_single(sol, ts)
    return ReferenceSolution(**{**{f: getattr(sol, f) for f in FIELDS}, "ts": ts, "xs": xs,
                                "vs": vs})


def _solve_batched(osc, x0, v0, t_end, ts, **kw):
    """`_solve_single` over the broadcast shape of all inputs (vmapped when not scalar)."""
    leaves = jax.tree_util.tree_leaves((osc, x0, v0, t_end))
    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in leaves))
    if shape == ():
        return _solve_single(osc, x0, v0, t_end, ts, **kw)
    size = math.prod(shape)

    def flat(a):
        return jnp.broadcast_to(a, shape).reshape(size)

    args = jax.tree_util.tree_map(flat, (osc, x0, v0, t_end))
    sol = jax.vmap(lambda o, a, b, c: _solve_single(o, a, b, c, ts, **kw))(*args)
    out = jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), sol)
    if ts is not None:  # the sample times are shared, not batched
        out = ReferenceSolution(**{**{f: getattr(out, f) for f in FIELDS}, "ts": ts,
                                   "xs": out.xs, "vs": out.vs})
    return out


_solve_jit = jax.jit(_solve_batched,
                     static_argnames=("rtol", "atol", "max_swings", "rows", "adjoint"))


def solve_reference(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                    atol: float = 1e-12, max_swings: int | None = None,
                    max_steps_per_swing: int | None = None, ts=None,
                    adjoint: str = "recursive", solver: str = "dop853") -> ReferenceSolution:
    """Integrate eq. 3 swing by swing with exact stick-slip: the reference for the analytic
    models (DESIGN.md section 2.6).

    Inside a swing sgn(v) is constant and DOP853 integrates the smooth motion; the swing ends
    at the velocity zero (located by Newton's method on re-taken steps), where the block
    sticks for good if |k x + k3 x^3| <= mu_s m g (``Oscillator.mu_s``; mu when None), else
    reverses and slides with mu. sgn(v) is never smoothed.

    Arguments:
        osc: the Oscillator. Its fields, x0, v0 and t_end broadcast together; a non-scalar
            shape solves every element (vmapped) and gives a batched solution.
        x0: initial position [m].
        v0: initial velocity [m/s].
        t_end: end of the time interval [s]; default 25 undamped periods (50 pi / w0), about
            50 swings. May be traced.
        rtol, atol: tolerances of the step-size control (static): 0 < rtol < 1, atol >= 0.
        max_swings: the most swings integrated (static); default from t_end and the
            oscillator when both are concrete (the swings of the window, with a margin),
            else 64. Past it the solution is invalid (``RESULTS.max_swings_reached``).
        max_steps_per_swing: rows of the step table budgeted per swing (static; default from
            rtol, about twice the steps a swing takes). The table holds max_swings times
            this; a trajectory uses only the steps its motion takes.
        ts: optional 1-D sample times: x and v there are computed in the same compiled call
            (from each step's polynomial, built once) and `x(ts)`, `v(ts)` return them.
        adjoint: "recursive" (default; reverse mode, jax.grad), "forward" (jax.jacfwd) or
            "direct" (both; slower).
        solver: "dop853" (the only one; kept as an option for clarity).

    Returns:
        A `ReferenceSolution`. Called eagerly it raises ValueError when x0, v0 or t_end is not
        finite, t_end is not positive, or the budget ran out before t_end or the halt (naming
        max_swings); under jit it returns valid = False instead.
    """
    options = check_reference_options(x0, v0, t_end=t_end, rtol=rtol, atol=atol,
                                      max_swings=max_swings,
                                      max_steps_per_swing=max_steps_per_swing, ts=ts,
                                      adjoint=adjoint, solver=solver)
    return solve_reference_checked(osc, x0, v0, **options)


def check_reference_options(x0, v0, *, t_end=None, rtol: float = 1e-10, atol: float = 1e-12,
                            max_swings: int | None = None,
                            max_steps_per_swing: int | None = None, ts=None,
                            adjoint: str = "recursive", solver: str = "dop853") -> dict:
    """The checks of :func:`solve_reference` (at the edge: ``dp.solve``, ``solve_reference``):
    ValueError naming the option; x0, v0, t_end and ts finite where concrete.

    Returns:
        The options of :func:`solve_reference_checked`, normalised (floats, arrays).
    """
    if solver not in ("dop853", "dopri8"):
        raise ValueError(f"solver must be 'dop853' (Hairer's 8th-order pair), got {solver!r}")
    if adjoint not in _KINDS:
        raise ValueError(f"adjoint must be one of {tuple(_KINDS)}, got {adjoint!r}")
    if jnp.asarray(0.0, dtype=float).dtype != jnp.float64:
        raise ValueError("solve_reference needs float64: call "
                         "jax.config.update('jax_enable_x64', True) first")
    rtol = check_real("rtol", rtol, low=0.0, low_open=True, high=1.0, high_open=True,
                      hint=" (the relative tolerance of the step-size control)")
    atol = check_real("atol", atol, low=0.0,
                      hint=" (the absolute tolerance of the step-size control)")
    if max_swings is not None and (isinstance(max_swings, bool) or int(max_swings) < 1):
        raise ValueError(f"max_swings must be an int >= 1, got {max_swings!r}")
    if max_steps_per_swing is not None and int(max_steps_per_swing) < 2:
        raise ValueError(f"max_steps_per_swing must be an int >= 2, got {max_steps_per_swing!r}")
    check_finite("x0", x0)
    check_finite("v0", v0)
    if t_end is not None:  # None: the default span, from the oscillator
        check_finite("t_end", t_end)
        if is_concrete(t_end) and np.any(np.asarray(t_end, dtype=float) <= 0):
            raise ValueError(f"t_end must be > 0, got {t_end!r}")
    if ts is not None:
        check_finite("ts", ts)
        ts = jnp.asarray(ts, dtype=float)
        if ts.ndim != 1:
            raise ValueError(f"ts must be a 1-D array of sample times, got shape {ts.shape}")
    return dict(t_end=t_end, rtol=rtol, atol=atol, max_swings=max_swings,
                max_steps_per_swing=max_steps_per_swing, ts=ts, adjoint=adjoint)


def solve_reference_checked(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                            atol: float = 1e-12, max_swings: int | None = None,
                            max_steps_per_swing: int | None = None, ts=None,
                            adjoint: str = "recursive") -> ReferenceSolution:
    """:func:`solve_reference` for options already checked (:func:`check_reference_options`):
    the integration, and eagerly the failure's ValueError (budget named)."""
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    if t_end is None:
        t_end = DEFAULT_PERIODS * 2.0 * math.pi / osc.omega0
    t_end = jnp.asarray(t_end, dtype=float)
    if max_swings is None:
        max_swings = (default_swings(osc, x0, v0, t_end) if is_concrete(osc, x0, v0, t_end)
                      else DEFAULT_SWINGS)
    per_swing = rows_per_swing(rtol) if max_steps_per_swing is None else max_steps_per_swing
    sol = _solve_jit(osc, x0, v0, t_end, ts, rtol=rtol, atol=atol, max_swings=int(max_swings),
                     rows=int(max_swings) * int(per_swing), adjoint=adjoint)
    if is_concrete(sol.result._value) and sol.message:
        budget = bool(np.any(np.asarray(sol.result == RESULTS.max_swings_reached)))
        raise ValueError(sol.message + (f" (now max_swings = {max_swings}, max_steps_per_swing"
                                        f" = {per_swing})" if budget else ""))
    return sol
