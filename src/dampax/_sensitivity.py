"""Sensitivities of the motion to the parameters: d x(t)/d theta, d E(t)/d theta, d tau/d theta.

:func:`sensitivity` differentiates one model of :func:`dampax.solve` with respect to any of the
oscillator's fields (m, k, mu, b, D, g) and the initial state (x0, v0), for the displacement
and the energy at given times and for the halt time and position. Forward mode (``jax.jacfwd``)
is the default: a handful of parameters against many outputs (x and E at every time). The
whole evaluation is compiled once per (method, options, wrt, shape of ts) and re-used for new
numbers; it runs under ``jax.vmap`` for a grid of parameters.

:func:`plot_sensitivity` draws d x(t)/d theta of several models, one panel per parameter, and
:func:`add_arguments` / :func:`run` are the ``dampax sensitivity`` subcommand.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._oscillator import Oscillator, check_choices, check_finite, is_concrete
from ._solve import METHODS, solve

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
        valid: the model's validity flag (False: NaN values, e.g. no admissible amplitude).
        wrt: the parameter names (static).

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
    valid: Array
    wrt: tuple[str, ...] = eqx.field(static=True)

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
            "halt_position": d x_halt/d name}, with the batch axes in front when batched.
        """
        i = self.index(name)
        axis = jnp.ndim(self.dhalt_time) - 1  # the wrt axis comes after the batch axes
        return {"x": jnp.take(self.dx, i, axis=axis),
                "energy": jnp.take(self.denergy, i, axis=axis),
                "halt_time": jnp.take(self.dhalt_time, i, axis=axis),
                "halt_position": jnp.take(self.dhalt_position, i, axis=axis)}

    def as_dict(self) -> dict[str, dict[str, Array]]:
        """{name: self.of(name)} for every name of ``wrt``, in order."""
        return {name: self.of(name) for name in self.wrt}


def _check_wrt(wrt) -> tuple[str, ...]:
    if isinstance(wrt, str):
        wrt = (wrt,)
    try:
        names = tuple(wrt)
    except TypeError:
        raise ValueError(f"wrt must be a sequence of names from {PARAMETERS}, "
                         f"got {wrt!r}") from None
    return check_choices("wrt", names, PARAMETERS)


def _check_ts(ts) -> Array:
    if is_concrete(ts):
        arr = np.asarray(ts, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"ts must be finite times, got {ts!r}")
        if np.any(arr < 0.0):
            raise ValueError(f"ts must be times >= 0, got {ts!r}")
    return jnp.asarray(ts, dtype=float)


@eqx.filter_jit
def _evaluate(osc, x0, v0, ts, t_end, wrt, method, mode, options):
    """Values and Jacobians of (x(ts), E(ts), tau, x_halt) w.r.t. ``wrt``, compiled."""
    base = dict(m=osc.m, k=osc.k, mu=osc.mu, b=osc.b, D=osc.D, g=osc.g, x0=x0, v0=v0)
    theta = jnp.stack([base[name] for name in wrt])
    if method == "reference":
        if t_end is None:  # the reference's own default, stretched to cover ts
            t_end = jnp.maximum(_REFERENCE_PERIODS * 2.0 * math.pi / osc.omega0, jnp.max(ts))
        options = dict(options, t_end=t_end)

    def outputs(p):
        values = dict(base)
        values.update({name: p[i] for i, name in enumerate(wrt)})
        o = Oscillator(**{f: values[f] for f in FIELDS})
        sol = solve(o, values["x0"], values["v0"], method=method, **options)
        out = (sol.x(ts), sol.energy(ts), sol.halt_time, sol.halt_position)
        return out, (out, sol.valid)

    jac = jax.jacfwd if mode == "forward" else jax.jacrev
    d, ((x, e, tau, xh), valid) = jac(outputs, has_aux=True)(theta)
    dx, de, dtau, dxh = (jnp.moveaxis(a, -1, 0) for a in d)
    # the halt time and position have no derivative where the model never halts
    dtau = jnp.where(jnp.isfinite(tau), dtau, jnp.nan)
    dxh = jnp.where(jnp.isfinite(xh), dxh, jnp.nan)
    return Sensitivity(ts=ts, x=x, dx=dx, energy=e, denergy=de, halt_time=tau, dhalt_time=dtau,
                       halt_position=xh, dhalt_position=dxh, valid=valid, wrt=wrt)


