"""``dampax solve``: the models' key numbers for one oscillator, and a plot of them."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from dampax_cli._arguments import add_solve_arguments as add_arguments  # noqa: F401 (SUBCOMMANDS)

from ._common import (
    PROG,
    check_digits,
    check_plot_path,
    fmt,
    oscillator_from,
    oscillator_text,
)


def run(args: argparse.Namespace) -> int:
    """Print the amplitudes, damping ratios, halt times and turning points of every model."""
    from .._models._registry import applicable_models
    from .._plot import plot_results
    from .._studies._summary import damping_ratios, run_models

    if args.turning < 0:
        raise ValueError(f"--turning must be >= 0, got {args.turning}")
    check_digits(args.digits)
    if args.plot:
        check_plot_path(args.plot)
    if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0):
        raise ValueError(f"--t-end must be a finite time > 0 [s], got {args.t_end:g}")
    osc = oscillator_from(args)
    check_start(osc, args)
    models = applicable_models(osc, reference=not args.no_reference)
    if "matched" not in models:
        limit = 2.0 * math.sqrt(args.k * args.m)
        raise ValueError(f"--b {args.b:g}: the oscillator is not underdamped (b >= 2 sqrt(k m) "
                         f"= {limit:.4g} kg/s); the matched ansatz and this table need "
                         f"b < {limit:.4g}; for the overdamped motion use "
                         f"dp.solve(osc, x0, v0, method='reference')")
    run = run_models(osc, args.x0, args.v0, models=models, n_turning=max(args.turning, 1),
                     t_end=args.t_end)
    matched = run.results["matched"]
    if matched.error is not None and osc.mu_s is not None:
        # static friction above sliding friction: the matched ansatz (which assumes
        # mu_s = mu) is listed as not available; its amplitude, phase and turning points
        # below are those of the sliding motion, which mu_s changes only at the halt
        sliding = type(osc)(m=osc.m, k=osc.k, mu=osc.mu, b=osc.b, D=osc.D, g=osc.g,
                            k3=osc.k3)
        matched = run_models(sliding, args.x0, args.v0, models=("matched",),
                             n_turning=max(args.turning, 1), t_end=args.t_end
                             ).results["matched"]
        print(f"{PROG}: note: mu_s > mu: the matched ansatz's amplitude, phase and turning "
              "points are those of mu_s = mu (before the halt)", file=sys.stderr)
    if matched.error is not None:
        raise ValueError(f"the matched ansatz does not exist for {_flags(args)}: "
                         f"{matched.error}")
    for note in run.notes:
        print(f"{PROG}: note: {note}", file=sys.stderr)

    d = args.digits
    x0, v0 = run.x0, run.v0
    w0 = float(np.asarray(osc.omega0))
    A0 = math.hypot(x0, v0 / w0)
    phi0 = math.atan2(-v0 / w0, x0) if A0 > 0 else 0.0
    r0, r1, r2 = damping_ratios(osc, x0, v0)
    sol = matched.solution  # valid (else matched.error): its A, phi are the amplitude, phase
    rows = [
        ("A", float(np.asarray(sol.A)), "m", "matched amplitude (eq. 22)"),
        ("phi", float(np.asarray(sol.phi)), "rad", "matched phase (eq. 23)"),
        ("A0", A0, "m", "undamped amplitude, x0 = A0 cos(phi0)"),
        ("phi0", phi0, "rad", "undamped phase, v0 = -w0 A0 sin(phi0)"),
        ("d0/(w0 A0)", r0, "", "Coulomb ratio, d0 = 2 mu g/(pi w0)"),
        ("d1/w0", r1, "", "viscous ratio, d1 = b/(2m)"),
        ("d2 A0/w0", r2, "", "quadratic ratio, d2 = 4 D w0/(3 pi m)"),
        ("xc", float(np.asarray(osc.xc)), "m", "sticking band |x| <= xc = mu g/w0^2"),
        ("w0", w0, "rad/s", f"undamped period T0 = {fmt(2 * math.pi / w0, d)} s"),
    ]
    print(f"{PROG} solve: {oscillator_text(args)}")
    print()
    for name, value, unit, what in rows:
        print(f"  {name:<11} = {fmt(value, d):>10} {unit:<6} {what}")
    print()

    width = max(len(r.label) for r in run.results.values())
    print(f"  {'model':<{width}}  {'halt time [s]':>13}  {'halt position [m]':>17}")
    for r in run.results.values():
        if r.error is not None:
            reason = "not available" if r.name == "reference" else f"not available: {r.error}"
            print(f"  {r.label:<{width}}  {reason}")
            continue
        # the reference integrates [0, t_end]: no halt there is none before t_end, not never
        never = "never" if r.name != "reference" or not float(np.asarray(osc.mu)) > 0 else \
            f"> {fmt(run.t_end, d)}"
        print(f"  {r.label:<{width}}  {fmt(r.halt_time, d, inf=never):>13}  "
              f"{fmt(r.halt_position, d):>17}")

    if args.turning > 0:
        ts, xs = matched.turning_t[:args.turning], matched.turning_x[:args.turning]
        shown = int(np.sum(np.isfinite(ts)))
        print()
        if shown < args.turning:
            print(f"  turning points of the matched ansatz (v = 0, t > 0): only {shown} "
                  f"before it halts at t = {fmt(matched.halt_time, d)} s")
        else:
            print(f"  turning points of the matched ansatz (v = 0, t > 0), first {shown}:")
        if shown:
            print(f"  {'n':>3}  {'t [s]':>10}  {'x [m]':>10}  {'x/x0':>10}")
        for i in range(shown):
            rel = xs[i] / x0 if x0 != 0 else math.nan
            print(f"  {i + 1:>3}  {fmt(ts[i], d):>10}  {fmt(xs[i], d):>10}  "
                  f"{fmt(rel, d):>10}")

    if args.plot:
        path = plot_results(run, args.plot)
        print()
        print(f"  plot written to {path}")
    return 0


def _flags(args: argparse.Namespace) -> str:
    """The options that shape the start and its damping, as given: "--x0 0.2, --D 15"."""
    named = [("--x0", args.x0), ("--v0", args.v0), ("--mu", args.mu), ("--b", args.b),
             ("--D", args.D)]
    return ", ".join(f"{flag} {value:g}" for flag, value in named
                     if value != 0 or flag == "--x0")


def check_start(osc, args: argparse.Namespace) -> None:
    """ValueError naming --x0 / --v0 for a start that is not finite or whose amplitude is
    outside the models' range (``dampax._solve.AMPLITUDE_RANGE``)."""
    from .._solve import check_amplitude

    for flag, value in (("--x0", args.x0), ("--v0", args.v0)):
        if not math.isfinite(value):
            raise ValueError(f"{flag} must be a finite number, got {value:g}")
    try:
        check_amplitude(osc, args.x0, args.v0)
    except ValueError as err:
        raise ValueError(f"--x0 {args.x0:g}, --v0 {args.v0:g}: "
                         f"{str(err).removeprefix('x0, v0: ')}") from None
