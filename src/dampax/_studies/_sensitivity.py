"""Sensitivities of the motion to the parameters: d x(t)/d theta, d E(t)/d theta, d tau/d theta.

:func:`sensitivity` differentiates one model of :func:`dampax.solve` with respect to any of the
oscillator's fields (m, k, mu, b, D, g) and the initial state (x0, v0), for the displacement
and the energy at given times, for the halt time and position and (opt-in) for the first few
turning points, and next to each local derivative of the halt time and position (and of the
number of swings and the turning points) a *trend* derivative: the least-squares slope of the
quantity over a window of +-5 % (``window``) of each parameter, from one vmapped sweep. The halt
jumps where a swing is lost or gained, so the local derivative (the slope between jumps) and the
trend (the slope the jumps set) can differ by orders of magnitude; a turning point of the exact
motion does not jump (it only appears or disappears with its swing), so there its two
derivatives agree where it exists. Forward mode (``jax.jacfwd``) is the default: a handful of
parameters against many outputs (x and E at every time). The whole evaluation is compiled
once per (method, options, wrt, shape of ts) and re-used for new numbers; it runs under
``jax.vmap`` for a grid of parameters.

:func:`dampax.plot_sensitivity` (in ``_plot``) draws d x(t)/d theta of several models, and
``dampax._cli.sensitivity`` is the ``dampax sensitivity`` command.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._cache import call_cached
from .._models._registry import METHODS, MODELS
from .._models._solution import RESULTS, is_successful, message
from .._oscillator import Oscillator, check_choices, check_count, is_concrete
from .._solve import check_options, solve_checked
from .._solve import turning_points_checked as _turning_points

Array = jax.Array

#: Oscillator fields, in the order of its constructor.
FIELDS = ("m", "k", "mu", "b", "D", "g", "k3")
#: Every name :func:`sensitivity` can differentiate with respect to.
PARAMETERS = FIELDS + ("x0", "v0")
#: Units of the parameters (d x/d theta is in m per this unit).
UNITS = {"m": "kg", "k": "N/m", "mu": "", "b": "kg/s", "D": "kg/m", "g": "m/s²", "k3": "N/m³",
         "x0": "m", "v0": "m/s"}
_SYMBOLS = {"m": "m", "k": "k", "mu": r"\mu", "b": "b", "D": "D", "g": "g", "k3": "k_3",
            "x0": "x_0", "v0": "v_0"}
_MODES = ("forward", "reverse")
#: the most turning points a sensitivity follows (1e9 hung allocating their derivatives)
MAX_TURNING = 1000
# the adjoints of the reference integrator that each mode of differentiation can go through
_ADJOINTS = {"forward": ("forward", "direct"), "reverse": ("recursive", "direct")}
# default reference integration span, in undamped periods (as solve_reference's default)
_REFERENCE_PERIODS = 25.0


class Sensitivity(eqx.Module):
    """Values and first derivatives of one model at the times ``ts``.

    The derivatives are stacked along a leading axis, one row per name of ``wrt`` (in that
    order): ``dx[i]`` is d x(ts)/d wrt[i] in m per unit of wrt[i] (e.g. m per kg/m for D,
    m for the dimensionless mu, m/m for x0). Use :meth:`of` for one parameter by name and
    :meth:`as_dict` for all of them.

    Attributes:
        ts: the times [s].
        x: x(ts) [m], shaped like ts.
        dx: d x(ts)/d theta, shape (len(wrt),) + ts.shape.
        energy: E(ts) = k x^2/2 + m v^2/2 [J].
        denergy: d E(ts)/d theta, shape (len(wrt),) + ts.shape.
        halt_time: when the model comes to rest [s]; inf when it never does (mu = 0) or, for
            the reference, not within its t_end.
        dhalt_time: d halt_time/d theta, shape (len(wrt),); NaN where halt_time is not finite.
        halt_position: where it comes to rest [m] (0 for the plain ansatz); NaN if never.
        dhalt_position: d halt_position/d theta, shape (len(wrt),); NaN where it never halts.
        dhalt_time_trend: the trend derivative of the halt time, shape (len(wrt),): the
            least-squares slope of halt_time over the window theta (1 - w) ... theta (1 + w);
            NaN where the halt time is not finite somewhere in the window, where theta = 0
            (an empty window) or where ``trend=False``.
        dhalt_position_trend: the same for the halt position.
        swings: the number of swings: turning points (v = 0, t > 0) before the halt, as
            counted by :func:`dampax.turning_points` (the rest point included where the model
            stops at a turning point: the reference, the Coulomb tail); an integer, so its
            local derivative is 0 where defined; NaN if it never halts, beyond 64 turning
            points, or without ``swings=True`` (and ``trend=True``).
        dswings_trend: the trend derivative of ``swings`` (swings per unit of the parameter).
        turning_times, turning_positions: the first N = ``turning_points`` turning points
            (t_n, x_n), n = 1 ... N, as :func:`dampax.turning_points` lists them (v = 0, t > 0,
            the rest point last where the model stops at a turning point), shape (N,); NaN
            where the motion has fewer (it halted before, or the reference's t_end or
            max_swings ended it). Empty (N = 0) unless ``turning_points`` > 0.
        dturning_time, dturning_position: their local derivatives d t_n/d theta,
            d x_n/d theta, shape (len(wrt), N); NaN where the turning point does not exist.
        dturning_time_trend, dturning_position_trend: their trend derivatives, shape
            (len(wrt), N): the least-squares slope of t_n (x_n) over the window points where
            turning point n exists (NaN on the sweep elsewhere); NaN where fewer than
            :data:`MIN_TREND_POINTS` window points have it, or where theta = 0. In the exact
            motion (reference, coulomb_exact) and the plain ansatz a turning point is smooth in
            the parameters where it exists (a swing lost or gained removes or adds the last one
            and does not move the others), so trend and local derivative agree up to the
            window's curvature; with tail="coulomb" the points after the switch to the exact
            tail jump where the switch moves.
        window_values: the parameter values of the sweeps, shape (len(wrt), window_points):
            row i varies wrt[i] alone, the others held.
        window_halt_time, window_halt_position, window_swings: the halt time, position and
            number of swings on the sweeps,
            shape (len(wrt), window_points) (for :func:`dampax.plot_trend`).
        window_turning_times, window_turning_positions: the turning points on the sweeps,
            shape (len(wrt), window_points, N).
        result: the model's ``RESULTS`` member (why it failed: NaN values, e.g. no admissible
            amplitude); ``valid`` is ``result == RESULTS.successful``.
        wrt: the parameter names (static).
        window: the relative half-width w of the trend window (static).

    Under ``jax.vmap`` every array gains the batch axes in front (dx: batch + (len(wrt),) +
    ts.shape); :meth:`of` and :meth:`as_dict` handle that.
    """

    ts: Array
    x: Array
    dx: Array
    energy: Array
    denergy: Array
    halt_time: Array
    dhalt_time: Array
    halt_position: Array
    dhalt_position: Array
    dhalt_time_trend: Array
    dhalt_position_trend: Array
    swings: Array
    dswings_trend: Array
    window_values: Array
    window_halt_time: Array
    window_halt_position: Array
    window_swings: Array
    turning_times: Array
    turning_positions: Array
    dturning_time: Array
    dturning_position: Array
    dturning_time_trend: Array
    dturning_position_trend: Array
    window_turning_times: Array
    window_turning_positions: Array
    result: RESULTS
    wrt: tuple[str, ...] = eqx.field(static=True)
    window: float = eqx.field(static=True)

    @property
    def valid(self) -> Array:
        """The model's validity flag (``result`` is successful)."""
        return is_successful(self.result)

    def index(self, name: str) -> int:
        """Row of ``name`` in the derivative arrays (ValueError naming wrt if absent)."""
        if name not in self.wrt:
            raise ValueError(f"wrt: {name!r} was not differentiated; this result has {self.wrt}")
        return self.wrt.index(name)

    def of(self, name: str) -> dict[str, Array]:
        """Derivatives with respect to one parameter.

        Arguments:
            name: one of ``wrt``, e.g. "mu".

        Returns:
            {"x": d x(ts)/d name, "energy": d E(ts)/d name, "halt_time": d tau/d name,
            "halt_position": d x_halt/d name, "halt_time_trend": the trend derivative of tau,
            "halt_position_trend": that of x_halt, "swings_trend": that of the number of
            swings, "turning_time": d t_n/d name (shape (N,), n = 1 ... N),
            "turning_time_trend", "turning_position": d x_n/d name, "turning_position_trend"},
            with the batch axes in front when batched.
        """
        i = self.index(name)
        axis = jnp.ndim(self.dhalt_time) - 1  # the wrt axis comes after the batch axes
        arrays = {"x": self.dx, "energy": self.denergy, "halt_time": self.dhalt_time,
                  "halt_position": self.dhalt_position,
                  "halt_time_trend": self.dhalt_time_trend,
                  "halt_position_trend": self.dhalt_position_trend,
                  "swings_trend": self.dswings_trend, "turning_time": self.dturning_time,
                  "turning_time_trend": self.dturning_time_trend,
                  "turning_position": self.dturning_position,
                  "turning_position_trend": self.dturning_position_trend}
        if axis == 0 and is_concrete(arrays):  # values: numpy's take compiles no program
            return {k: jax.device_put(np.take(np.asarray(a), i, axis=axis))
                    for k, a in arrays.items()}
        return {k: jnp.take(a, i, axis=axis) for k, a in arrays.items()}

    def as_dict(self) -> dict[str, dict[str, Array]]:
        """{name: self.of(name)} for every name of ``wrt``, in order."""
        return {name: self.of(name) for name in self.wrt}

    def disagreements(self) -> dict[str, dict[str, bool]]:
        """Where the local and the trend derivative differ by more than a factor 2.

        Returns:
            {name: {"halt_time": bool, "halt_position": bool, "swings": bool,
            "turning_time_1": bool, "turning_position_1": bool, ...}} for an unbatched result,
            one pair of turning-point keys per n = 1 ... N; see :func:`differ_by_factor` (a NaN
            trend is never flagged; a derivative d with |d| theta w < :data:`NEGLIGIBLE` times
            the quantity counts as 0). The local derivative of the number of swings is 0 (an
            integer), so "swings" is True wherever its trend is not 0: a swing is lost or
            gained inside the window.
        """
        if jnp.ndim(self.dhalt_time) != 1:
            raise ValueError("disagreements: needs an unbatched Sensitivity")
        values = {"halt_time": self.halt_time, "halt_position": self.halt_position,
                  "swings": self.swings, "turning_time": self.turning_times,
                  "turning_position": self.turning_positions}
        out = {}
        for i, name in enumerate(self.wrt):
            g = self.of(name)
            g["swings"] = jax.device_put(np.zeros(()))  # an integer: 0 locally, where defined
            # rounding (e.g. a trend of 1e-27 s where the quantity does not depend on the
            # parameter): |d| theta w below NEGLIGIBLE |quantity|
            theta = abs(float(np.asarray(self.window_values)[i, 0] + np.asarray(
                self.window_values)[i, -1])) / 2.0
            span = theta * self.window

            def flag(local, trend, value, span=span):
                value = abs(float(value))
                tiny = NEGLIGIBLE * value / span if span > 0.0 and math.isfinite(value) else 0.0
                return differ_by_factor(float(local), float(trend), negligible=tiny)

            flags = {q: flag(g[q], g[q + "_trend"], values[q])
                     for q in ("halt_time", "halt_position", "swings")}
            for q in ("turning_time", "turning_position"):
                for j, (local, trend, value) in enumerate(zip(
                        np.asarray(g[q]), np.asarray(g[q + "_trend"]), np.asarray(values[q]),
                        strict=True)):
                    flags[f"{q}_{j + 1}"] = flag(local, trend, value)
            out[name] = flags
        return out

    def report(self, *, digits: int = 4) -> str:
        """A table of the halt time and position with their local and trend derivatives.

        Arguments:
            digits: significant digits.

        Returns:
            The text (several lines): one row per parameter, '*' where the local and the trend
            derivative differ by more than a factor 2, the number of swings and its trend
            (with ``swings=True``), then one row per parameter and turning point (with
            ``turning_points`` > 0), and one line saying why where something is flagged.
        """
        flags = self.disagreements()

        def num(v):
            v = float(v)
            return "-" if math.isnan(v) else f"{v:.{digits}g}"

        def star(flag):
            return "*" if flag else " "

        counted = math.isfinite(float(self.swings))
        lines = [f"halt time {num(self.halt_time)} s, halt position {num(self.halt_position)} m"
                 + (f", {num(self.swings)} swings" if counted else "")
                 + f"; trend: least-squares slope over +-{100 * self.window:g} % of each "
                 "parameter",
                 f"{'parameter':<10} {'d halt time':>13} {'trend':>13}  "
                 f"{'d halt position':>15} {'trend':>13}"
                 + (f"  {'d swings trend':>14}" if counted else "")]
        for name in self.wrt:
            g = self.of(name)
            f = flags[name]
            lines.append(f"{name:<10} {num(g['halt_time']):>13} {num(g['halt_time_trend']):>12}"
                         f"{star(f['halt_time'])}  {num(g['halt_position']):>15} "
                         f"{num(g['halt_position_trend']):>12}{star(f['halt_position'])}"
                         + (f"  {num(g['swings_trend']):>13}{star(f['swings'])}"
                            if counted else ""))
        n_turning = int(np.shape(self.turning_times)[-1])
        if n_turning:
            lines.append("turning points (t_n [s], x_n [m]): " + ", ".join(
                f"{j + 1}: ({num(t)}, {num(x)})" for j, (t, x) in enumerate(
                    zip(np.asarray(self.turning_times), np.asarray(self.turning_positions),
                        strict=True))))
            lines.append(f"{'parameter':<10} {'n':>2} {'d t_n':>13} {'trend':>13}  "
                         f"{'d x_n':>13} {'trend':>13}")
            for name in self.wrt:
                g = self.of(name)
                f = flags[name]
                for j in range(n_turning):
                    lines.append(
                        f"{name if j == 0 else '':<10} {j + 1:>2} "
                        f"{num(g['turning_time'][j]):>13} "
                        f"{num(g['turning_time_trend'][j]):>12}"
                        f"{star(f[f'turning_time_{j + 1}'])}  "
                        f"{num(g['turning_position'][j]):>13} "
                        f"{num(g['turning_position_trend'][j]):>12}"
                        f"{star(f[f'turning_position_{j + 1}'])}")
        if any(any(f.values()) for f in flags.values()):
            lines.append(f"* {TREND_NOTE}")
        return "\n".join(lines)


