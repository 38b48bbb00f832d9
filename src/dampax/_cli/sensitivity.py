"""``dampax sensitivity``: how the halt time and position depend on the parameters.

Local mode (default): local (autodiff) and trend (least-squares slope over a window)
derivatives of the halt time and position (with ``--swings`` the number of swings, with
``--turning-points N`` the first N turning points), a plot of d x(t)/d theta and one of the halt
over each parameter's window. Global mode (``--global "mu=0.01:0.05,D=0.5:3"``): Sobol' indices S1,
ST with bootstrap half-widths and DGSM over those ranges, and a bar chart.
"""

from __future__ import annotations

import argparse
import math
import sys

import jax
import numpy as np

from dampax_cli._arguments import add_sensitivity_arguments as add_arguments  # noqa: F401 (SUBCOMMANDS)

from .._models._registry import MODELS, check_models
from .._oscillator import Oscillator, check_finite
from .._studies._sensitivity import (
    MAX_TURNING,
    TREND_NOTE,
    UNITS,
    Sensitivity,
    check_window,
    check_wrt,
    sensitivity,
)
from ._common import (
    PROG,
    check_digits,
    check_plot_path,
    fmt,
    not_used,
    oscillator_from,
    oscillator_text,
    split_names,
)
from .solve import check_start


def parse_global(spec: str) -> dict[str, tuple[float, float]]:
    """The ranges of ``--global "mu=0.01:0.05,D=0.5:3"`` as {name: (lo, hi)} (ValueError)."""
    from .._studies._global import check_bounds  # the global mode's module, imported only for it

    bounds: dict[str, tuple[float, float]] = {}
    for item in split_names(spec):
        name, sep, rng = item.partition("=")
        name = name.strip()
        lo, sep2, hi = rng.partition(":")
        if not sep or not sep2 or not name:
            raise ValueError(f"--global: {item!r} is not NAME=LO:HI (e.g. mu=0.01:0.05)")
        if name in bounds:
            raise ValueError(f"--global: {name} given twice")
        try:
            bounds[name] = (float(lo), float(hi))
        except ValueError:
            raise ValueError(f"--global: {item!r}: LO and HI must be numbers") from None
    if not bounds:
        raise ValueError("--global: no ranges given; e.g. --global \"mu=0.01:0.05,D=0.5:3\"")
    try:
        check_bounds(bounds)
    except ValueError as err:
        raise ValueError(f"--global: {err}") from None
    return bounds


def _trend_path(args: argparse.Namespace) -> str:
    if args.trend_plot is not None:
        return args.trend_plot
    from pathlib import Path

    plot = Path(args.plot)
    return str(plot.with_name(f"{plot.stem}_trend{plot.suffix}"))


def _default_t_end(osc: Oscillator, x0: float, v0: float) -> float:
    """The window of the plot: past the matched ansatz's halt, 2 to 12 undamped periods."""
    from .._models._solution import message
    from .._studies._summary import _solve_one

    period = 2.0 * math.pi / float(np.asarray(osc.omega0))
    # the matched ansatz (solve(method="ansatz")) by the kept program of dampax solve: a
    # repeated command neither traces nor compiles it; NaN where the model does not exist
    sol, (tau, _, _) = _solve_one(osc, jax.device_put(np.asarray(x0, dtype=float)),
                                  jax.device_put(np.asarray(v0, dtype=float)), "matched", 1)
    tau = math.inf if message(sol.result) else float(np.asarray(tau))
    if not math.isfinite(tau):
        return 4.0 * period
    return min(max(2.0 * period, tau + 0.5 * period), 12.0 * period)


