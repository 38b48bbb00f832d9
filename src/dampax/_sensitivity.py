"""Sensitivities of the motion to the parameters: d x(t)/d theta, d E(t)/d theta, d tau/d theta.

:func:`sensitivity` differentiates one model of :func:`dampax.solve` with respect to any of the
oscillator's fields (m, k, mu, b, D, g) and the initial state (x0, v0), for the displacement
and the energy at given times and for the halt time and position, and next to each local
derivative of the halt time and position a *trend* derivative: the least-squares slope of the
quantity over a window of +-5 % (``window``) of each parameter, from one vmapped sweep. The halt
jumps where a swing is lost or gained, so the local derivative (the slope between jumps) and the
trend (the slope the jumps set) can differ by orders of magnitude. Forward mode (``jax.jacfwd``)
is the default: a handful of parameters against many outputs (x and E at every time). The
whole evaluation is compiled once per (method, options, wrt, shape of ts) and re-used for new
numbers; it runs under ``jax.vmap`` for a grid of parameters.

:func:`dampax.plot_sensitivity` (in ``_plot``) draws d x(t)/d theta of several models, and
``dampax._cli.sensitivity`` is the ``dampax sensitivity`` command.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._models import METHODS
from ._oscillator import Oscillator, check_choices, check_finite, is_concrete
from ._solution import RESULTS, is_successful, message
from ._solve import solve, turning_points

Array = jax.Array

#: Oscillator fields, in the order of its constructor.
FIELDS = ("m", "k", "mu", "b", "D", "g")
#: Every name :func:`sensitivity` can differentiate with respect to.
PARAMETERS = FIELDS + ("x0", "v0")
#: Units of the parameters (d x/d theta is in m per this unit).
UNITS = {"m": "kg", "k": "N/m", "mu": "", "b": "kg/s", "D": "kg/m", "g": "m/s²", "x0": "m",
         "v0": "m/s"}
_SYMBOLS = {"m": "m", "k": "k", "mu": r"\mu", "b": "b", "D": "D", "g": "g", "x0": "x_0",
            "v0": "v_0"}
_MODES = ("forward", "reverse")
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
        window_values: the parameter values of the sweeps, shape (len(wrt), window_points):
            row i varies wrt[i] alone, the others held.
        window_halt_time, window_halt_position, window_swings: the halt time, position and
            number of swings on the sweeps,
            shape (len(wrt), window_points) (for :func:`dampax.plot_trend`).
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
            swings}, with the batch axes in front when batched.
        """
        i = self.index(name)
        axis = jnp.ndim(self.dhalt_time) - 1  # the wrt axis comes after the batch axes
        return {"x": jnp.take(self.dx, i, axis=axis),
                "energy": jnp.take(self.denergy, i, axis=axis),
                "halt_time": jnp.take(self.dhalt_time, i, axis=axis),
                "halt_position": jnp.take(self.dhalt_position, i, axis=axis),
                "halt_time_trend": jnp.take(self.dhalt_time_trend, i, axis=axis),
                "halt_position_trend": jnp.take(self.dhalt_position_trend, i, axis=axis),
                "swings_trend": jnp.take(self.dswings_trend, i, axis=axis)}

    def as_dict(self) -> dict[str, dict[str, Array]]:
        """{name: self.of(name)} for every name of ``wrt``, in order."""
        return {name: self.of(name) for name in self.wrt}

    def disagreements(self) -> dict[str, dict[str, bool]]:
        """Where the local and the trend derivative differ by more than a factor 2.

        Returns:
            {name: {"halt_time": bool, "halt_position": bool}} for an unbatched result; see
            :func:`differ_by_factor` (a NaN trend is never flagged).
        """
        if jnp.ndim(self.dhalt_time) != 1:
            raise ValueError("disagreements: needs an unbatched Sensitivity")
        out = {}
        for name in self.wrt:
            g = self.of(name)
            out[name] = {q: differ_by_factor(float(g[q]), float(g[q + "_trend"]))
                         for q in ("halt_time", "halt_position")}
        return out

    def report(self, *, digits: int = 4) -> str:
        """A table of the halt time and position with their local and trend derivatives.

        Arguments:
            digits: significant digits.

        Returns:
            The text (several lines): one row per parameter, '*' where the local and the trend
            derivative differ by more than a factor 2, and then one line saying why.
        """
        flags = self.disagreements()

        def num(v):
            v = float(v)
            return "-" if math.isnan(v) else f"{v:.{digits}g}"

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
            ft = "*" if flags[name]["halt_time"] else " "
            fp = "*" if flags[name]["halt_position"] else " "
            lines.append(f"{name:<10} {num(g['halt_time']):>13} {num(g['halt_time_trend']):>12}"
                         f"{ft}  {num(g['halt_position']):>15} "
                         f"{num(g['halt_position_trend']):>12}{fp}"
                         + (f"  {num(g['swings_trend']):>14}" if counted else ""))
        if any(any(f.values()) for f in flags.values()):
            lines.append(f"* {TREND_NOTE}")
        return "\n".join(lines)