#: The one line that explains a flagged pair (local vs trend derivative).
TREND_NOTE = ("local and trend differ by more than a factor 2: the quantity jumps inside the "
              "window (a swing lost or gained), the local derivative is the slope between "
              "jumps; for changes wider than the jumps use the trend")


def differ_by_factor(local: float, trend: float, factor: float = 2.0, *,
                     negligible: float = 0.0) -> bool:
    """Whether two derivatives differ by more than ``factor`` (or in sign).

    Arguments:
        local, trend: the two numbers (a NaN gives False: nothing to compare).
        factor: the ratio allowed, > 1.
        negligible: magnitudes up to this count as 0 (rounding: e.g. a trend of 1e-27 s where
            the quantity does not depend on the parameter at all).

    Returns:
        True when the signs differ, or max(|local|, |trend|) > factor * min(|local|, |trend|)
        (so 0 against a non-zero number differs; 0 against 0 does not).
    """
    if not (math.isfinite(local) and math.isfinite(trend)):
        return False
    local = 0.0 if abs(local) <= negligible else local
    trend = 0.0 if abs(trend) <= negligible else trend
    if local == 0.0 and trend == 0.0:
        return False
    if local * trend < 0.0:
        return True
    small, big = sorted((abs(local), abs(trend)))
    return big > factor * small