def run(args: argparse.Namespace) -> int:
    """Print how the halt time and position depend on the parameters; plot d x(t)/d theta."""
    from .._plot import plot_sensitivity, plot_trend

    # the other mode's flags, given, were ignored without a word
    if args.global_spec is not None:
        not_used(args, "--global (a global study over ranges)",
                 ("--wrt", "--t-end", "--samples", "--window", "--window-points", "--swings",
                  "--turning-points", "--trend-plot"), add_arguments)
        return run_global(args)
    not_used(args, "a local study (they are --global's)",
             ("--quantity", "--time", "--n", "--seed"), add_arguments)
    names = check_wrt(split_names(args.wrt))
    models = check_models(args.models or "matched,reference", "--models")
    if args.samples < 2:
        raise ValueError(f"--samples must be >= 2, got {args.samples}")
    check_digits(args.digits)
    if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0.0):
        raise ValueError(f"--t-end must be a finite time > 0, got {args.t_end}")
    try:
        window = check_window(args.window)
    except ValueError as err:
        raise ValueError(f"--{err}") from None
    if args.window_points < 3:
        raise ValueError(f"--window-points must be >= 3, got {args.window_points}")
    if not 0 <= args.turning_points <= MAX_TURNING:
        raise ValueError(f"--turning-points must be between 0 and {MAX_TURNING}, got "
                         f"{args.turning_points}")
    check_plot_path(args.plot)
    trend_path = _trend_path(args)
    check_plot_path(trend_path, "--trend-plot")
    osc = oscillator_from(args)
    check_finite("x0", args.x0)
    check_finite("v0", args.v0)
    check_start(osc, args)
    for k in models:
        if not MODELS[k].applies(osc):
            raise ValueError(f"--models: {k} ({MODELS[k].label}) does not apply to this "
                             "oscillator (see dampax solve --help)")
    t_end = args.t_end if args.t_end is not None else _default_t_end(osc, args.x0, args.v0)
    ts = np.linspace(0.0, t_end, args.samples)

    def one(k):
        return sensitivity(osc, args.x0, args.v0, ts, wrt=names, window=window,
                           window_points=args.window_points, swings=args.swings,
                           turning_points=args.turning_points, **MODELS[k].solve_options)

    # the models side by side: each loads (or compiles) its own program with Python's lock
    # released, on a core of its own (a repeated command: 3.33 -> 2.96 s on 2 cores)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=len(models), thread_name_prefix="dampax-cli") as pool:
        futures = {k: pool.submit(one, k) for k in models}
    results: dict[str, Sensitivity] = {k: f.result() for k, f in futures.items()}
    flags = {k: r.disagreements() for k, r in results.items()}

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
    print(f"  derivatives per unit of the parameter: local (autodiff) and trend (least-squares "
          f"slope over +-{100 * window:g} % of the parameter); '-' where undefined")
    print(f"  {'parameter':<14}  {'model':<{width}}  {'d halt time [s]':>15}  {'trend':>11}  "
          f"{'d halt position [m]':>19}  {'trend':>11}")
    for name in names:
        unit = UNITS[name] or "1"
        first = f"{name} [{unit}]"
        for k, r in results.items():
            g = r.of(name)
            cells = []
            for q in ("halt_time", "halt_position"):
                local = float(np.asarray(g[q]))
                trend = float(np.asarray(g[q + "_trend"]))
                star = "*" if flags[k][name][q] else " "
                cells.append((fmt(local, d), fmt(trend, d) + star))
            print(f"  {first:<14}  {labels[k]:<{width}}  {cells[0][0]:>15}  {cells[0][1]:>12} "
                  f"{cells[1][0]:>19}  {cells[1][1]:>12}")
            first = ""
    if args.swings:
        _print_swings(results, names, flags, labels, width, d)
    if args.turning_points:
        _print_turning_points(results, names, flags, labels, width, d)
    if any(any(f.values()) for per_model in flags.values() for f in per_model.values()):
        print(f"  * {TREND_NOTE}")
    title = (rf"m = {args.m:g} kg, k = {args.k:g} N/m, $\mu$ = {args.mu:g}, b = {args.b:g} kg/s, "
             rf"D = {args.D:g} kg/m, $x_0$ = {args.x0:g} m, $v_0$ = {args.v0:g} m/s")
    path = plot_sensitivity(results, args.plot, title=title)
    tpath = plot_trend(results, trend_path, title=title)
    print()
    print(f"  plot written to {path}")
    print(f"  halt over the trend windows written to {tpath}")
    sys.stdout.flush()
    return 0


def _print_swings(results, names, flags, labels, width, d) -> None:
    """The number of swings of each model and its trend per parameter ('*': not 0)."""
    print()
    print("  number of swings (turning points before the halt, the rest point included): "
          + ", ".join(f"{labels[k]} {fmt(float(np.asarray(r.swings)), d)}"
                      for k, r in results.items()))
    print(f"  {'parameter':<14}  {'model':<{width}}  {'d swings':>9}  {'trend':>11}")
    for name in names:
        first = f"{name} [{UNITS[name] or '1'}]"
        for k, r in results.items():
            local = 0.0 if math.isfinite(float(np.asarray(r.swings))) else math.nan
            trend = float(np.asarray(r.of(name)["swings_trend"]))
            star = "*" if flags[k][name]["swings"] else " "
            print(f"  {first:<14}  {labels[k]:<{width}}  {fmt(local, d):>9}  "
                  f"{fmt(trend, d) + star:>12}")
            first = ""


