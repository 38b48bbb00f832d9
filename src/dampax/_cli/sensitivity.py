"""``dampax sensitivity``: how the halt time and position depend on the parameters."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from .._models import MODELS, check_models
from .._oscillator import Oscillator, check_finite
from .._sensitivity import PARAMETERS, UNITS, Sensitivity, check_wrt, sensitivity
from .._solve import solve
from ._common import (
    PROG,
    add_oscillator_arguments,
    check_digits,
    check_plot_path,
    fmt,
    oscillator_from,
    oscillator_text,
    split_names,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax sensitivity``."""
    add_oscillator_arguments(parser, mu=0.05, D=1.0, start_title="initial state")
    what = parser.add_argument_group("sensitivities")
    what.add_argument("--wrt", default="mu,D", metavar="NAMES",
                      help=f"comma-separated parameters to differentiate with respect to, from "
                           f"{','.join(PARAMETERS)} (default: %(default)s)")
    what.add_argument("--models", default="matched,reference", metavar="NAMES",
                      help=f"comma-separated models: {', '.join(MODELS)} "
                           "(default: %(default)s)")
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
    from .._plot import plot_sensitivity

    names = check_wrt(split_names(args.wrt))
    models = check_models(args.models, "--models")
    if args.samples < 2:
        raise ValueError(f"--samples must be >= 2, got {args.samples}")
    check_digits(args.digits)
    if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0.0):
        raise ValueError(f"--t-end must be a finite time > 0, got {args.t_end}")
    check_plot_path(args.plot)
    osc = oscillator_from(args)
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
                                 **MODELS[k].solve_options)

    d = args.digits
    print(f"{PROG} sensitivity: {oscillator_text(args)}")
    print()
    labels = {k: MODELS[k].label for k in models}
    width = max(max(len(s) for s in labels.values()), len("model"))
    print(f"  {'model':<{width}}  {'halt time [s]':>13}  {'halt position [m]':>17}")
    for k, r in results.items():
        print(f"  {labels[k]:<{width}}  "
              f"{fmt(float(np.asarray(r.halt_time)), d, inf='never'):>13}  "
              f"{fmt(float(np.asarray(r.halt_position)), d):>17}")
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
                  f"{fmt(float(np.asarray(g['halt_time'])), d):>15}  "
                  f"{fmt(float(np.asarray(g['halt_position'])), d):>19}")
            first = ""
    title = (rf"m = {args.m:g} kg, k = {args.k:g} N/m, $\mu$ = {args.mu:g}, b = {args.b:g} kg/s, "
             rf"D = {args.D:g} kg/m, $x_0$ = {args.x0:g} m, $v_0$ = {args.v0:g} m/s")
    path = plot_sensitivity(results, args.plot, title=title)
    print()
    print(f"  plot written to {path}")
    sys.stdout.flush()
    return 0