#: A derivative d with |d| theta w below this fraction of the quantity (a change over the
#: half-window that no one could see: rounding, or the reference's integration error) counts as
#: 0 in :meth:`Sensitivity.disagreements`.
NEGLIGIBLE = 1e-6


def check_wrt(wrt) -> tuple[str, ...]:
    if isinstance(wrt, str):
        wrt = (wrt,)
    try:
        names = tuple(wrt)
    except TypeError:
        raise ValueError(f"wrt must be a sequence of names from {PARAMETERS}, "
                         f"got {wrt!r}") from None
    return check_choices("wrt", names, PARAMETERS)


def check_window(window) -> float:
    """The relative half-width of the trend window as a float; ValueError unless 0 < w < 1."""
    try:
        w = float(window)
    except (TypeError, ValueError):
        raise ValueError(f"window must be a number between 0 and 1, got {window!r}") from None
    if not (math.isfinite(w) and 0.0 < w < 1.0):
        raise ValueError(f"window must be a relative half-width with 0 < window < 1 (0.05 is "
                         f"+-5 %), got {window!r}")
    return w


def _as_float64(value):
    """``jnp.asarray(value, dtype=float)``; a Python or numpy number is put on the device as a
    float64 array instead (no conversion program compiled, issue 26): the same value."""
    if isinstance(value, (int, float, np.number, np.ndarray)) and not isinstance(value, bool):
        return jax.device_put(np.asarray(value, dtype=float))
    return jnp.asarray(value, dtype=float)