def sensitivity(osc: Oscillator, x0, v0, ts, *, wrt: Sequence[str] = ("mu", "b", "D", "x0", "v0"),
                method: str = "ansatz", mode: str = "forward", **solve_options) -> Sensitivity:
    """First derivatives of a model's x(t), E(t), halt time and halt position.

    Differentiates ``dampax.solve(osc, x0, v0, method=method, **solve_options)`` with respect to
    each name in ``wrt``, exactly (automatic differentiation through the closed forms, or
    through the diffrax integration and its event times for the reference).

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
            does not suit the mode; and, called eagerly, a model that is invalid for these
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
    names = _check_wrt(wrt)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    ts = _check_ts(ts)
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
    result = _evaluate(osc, x0, v0, ts, t_end, names, method, mode, options)
    if is_concrete(result.valid) and not np.all(np.asarray(result.valid)):
        # dampax.solve called eagerly gives the reason (it raises ValueError)
        if t_end is not None:
            options["t_end"] = t_end
        solve(osc, x0, v0, method=method, **options)
        raise ValueError(f"method={method!r}: the model could not be evaluated for these "
                         "parameters (validity flag is False)")
    return result


# ----------------------------------------------------------------------------------------------
# plot


_EXTRA_COLORS = ("tab:cyan", "tab:olive", "tab:pink", "tab:brown", "tab:gray")


def _style(key: str, n_other: int) -> dict:
    """Line style of a model: the papers' colours for the keys of dampax._plot.MODELS."""
    from ._plot import MODELS

    spec = MODELS.get(key)
    if spec is not None:
        return dict(color=spec.color, linestyle=spec.linestyle, linewidth=spec.linewidth,
                    zorder=spec.zorder, label=spec.label)
    return dict(color=_EXTRA_COLORS[n_other % len(_EXTRA_COLORS)],
                linestyle=("-", "--", "-.")[n_other % 3], linewidth=1.5, zorder=2.0, label=key)


def axis_label(name: str) -> str:
    """y-axis label of d x/d name with its unit, e.g. 'dx/dD [m per kg/m]'."""
    unit = UNITS[name]
    sym = _SYMBOLS[name]
    per = f"m per {unit}" if unit else "m"
    return rf"$\partial x / \partial {sym}$  [{per}]"


def plot_sensitivity(results: Mapping[str, Sensitivity], path, *, title: str | None = None,
                     dpi: int = 120):
    """Plot d x(t)/d theta of several models, one panel per parameter, and save the figure.

    Arguments:
        results: model name -> unbatched :class:`Sensitivity` over a 1-d grid ``ts``. The keys
            of ``dampax._plot.MODELS`` are drawn in the papers' colours (matched ansatz solid
            red, reference black dotted, ...); any other key gets its own colour and is its
            own legend label. The panels are the union of the results' ``wrt``, in order.
        path: output file; the format follows the suffix (e.g. ``.png``).
        title: figure title (default: none).
        dpi: resolution of raster output.

    Returns:
        ``path``, unchanged.

    Each panel marks the halt time of each model that halts by a thin vertical line in the
    model's colour (x has a kink there: the derivative jumps to 0, or to the rest position's).
    """
    from matplotlib.figure import Figure  # Agg canvas; no pyplot, no display needed

    if not results:
        raise ValueError("results: nothing to plot")
    for key, r in results.items():
        if not isinstance(r, Sensitivity) or np.ndim(r.ts) != 1 or np.ndim(r.dhalt_time) != 1:
            raise ValueError(f"results[{key!r}]: need an unbatched Sensitivity over a 1-d ts")
    names: list[str] = []
    for r in results.values():
        names += [n for n in r.wrt if n not in names]
    n = len(names)
    ncols = 1 if n <= 3 else 2
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(7.0 * ncols + 2.0 * (ncols == 1), 2.5 * nrows + 1.2),
                 layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True, squeeze=False)).ravel()
    styles, n_other = {}, 0
    for key in results:
        styles[key] = _style(key, n_other)
        n_other += styles[key]["label"] == key
    t_max = max(float(np.max(np.asarray(r.ts))) for r in results.values())
    for ax, name in zip(axes[:n], names, strict=True):
        for key, r in results.items():
            if name not in r.wrt:
                continue
            st = styles[key]
            ax.plot(np.asarray(r.ts), np.asarray(r.of(name)["x"]), **st)
            tau = float(np.asarray(r.halt_time))
            if math.isfinite(tau) and tau <= t_max:
                ax.axvline(tau, color=st["color"], linestyle="--", linewidth=0.8, alpha=0.6,
                           zorder=1.0)
        ax.axhline(0.0, color="0.8", linewidth=0.6, zorder=0.5)
        ax.set_ylabel(axis_label(name))
        ax.set_title(rf"sensitivity to ${_SYMBOLS[name]}$", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.set_xlim(0.0, t_max)
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax in axes[max(n - ncols, 0):n]:
        ax.set_xlabel("t [s]")
        ax.xaxis.set_tick_params(labelbottom=True)
    handles, labels = axes[0].get_legend_handles_labels()
    if any(math.isfinite(float(np.asarray(r.halt_time))) for r in results.values()):
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="0.4", linestyle="--", linewidth=0.8))
        labels.append("halt time")
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 4),
               fontsize=9, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=dpi)
    fig.clear()
    return path