#: The one line that explains a flagged pair (local vs trend derivative).
TREND_NOTE = ("local and trend differ by more than a factor 2: the quantity jumps inside the "
              "window (a swing lost or gained), the local derivative is the slope between "
              "jumps; for changes wider than the jumps use the trend")


def differ_by_factor(local: float, trend: float, factor: float = 2.0) -> bool:
    """Whether two derivatives differ by more than ``factor`` (or in sign).

    Arguments:
        local, trend: the two numbers (a NaN gives False: nothing to compare).
        factor: the ratio allowed, > 1.

    Returns:
        True when the signs differ, or max(|local|, |trend|) > factor * min(|local|, |trend|)
        (so 0 against a non-zero number differs; 0 against 0 does not).
    """
    if not (math.isfinite(local) and math.isfinite(trend)):
        return False
    if local == 0.0 and trend == 0.0:
        return False
    if local * trend < 0.0:
        return True
    small, big = sorted((abs(local), abs(trend)))
    return big > factor * small


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


def count_swings(sol) -> Array:
    """Number of turning points (t > 0, v = 0) before the halt, the rest point included where
    the model stops at a turning point (as :func:`dampax.turning_points`); NaN when the model
    never halts or has more than :data:`MAX_SWINGS` of them."""
    t, _ = turning_points(sol, MAX_SWINGS)
    count = jnp.sum(jnp.isfinite(t)).astype(float)
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


@eqx.filter_jit
def _evaluate(osc, x0, v0, ts, t_end, wrt, method, mode, options, window, points, trend,
              swings):
    """Values and Jacobians of (x(ts), E(ts), tau, x_halt) w.r.t. ``wrt``, and the trend
    sweeps, compiled."""
    base = dict(m=osc.m, k=osc.k, mu=osc.mu, b=osc.b, D=osc.D, g=osc.g, x0=x0, v0=v0)
    theta = jnp.stack([base[name] for name in wrt])
    if method == "reference":
        if t_end is None:  # the reference's own default, stretched to cover ts
            t_end = jnp.maximum(_REFERENCE_PERIODS * 2.0 * math.pi / osc.omega0, jnp.max(ts))
        options = dict(options, t_end=t_end)

    def solution(p):
        values = dict(base)
        values.update({name: p[i] for i, name in enumerate(wrt)})
        o = Oscillator(**{f: values[f] for f in FIELDS})
        return solve(o, values["x0"], values["v0"], method=method, **options)

    def outputs(p):
        sol = solution(p)
        out = (sol.x(ts), sol.energy(ts), sol.halt_time, sol.halt_position)
        return out, (out, sol.result)

    jac = jax.jacfwd if mode == "forward" else jax.jacrev
    d, ((x, e, tau, xh), result) = jac(outputs, has_aux=True)(theta)
    dx, de, dtau, dxh = (jnp.moveaxis(a, -1, 0) for a in d)
    # the halt time and position have no derivative where the model never halts
    dtau = jnp.where(jnp.isfinite(tau), dtau, jnp.nan)
    dxh = jnp.where(jnp.isfinite(xh), dxh, jnp.nan)
    # trend: one sweep per parameter over theta_i (1 - w) ... theta_i (1 + w), the others held
    n = len(wrt)
    grid = theta[:, None] * (1.0 + window * jnp.linspace(-1.0, 1.0, points))  # (n, points)
    if trend:
        eye = jnp.eye(n, dtype=bool)
        P = jnp.where(eye[:, None, :], grid[:, :, None], theta[None, None, :])  # (n, pts, n)

        def halt(p):
            sol = solution(p)
            count = count_swings(sol) if swings else jnp.array(jnp.nan)
            return sol.halt_time, sol.halt_position, count

        wtau, wxh, wsw = jax.vmap(jax.vmap(halt))(P)
        ttau, txh = least_squares_slope(grid, wtau), least_squares_slope(grid, wxh)
        tsw = least_squares_slope(grid, wsw)
        n_swings = halt(theta)[2]
    else:
        wtau = wxh = wsw = jnp.full(grid.shape, jnp.nan)
        ttau = txh = tsw = jnp.full((n,), jnp.nan)
        n_swings = jnp.array(jnp.nan)
    return Sensitivity(ts=ts, x=x, dx=dx, energy=e, denergy=de, halt_time=tau, dhalt_time=dtau,
                       halt_position=xh, dhalt_position=dxh, dhalt_time_trend=ttau,
                       dhalt_position_trend=txh, window_values=grid, window_halt_time=wtau,
                       window_halt_position=wxh, swings=n_swings, dswings_trend=tsw,
                       window_swings=wsw, result=result, wrt=wrt, window=window)