def _check_ts(ts) -> Array:
    if is_concrete(ts):
        arr = np.asarray(ts, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"ts must be finite times, got {ts!r}")
        if np.any(arr < 0.0):
            raise ValueError(f"ts must be times >= 0, got {ts!r}")
    return jnp.asarray(ts, dtype=float)


#: Turning points counted by :func:`count_swings` (more are reported as NaN).
MAX_SWINGS = 64
#: The fewest window points a turning point's trend is fitted over (else NaN).
MIN_TREND_POINTS = 3


def count_swings(sol, t_turning=None) -> Array:
    """Number of turning points (t > 0, v = 0) before the halt, the rest point included where
    the model stops at a turning point (as :func:`dampax.turning_points`); NaN when the model
    never halts or has more than :data:`MAX_SWINGS` of them. ``t_turning``: the times of its
    first MAX_SWINGS (or more) turning points, if computed already."""
    if t_turning is None:
        t_turning, _ = _turning_points(sol, MAX_SWINGS)
    count = jnp.sum(jnp.isfinite(t_turning[..., :MAX_SWINGS]), axis=-1).astype(float)
    ok = jnp.isfinite(sol.halt_time) & (count < MAX_SWINGS)
    return jnp.where(ok, count, jnp.nan)


def least_squares_slope(u: Array, y: Array) -> Array:
    """Least-squares slope of y against u along the last axis (NaN if u is constant or y not
    finite somewhere); NaN-safe under grad (double where)."""
    du = u - jnp.mean(u, axis=-1, keepdims=True)
    finite = jnp.all(jnp.isfinite(y), axis=-1)
    y_safe = jnp.where(jnp.isfinite(y), y, 0.0)
    dy = y_safe - jnp.mean(y_safe, axis=-1, keepdims=True)
    den = jnp.sum(du * du, axis=-1)
    ok = finite & (den > 0.0)
    slope = jnp.sum(du * dy, axis=-1) / jnp.where(ok, den, 1.0)
    return jnp.where(ok, slope, jnp.nan)