# ----------------------------------------------------------------------------------------------
# command line: ``dampax sensitivity``


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax sensitivity`` (register with run in dampax._cli.SUBCOMMANDS)."""
    from ._cli import add_oscillator_arguments

    add_oscillator_arguments(parser, mu=0.05, D=1.0, start_title="initial state")
    what = parser.add_argument_group("sensitivities")
    what.add_argument("--wrt", default="mu,D", metavar="NAMES",
                      help=f"comma-separated parameters to differentiate with respect to, from "
                           f"{','.join(PARAMETERS)} (default: %(default)s)")
    what.add_argument("--models", default="matched,reference", metavar="NAMES",
                      help="comma-separated models: matched, undamped, tail, rizcallah, "
                           "coulomb_exact, reference (default: %(default)s)")
    what.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                      help="time span of the plot (default: half an undamped period past the "
                           "matched ansatz's halt, 2 to 12 periods; 4 periods if it never halts)")
    what.add_argument("--samples", type=int, default=400, metavar="N",
                      help="time samples of the plot (default: %(default)s)")
    out = parser.add_argument_group("output")
    out.add_argument("--digits", type=int, default=4, metavar="N",
                     help="significant digits printed (default: %(default)s)")
    out.add_argument("--plot", metavar="FILE.png", default="sensitivity.png",
                     help="where to save the plot of dx/dtheta (default: %(default)s)")


def _split(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def _default_t_end(osc: Oscillator, x0: float, v0: float) -> float:
    period = 2.0 * math.pi / float(np.asarray(osc.omega0))
    try:
        tau = float(np.asarray(solve(osc, x0, v0, method="ansatz").halt_time))
    except ValueError:
        tau = math.inf
    if not math.isfinite(tau):
        return 4.0 * period
    return min(max(2.0 * period, tau + 0.5 * period), 12.0 * period)


def run(args: argparse.Namespace) -> int:
    """Print how the halt time and position depend on the parameters; plot d x(t)/d theta."""
    from ._cli import PROG, _check_plot_path, _fmt
    from ._plot import MODELS

    names = _check_wrt(_split(args.wrt))
    models = check_choices("--models", _split(args.models), MODELS)
    if args.samples < 2:
        raise ValueError(f"--samples must be >= 2, got {args.samples}")
    if not 1 <= args.digits <= 17:
        raise ValueError(f"--digits must be between 1 and 17, got {args.digits}")
    if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0.0):
        raise ValueError(f"--t-end must be a finite time > 0, got {args.t_end}")
    _check_plot_path(args.plot)
    osc = Oscillator(m=args.m, k=args.k, mu=args.mu, b=args.b, D=args.D, g=args.g)
    check_finite("x0", args.x0)
    check_finite("v0", args.v0)
    for k in models:
        if not MODELS[k].applies(osc):
            raise ValueError(f"--models: {k} ({MODELS[k].label}) does not apply to this "
                             "oscillator (see dampax solve --help)")
    t_end = args.t_end if args.t_end is not None else _default_t_end(osc, args.x0, args.v0)
    ts = np.linspace(0.0, t_end, args.samples)

    results: dict[str, Sensitivity] = {}
    for k in models:
        results[k] = sensitivity(osc, args.x0, args.v0, ts, wrt=names,
                                 **dict(MODELS[k].options))

    d = args.digits
    print(f"{PROG} sensitivity: m = {args.m:g} kg, k = {args.k:g} N/m, mu = {args.mu:g}, "
          f"b = {args.b:g} kg/s, D = {args.D:g} kg/m, g = {args.g:g} m/s^2, "
          f"x0 = {args.x0:g} m, v0 = {args.v0:g} m/s")
    print()
    labels = {k: MODELS[k].label for k in models}
    width = max(max(len(s) for s in labels.values()), len("model"))
    print(f"  {'model':<{width}}  {'halt time [s]':>13}  {'halt position [m]':>17}")
    for k, r in results.items():
        print(f"  {labels[k]:<{width}}  "
              f"{_fmt(float(np.asarray(r.halt_time)), d, inf='never'):>13}  "
              f"{_fmt(float(np.asarray(r.halt_position)), d):>17}")
    print()
    print("  derivatives per unit of the parameter ('-' where the model never halts):")
    print(f"  {'parameter':<14}  {'model':<{width}}  {'d halt time [s]':>15}  "
          f"{'d halt position [m]':>19}")
    for name in names:
        unit = UNITS[name] or "1"
        first = f"{name} [{unit}]"
        for k, r in results.items():
            g = r.of(name)
            print(f"  {first:<14}  {labels[k]:<{width}}  "
                  f"{_fmt(float(np.asarray(g['halt_time'])), d):>15}  "
                  f"{_fmt(float(np.asarray(g['halt_position'])), d):>19}")
            first = ""
    title = (rf"m = {args.m:g} kg, k = {args.k:g} N/m, $\mu$ = {args.mu:g}, b = {args.b:g} kg/s, "
             rf"D = {args.D:g} kg/m, $x_0$ = {args.x0:g} m, $v_0$ = {args.v0:g} m/s")
    path = plot_sensitivity(results, args.plot, title=title)
    print()
    print(f"  plot written to {path}")
    sys.stdout.flush()
    return 0