def _print_turning_points(results, names, flags, labels, width, d) -> None:
    """The first N turning points of each model with their local and trend derivatives."""
    print()
    print("  turning points (v = 0, t > 0): t_n [s], x_n [m]; '-' where the motion has fewer")
    for k, r in results.items():
        points = ", ".join(f"{j + 1}: ({fmt(float(t), d)}, {fmt(float(x), d)})"
                           for j, (t, x) in enumerate(zip(np.asarray(r.turning_times),
                                                          np.asarray(r.turning_positions),
                                                          strict=True)))
        print(f"  {labels[k]:<{width}}  {points}")
    print(f"  {'parameter':<14}  {'model':<{width}}  {'n':>2}  {'d t_n [s]':>11}  "
          f"{'trend':>11}  {'d x_n [m]':>11}  {'trend':>11}")
    for name in names:
        first = f"{name} [{UNITS[name] or '1'}]"
        for k, r in results.items():
            g = r.of(name)
            for j in range(int(np.shape(r.turning_times)[-1])):
                cells = []
                for q in ("turning_time", "turning_position"):
                    star = "*" if flags[k][name][f"{q}_{j + 1}"] else " "
                    cells.append(fmt(float(np.asarray(g[q])[j]), d))
                    cells.append(fmt(float(np.asarray(g[q + "_trend"])[j]), d) + star)
                print(f"  {first:<14}  {labels[k] if j == 0 else '':<{width}}  {j + 1:>2}  "
                      f"{cells[0]:>11}  {cells[1]:>12} {cells[2]:>11}  {cells[3]:>12}")
                first = ""


def run_global(args: argparse.Namespace) -> int:
    """``--global``: Sobol' indices and DGSM of the quantity over the ranges; bar chart."""
    from .._plot import plot_global_sensitivity
    from .._studies._global import global_sensitivity

    bounds = parse_global(args.global_spec)
    models = check_models(args.models or "matched", "--models")
    check_digits(args.digits)
    if args.n < 16:
        raise ValueError(f"--n must be >= 16, got {args.n}")
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    if args.quantity in ("energy", "x") and args.time is None:
        raise ValueError(f"--time: --quantity {args.quantity} needs the time [s]")
    if args.time is not None and not (math.isfinite(args.time) and args.time >= 0.0):
        raise ValueError(f"--time must be a finite time >= 0, got {args.time}")
    if args.quantity == "max_error" and "reference" in models:
        raise ValueError("--models: max_error compares a model against the reference; "
                         "leave reference out")
    check_plot_path(args.plot)
    osc = oscillator_from(args)
    check_finite("x0", args.x0)
    check_finite("v0", args.v0)
    results = {}
    for k in models:
        results[k] = global_sensitivity(bounds=bounds, oscillator=osc, x0=args.x0, v0=args.v0,
                                        quantity=args.quantity, n=args.n, seed=args.seed,
                                        t=args.time, **MODELS[k].solve_options)
    d = args.digits
    ranges = ", ".join(f"{k} in [{lo:g}, {hi:g}]" for k, (lo, hi) in bounds.items())
    print(f"{PROG} sensitivity --global: {args.quantity} over {ranges}")
    print(f"  others: {oscillator_text(args)}")
    print(f"  n = {args.n} base samples, seed {args.seed}; half-widths: 95 % bootstrap")
    print()
    labels = {k: MODELS[k].label for k in models}
    width = max(max(len(s) for s in labels.values()), len("model"))
    print(f"  {'parameter':<10}  {'model':<{width}}  {'S1':>9}  {'+-':>8}  {'ST':>9}  "
          f"{'+-':>8}  {'DGSM':>9}")
    for name in bounds:
        first = name
        for k, ds in results.items():
            row = ds.sel(parameter=name)
            print(f"  {first:<10}  {labels[k]:<{width}}  {fmt(float(row.S1), d):>9}  "
                  f"{fmt(float(row.S1_conf), 2):>8}  {fmt(float(row.ST), d):>9}  "
                  f"{fmt(float(row.ST_conf), 2):>8}  {fmt(float(row.DGSM), d):>9}")
            first = ""
    print("  S1: share of the variance from the parameter alone; ST: with its interactions; "
          "DGSM: derivative bound on ST (not a bound where the quantity jumps)")
    path = plot_global_sensitivity(results, args.plot)
    print()
    print(f"  plot written to {path}")
    sys.stdout.flush()
    return 0