def least_squares_slope_where_finite(u: Array, y: Array,
                                     min_points: int = MIN_TREND_POINTS) -> Array:
    """Least-squares slope of y against u along the last axis over the points where y is
    finite (NaN if fewer than ``min_points`` of them, or u constant there); NaN-safe under grad.

    Arguments:
        u, y: the abscissae and values, same shape (or broadcastable).
        min_points: the fewest finite points to fit a slope through.

    Returns:
        The slopes, shaped like y without its last axis.
    """
    u, y = jnp.broadcast_arrays(u, y)
    mask = jnp.isfinite(y)
    w = mask.astype(float)
    count = jnp.sum(w, axis=-1, keepdims=True)
    count_safe = jnp.maximum(count, 1.0)
    y_safe = jnp.where(mask, y, 0.0)
    du = (u - jnp.sum(w * u, axis=-1, keepdims=True) / count_safe) * w
    dy = (y_safe - jnp.sum(y_safe, axis=-1, keepdims=True) / count_safe) * w
    den = jnp.sum(du * du, axis=-1)
    ok = (count[..., 0] >= min_points) & (den > 0.0)
    slope = jnp.sum(du * dy, axis=-1) / jnp.where(ok, den, 1.0)
    return jnp.where(ok, slope, jnp.nan)


@eqx.filter_jit
def with_values(osc: Oscillator, x0, v0, names, p):
    """(oscillator, x0, v0) with the parameters ``names`` (Oscillator fields, "x0", "v0") set
    to the entries of ``p``, every other field kept (k3 included)."""
    values = {f: getattr(osc, f) for f in FIELDS} | dict(x0=x0, v0=v0)
    values.update({name: p[i] for i, name in enumerate(names)})
    fields = [f for f in FIELDS if f in names]
    if fields:  # the checked oscillator with its leaves replaced: not constructed (checked) again
        osc = eqx.tree_at(lambda o: [getattr(o, f) for f in fields], osc,
                          [jnp.asarray(values[f], dtype=float) for f in fields])
    return osc, values["x0"], values["v0"]