def sensitivity(osc: Oscillator, x0, v0, ts, *, wrt: Sequence[str] = ("mu", "b", "D", "x0", "v0"),
                method: str = "ansatz", mode: str = "forward", trend: bool = True,
                window: float = 0.05, window_points: int = 41, swings: bool = False,
                **solve_options) -> Sensitivity:
    """First derivatives of a model's x(t), E(t), halt time and halt position, local and trend.

    Differentiates ``dampax.solve(osc, x0, v0, method=method, **solve_options)`` with respect to
    each name in ``wrt``, exactly (automatic differentiation through the closed forms, or
    through the diffrax integration and its event times for the reference): the *local*
    derivatives. For the halt time and position, which are only piecewise continuous in the
    parameters (they jump where a turning point crosses the band |x| = xc and a swing is lost),
    it also returns the *trend* derivative: for each theta_i of ``wrt`` the model is evaluated
    at ``window_points`` equally spaced values u_j in [theta_i (1 - w), theta_i (1 + w)]
    (w = ``window``; the other parameters held; one vmapped sweep) and the trend is the
    least-squares slope sum_j (u_j - u_mean)(q_j - q_mean) / sum_j (u_j - u_mean)^2.
    Local derivative: the response to an infinitesimal change (between jumps); trend: the
    response to changes of the order of the window, jumps included. Where the two differ by
    more than a factor 2 (``Sensitivity.disagreements``, flagged by ``report``), the quantity
    jumps inside the window and the local number must not be read as the trend.

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator` (for a batch, use ``jax.vmap``, below).
        x0, v0: initial displacement [m] and velocity [m/s] (scalars).
        ts: times [s] >= 0, any shape (scalar, 1-d grid, ...).
        wrt: names to differentiate with respect to, from ("m", "k", "mu", "b", "D", "g",
            "x0", "v0"); a single name may be given as a string.
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

    Returns:
        A :class:`Sensitivity`: ``dx`` has shape (len(wrt),) + ts.shape, ``dx[i]`` in m per
        unit of ``wrt[i]``; ``result.of("mu")["x"]`` is d x(ts)/d mu, ``result.as_dict()`` all.

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
            does not suit the mode; window not in (0, 1); window_points < 3; and, called
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
    check_finite("x0", x0)
    check_finite("v0", v0)
    for name, value in (("osc", osc), ("x0", x0), ("v0", v0)):
        if any(jnp.ndim(leaf) for leaf in jax.tree_util.tree_leaves(value)):
            raise ValueError(f"{name}: sensitivity needs scalars, not a batch; map over a batch "
                             f"with jax.vmap")
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    options = dict(solve_options)
    t_end = options.pop("t_end", None)
    if method == "reference":
        adjoint = options.setdefault("adjoint", "forward" if mode == "forward" else "recursive")
        if adjoint not in _ADJOINTS[mode]:
            raise ValueError(f"adjoint={adjoint!r} cannot be differentiated in {mode} mode; "
                             f"use one of {_ADJOINTS[mode]} (or leave adjoint out)")
        if t_end is not None:
            check_finite("t_end", t_end)
            if is_concrete(t_end) and np.any(np.asarray(t_end, dtype=float) <= 0.0):
                raise ValueError(f"t_end must be > 0, got {t_end!r}")
            t_end = jnp.asarray(t_end, dtype=float)
    elif t_end is not None:
        options["t_end"] = t_end  # dampax.solve names the misplaced option
    result = _evaluate(osc, x0, v0, ts, t_end, names, method, mode, options, window,
                       int(window_points), bool(trend), bool(swings))
    if is_concrete(result.result._value) and not np.all(np.asarray(result.valid)):
        raise ValueError(f"method={method!r}: {message(result.result)}")
    return result