def _evaluate(osc, x0, v0, ts, t_end, wrt, method, mode, options, window, points, trend,
              swings, n_turning):
    """Values and Jacobians of (x(ts), E(ts), tau, x_halt, turning points) w.r.t. ``wrt``, and
    the trend sweeps, compiled."""
    base = {f: getattr(osc, f) for f in FIELDS} | dict(x0=x0, v0=v0)
    theta = jnp.stack([base[name] for name in wrt])
    if method == "reference":
        if t_end is None:  # the reference's own default, stretched to cover ts
            t_end = jnp.maximum(_REFERENCE_PERIODS * 2.0 * math.pi / osc.omega0, jnp.max(ts))
        options = dict(options, t_end=t_end)

    def solution(p):  # the options were checked at the edge (sensitivity)
        return solve_checked(*with_values(osc, x0, v0, wrt, p), method=method, **options)

    def turning(sol, n):
        if n == 0:  # nothing asked: leave the program as it was
            empty = jnp.zeros((0,))
            return empty, empty
        return _turning_points(sol, n)

    count_on = swings and trend  # the swing count is only given with its trend

    def outputs(p):
        sol = solution(p)
        # the swing count and the turning points share one search
        t_all, x_all = turning(sol, max(n_turning, MAX_SWINGS) if count_on else n_turning)
        out = (sol.x(ts), sol.energy(ts), sol.halt_time, sol.halt_position,
               t_all[:n_turning], x_all[:n_turning])
        count = count_swings(sol, t_all) if count_on else jnp.array(jnp.nan)
        return out, (out, count, sol.result)

    # trend: one sweep per parameter over theta_i (1 - w) ... theta_i (1 + w), the others held
    n = len(wrt)
    grid = theta[:, None] * (1.0 + window * jnp.linspace(-1.0, 1.0, points))  # (n, points)
    eye = jnp.eye(n, dtype=bool)
    P = jnp.where(eye[:, None, :], grid[:, :, None], theta[None, None, :])  # (n, pts, n)
    P = P.reshape(n * points, n)
    jac = jax.jacfwd if mode == "forward" else jax.jacrev
    d, (values, count, result) = jac(outputs, has_aux=True)(theta)
    # the sweep, values only (one vmapped Jacobian over the nominal point and the sweep would
    # compile the model once instead of twice, but for the reference that saves only ~5 % of
    # the compilation and costs 20-50 times the run time)
    swept = jax.vmap(lambda p: outputs(p)[1][:2])(P) if trend else None
    x, e, tau, xh, tt, xt = values
    dx, de, dtau, dxh, dtt, dxt = (jnp.moveaxis(a, -1, 0) for a in d)
    # the halt time and position have no derivative where the model never halts, a turning
    # point none where the motion does not reach it
    dtau = jnp.where(jnp.isfinite(tau), dtau, jnp.nan)
    dxh = jnp.where(jnp.isfinite(xh), dxh, jnp.nan)
    dtt = jnp.where(jnp.isfinite(tt), dtt, jnp.nan)
    dxt = jnp.where(jnp.isfinite(xt), dxt, jnp.nan)
    if trend:
        (_, _, wtau, wxh, wtt, wxt), wsw = jax.tree_util.tree_map(
            lambda a: a.reshape((n, points) + a.shape[1:]), swept)
        ttau, txh = least_squares_slope(grid, wtau), least_squares_slope(grid, wxh)
        tsw = least_squares_slope(grid, wsw)
        # turning point j: over the window points where it exists; axes (n, N, points)
        ttt = least_squares_slope_where_finite(grid[:, None, :], jnp.moveaxis(wtt, -1, 1))
        txt = least_squares_slope_where_finite(grid[:, None, :], jnp.moveaxis(wxt, -1, 1))
    else:
        wtau = wxh = wsw = jnp.full(grid.shape, jnp.nan)
        ttau = txh = tsw = jnp.full((n,), jnp.nan)
        wtt = wxt = jnp.full(grid.shape + (n_turning,), jnp.nan)
        ttt = txt = jnp.full((n, n_turning), jnp.nan)
    return Sensitivity(ts=ts, x=x, dx=dx, energy=e, denergy=de, halt_time=tau, dhalt_time=dtau,
                       halt_position=xh, dhalt_position=dxh, dhalt_time_trend=ttau,
                       dhalt_position_trend=txh, window_values=grid, window_halt_time=wtau,
                       window_halt_position=wxh, swings=count, dswings_trend=tsw,
                       window_swings=wsw, turning_times=tt, turning_positions=xt,
                       dturning_time=dtt, dturning_position=dxt, dturning_time_trend=ttt,
                       dturning_position_trend=txt, window_turning_times=wtt,
                       window_turning_positions=wxt, result=result, wrt=wrt, window=window)


#: The array fields of a Sensitivity (all but the result and the static wrt, window).
_ARRAY_FIELDS = tuple(f.name for f in dataclasses.fields(Sensitivity)
                      if f.name not in ("result", "wrt", "window"))


def _cacheable(osc, x0, v0, ts, t_end, options) -> bool:
    """True for an eager call whose options are plain values (their repr names the program)."""
    leaves = jax.tree_util.tree_leaves((osc, x0, v0, ts, t_end))
    plain = all(v is None or isinstance(v, str | int | float | bool) for v in options.values())
    return plain and all(is_concrete(leaf) for leaf in leaves)


def _evaluate_cached(osc, x0, v0, ts, t_end, static) -> Sensitivity:
    """`_evaluate` for concrete input through a kept compiled program (`call_cached`): a
    repeated call, also in a new process, neither traces nor compiles the Jacobians and sweeps."""
    leaves, treedef = jax.tree_util.tree_flatten(osc)
    n = len(leaves)

    def arrays(*flat):
        sens = _evaluate(jax.tree_util.tree_unflatten(treedef, flat[:n]), *flat[n:n + 3],
                         flat[n + 3] if len(flat) > n + 3 else None, *static)
        out = {name: getattr(sens, name) for name in _ARRAY_FIELDS}
        out["result"] = sens.result._value
        return out

    args = (*leaves, x0, v0, ts) + (() if t_end is None else (t_end,))
    key = (str(treedef), static, t_end is None)
    out = call_cached("sensitivity", key, arrays, *args)
    result = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(RESULTS.successful),
                                          [out.pop("result")])
    return Sensitivity(**out, result=result, wrt=static[0], window=static[4])


def _check_terms(names, method: str, named: dict) -> None:
    """ValueError for a name of ``wrt`` that the model of ``method`` (with its phase and
    tail) leaves out (``Model.lacks`` of every registry entry whose options it holds): its
    derivative came out 0, no derivative of x (dx/db of Rizcallah's Coulomb-only solution)."""
    chosen = {"method": method, **{k: named[k] for k in ("phase", "tail")
                                   if named.get(k) not in (None, "matched")}}
    models = [m for m in MODELS.values()
              if all(chosen.get(k) == v for k, v in m.solve_options.items())]
    bad = [n for n in names if any(n in m.lacks for m in models)]
    if bad:
        which = next(m for m in models if bad[0] in m.lacks)
        raise ValueError(f"wrt: {', '.join(bad)} not in the {which.name} model (method="
                         f"{method!r}; {which.domain}): its derivative would be 0, not that "
                         "of x; leave it out of wrt, or use method='reference'")


def sensitivity(osc: Oscillator, x0, v0, ts, *, wrt: Sequence[str] = ("mu", "b", "D", "x0", "v0"),
                method: str = "ansatz", mode: str = "forward", trend: bool = True,
                window: float = 0.05, window_points: int = 41, swings: bool = False,
                turning_points: int = 0, **solve_options) -> Sensitivity:
    """First derivatives of a model's x(t), E(t), halt time and position, local and trend.

    Differentiates ``dampax.solve(osc, x0, v0, method=method, **solve_options)`` with respect to
    each name in ``wrt``, exactly (automatic differentiation through the closed forms, or
    through the reference's integration and its event times for the reference): the *local*
    derivatives. For the halt time and position, which are only piecewise continuous in the
    parameters (they jump where a turning point crosses the band |x| = xc and a swing is lost),
    it also returns the *trend* derivative: for each theta_i of ``wrt`` the model is evaluated
    at ``window_points`` equally spaced values u_j in [theta_i (1 - w), theta_i (1 + w)]
    (w = ``window``; the other parameters held; one vmapped sweep) and the trend is the
    least-squares slope sum_j (u_j - u_mean)(q_j - q_mean) / sum_j (u_j - u_mean)^2.
    Local derivative: the response to an infinitesimal change (between jumps); trend: the
    response to changes of the order of the window, jumps included. Where the two differ by
    more than a factor 2 (``Sensitivity.disagreements``, flagged by ``report``), the quantity
    jumps inside the window and the local number must not be read as the trend. Opt-in, the
    same for the number of swings (``swings=True``) and for the first few turning points
    (``turning_points=N``; their trend is fitted over the window points where turning point n
    exists).

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator` (for a batch, use ``jax.vmap``, below).
        x0, v0: initial displacement [m] and velocity [m/s] (scalars).
        ts: times [s] >= 0, any shape (scalar, 1-d grid, ...).
        wrt: names to differentiate with respect to, from ("m", "k", "mu", "b", "D", "g",
            "x0", "v0"); a single name may be given as a string. A constant the method's
            model leaves out (``MODELS[...].lacks``: b and D for "rizcallah", D for
            "coulomb_exact", k3 but for the matched ansatz and the reference) is a
            ValueError: its derivative there is 0, not that of x.
        method: "ansatz" (default), "reference", "rizcallah" or "coulomb_exact", as in
            :func:`dampax.solve`.
        mode: "forward" (default; ``jax.jacfwd``, one pass for all names: the fast choice
            since there are few parameters and many outputs) or "reverse" (``jax.jacrev``, one
            backward pass per output; a cross-check: equal to 1e-14, but for the reference it
            compiles about 3 times longer, ~60 s against ~20 s on 2 CPU cores).
        **solve_options: passed to :func:`dampax.solve`: phase, tail, back for the ansatz (e.g.
            ``method="ansatz", tail="coulomb"``), kappa for rizcallah; t_end, rtol, atol,
            max_swings, ... for the reference. The reference's ``adjoint`` is chosen to suit
            ``mode`` ("forward" resp. "recursive"); "direct" works with both. Its ``t_end``
            defaults to 25 undamped periods or max(ts), whichever is later (the halt time needs
            the integration to reach the halt).
        trend: compute the trend derivatives (default True; False leaves them NaN and skips
            the sweep).
        window: relative half-width w of the trend window, 0 < w < 1 (default 0.05: +-5 % of
            each parameter's value; a parameter equal to 0 has an empty window and a NaN
            trend).
        window_points: values per sweep, >= 3 (default 41; the sweep costs
            len(wrt) * window_points evaluations of the model, no derivatives).
        swings: also count the swings (turning points before the halt, via
            :func:`dampax.turning_points`, at most 64) at the nominal point and on the sweeps,
            and give their trend ``dswings_trend`` (default False: for the analytic models the
            count costs a Newton solve per turning point and about doubles the compilation).
        turning_points: also give the first N = ``turning_points`` turning points (t_n, x_n)
            (v = 0, t > 0, as :func:`dampax.turning_points`; N <= 1000), their local derivatives
            (``dturning_time``, ``dturning_position``) and, on the same sweeps, their trends
            (``dturning_time_trend``, ``dturning_position_trend``: the least-squares slope over
            the window points where turning point n exists); default 0 (none: like
            ``swings``, this costs compilation time for the analytic models).

    Returns:
        A :class:`Sensitivity`: ``dx`` has shape (len(wrt),) + ts.shape, ``dx[i]`` in m per
        unit of ``wrt[i]``; ``result.of("mu")["x"]`` is d x(ts)/d mu, ``result.as_dict()`` all;
        ``dturning_time`` has shape (len(wrt), turning_points).

    Non-smooth points: the ansatz's x(t) has a kink at its halt time, so its d x(t)/d theta
    jumps there (to 0, or to the rest position's derivative with tail="coulomb"); for every
    model the number of swings before the halt jumps where a turning point crosses |x| = xc,
    and the halt time and position (and x after the halt) jump with it: the derivatives are
    those of the current swing count. Where the motion never halts
    (mu = 0, or the reference before its t_end) the halt time is inf and ``dhalt_time``,
    ``dhalt_position`` are NaN; ``dx`` and ``denergy`` stay finite there (also d x/d mu at
    mu = 0 for the ansatz and the reference).

    Raises:
        ValueError: unknown or repeated names in ``wrt``; ``ts`` not finite or negative;
            a non-scalar oscillator or initial state; an unknown method or mode; an adjoint that
            does not suit the mode; window not in (0, 1); window_points < 3; turning_points
            not an integer >= 0; and, called
            eagerly, a model that is invalid for these
            parameters (dampax.solve's reason). Under jit/vmap an invalid model gives
            ``valid = False`` and NaN instead.

    Example, a grid of friction coefficients::

        ts = jnp.linspace(0.0, 2.0, 200)

        def dx_dmu(mu):
            osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, D=1.0)
            return dp.sensitivity(osc, 0.2, 0.0, ts, wrt=("mu", "D")).dx

        dx = jax.vmap(dx_dmu)(jnp.array([0.02, 0.05, 0.1]))   # shape (3, 2, 200)
    """
    if not isinstance(osc, Oscillator):
        raise TypeError(f"osc must be a dampax.Oscillator, got {type(osc).__name__}")
    names = check_wrt(wrt)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    ts = _check_ts(ts)
    window = check_window(window)
    if isinstance(window_points, bool) or not isinstance(window_points, int | np.integer) \
            or window_points < 3:
        raise ValueError(f"window_points must be an integer >= 3, got {window_points!r}")
    n_turning = check_count("turning_points", turning_points)
    if n_turning > MAX_TURNING:
        raise ValueError(f"turning_points must be at most {MAX_TURNING} (each adds derivatives "
                         f"and sweeps of its own), got {n_turning}")
    for name, value in (("osc", osc), ("x0", x0), ("v0", v0)):
        if any(jnp.ndim(leaf) for leaf in jax.tree_util.tree_leaves(value)):
            raise ValueError(f"{name}: sensitivity needs scalars, not a batch; map over a batch "
                             f"with jax.vmap")
    options = dict(solve_options)
    if method == "reference":
        adjoint = options.setdefault("adjoint", "forward" if mode == "forward" else "recursive")
        if adjoint not in _ADJOINTS[mode]:
            raise ValueError(f"adjoint={adjoint!r} cannot be differentiated in {mode} mode; "
                             f"use one of {_ADJOINTS[mode]} (or leave adjoint out)")
    # dampax.solve's checks, once here (x0, v0 finite; the model's options, a misplaced one
    # named); inside the program the solves trust them (_solve.solve_checked)
    named = {k: options.pop(k) for k in ("phase", "tail", "back", "kappa") if k in options}
    _check_terms(names, method, named)
    kappa, back, checked = check_options(osc, x0, v0, method=method, **named, options=options)
    x0, v0 = _as_float64(x0), _as_float64(v0)
    if method == "reference":
        t_end = checked.pop("t_end")
        t_end = None if t_end is None else jnp.asarray(t_end, dtype=float)
        options = {k: v for k, v in checked.items() if v is not None}
    else:
        t_end = None
        options = dict(phase=named.get("phase", "matched"), tail=named.get("tail"), back=back,
                       kappa=kappa)
    static = (names, method, mode, options, window, int(window_points), bool(trend),
              bool(swings), n_turning)
    if _cacheable(osc, x0, v0, ts, t_end, options):
        result = _evaluate_cached(osc, x0, v0, ts, t_end, static)
    else:
        result = _evaluate(osc, x0, v0, ts, t_end, *static)
    if is_concrete(result.result._value) and message(result.result):  # numpy: no dispatch
        raise ValueError(f"method={method!r}: {message(result.result)}")
    return result


