"""The ``dampax`` command line: ``dampax solve`` prints the models' key numbers and plots them.

Subcommands live in :data:`SUBCOMMANDS`, name -> (add_arguments, run); ``run(args)`` returns the
exit status. A ValueError from dampax (bad input, a model that does not exist) is reported as
one line, ``dampax: error: <message>``, with exit status 2 (as argparse does for bad syntax).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

PROG = "dampax"


def _fmt(value: float, digits: int, *, inf: str = "inf", nan: str = "-") -> str:
    """A number with ``digits`` significant digits; inf / nan spelled out."""
    if math.isnan(value):
        return nan
    if math.isinf(value):
        return inf if value > 0 else f"-{inf}"
    text = f"{value:.{digits}g}"
    return "0" if text in ("-0", "0") else text


def _add_solve_arguments(parser: argparse.ArgumentParser) -> None:
    osc = parser.add_argument_group("oscillator (m x'' = -k x - mu m g sgn(x') - b x' - D x'|x'|)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=30.0,
                     help="spring stiffness [N/m] (default: %(default)s)")
    osc.add_argument("--mu", type=float, default=0.0,
                     help="Coulomb friction coefficient (default: %(default)s)")
    osc.add_argument("--b", type=float, default=0.0,
                     help="viscous damping [kg/s] (default: %(default)s)")
    osc.add_argument("--D", type=float, default=0.0,
                     help="quadratic drag [kg/m] (default: %(default)s)")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2] (default: %(default)s)")
    start = parser.add_argument_group("initial state (default: the papers' block)")
    start.add_argument("--x0", type=float, default=0.2,
                       help="initial displacement [m] (default: %(default)s)")
    start.add_argument("--v0", type=float, default=0.0,
                       help="initial velocity [m/s] (default: %(default)s)")
    out = parser.add_argument_group("output")
    out.add_argument("--turning", type=int, default=6, metavar="N",
                     help="turning points of the matched ansatz to print (default: %(default)s)")
    out.add_argument("--digits", type=int, default=4, metavar="N",
                     help="significant digits printed (default: %(default)s)")
    out.add_argument("--plot", metavar="FILE.png",
                     help="also save x(t) and E(t) of every model to this file")
    out.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                     help="time span of the plot and the reference integration "
                          "(default: a bit past the latest halt, or 6 undamped periods)")
    out.add_argument("--no-reference", action="store_true",
                     help="skip the reference integrator (diffrax)")


def _check_plot_path(path: str) -> None:
    """Fail before any solving when the plot cannot be written (folder, file format)."""
    from matplotlib.backend_bases import FigureCanvasBase

    target = Path(path)
    if not target.parent.is_dir():
        raise ValueError(f"--plot: folder {str(target.parent)!r} does not exist")
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = target.suffix.lstrip(".").lower()
    if suffix not in formats:
        raise ValueError(f"--plot: unsupported file type {target.suffix!r} of {path!r}; "
                         f"use one of {', '.join('.' + f for f in sorted(formats))}")


def _run_solve(args: argparse.Namespace) -> int:
    """Print the amplitudes, damping ratios, halt times and turning points of every model."""
    import dampax as dp

    from ._plot import applicable_models, damping_ratios, plot_results, run_models

    if args.turning < 0:
        raise ValueError(f"--turning must be >= 0, got {args.turning}")
    if not 1 <= args.digits <= 17:
        raise ValueError(f"--digits must be between 1 and 17, got {args.digits}")
    if args.plot:
        _check_plot_path(args.plot)
    osc = dp.Oscillator(m=args.m, k=args.k, mu=args.mu, b=args.b, D=args.D, g=args.g)
    models = applicable_models(osc, reference=not args.no_reference)
    run = run_models(osc, args.x0, args.v0, models=models, n_turning=max(args.turning, 1),
                     t_end=args.t_end)
    matched = run.results["matched"]
    if matched.error is not None:
        raise ValueError(matched.error)
    for note in run.notes:
        print(f"{PROG}: note: {note}", file=sys.stderr)

    d = args.digits
    x0, v0 = run.x0, run.v0
    w0 = float(np.asarray(osc.omega0))
    A0 = math.hypot(x0, v0 / w0)
    phi0 = math.atan2(-v0 / w0, x0) if A0 > 0 else 0.0
    r0, r1, r2 = damping_ratios(osc, x0, v0)
    sol = matched.solution
    rows = [
        ("A", float(np.asarray(sol.amplitude)), "m", "matched amplitude (eq. 22)"),
        ("phi", float(np.asarray(sol.phase)), "rad", "matched phase (eq. 23)"),
        ("A0", A0, "m", "undamped amplitude, x0 = A0 cos(phi0)"),
        ("phi0", phi0, "rad", "undamped phase, v0 = -w0 A0 sin(phi0)"),
        ("d0/(w0 A0)", r0, "", "Coulomb ratio, d0 = 2 mu g/(pi w0)"),
        ("d1/w0", r1, "", "viscous ratio, d1 = b/(2m)"),
        ("d2 A0/w0", r2, "", "quadratic ratio, d2 = 4 D w0/(3 pi m)"),
        ("xc", float(np.asarray(osc.xc)), "m", "sticking band |x| <= xc = mu g/w0^2"),
        ("w0", w0, "rad/s", f"undamped period T0 = {_fmt(2 * math.pi / w0, d)} s"),
    ]
    print(f"{PROG} solve: m = {args.m:g} kg, k = {args.k:g} N/m, mu = {args.mu:g}, "
          f"b = {args.b:g} kg/s, D = {args.D:g} kg/m, g = {args.g:g} m/s^2, "
          f"x0 = {x0:g} m, v0 = {v0:g} m/s")
    print()
    for name, value, unit, what in rows:
        print(f"  {name:<11} = {_fmt(value, d):>10} {unit:<6} {what}")
    print()

    width = max(len(r.label) for r in run.results.values())
    print(f"  {'model':<{width}}  {'halt time [s]':>13}  {'halt position [m]':>17}")
    for r in run.results.values():
        if r.error is not None:
            reason = "not available" if r.name == "reference" else f"not available: {r.error}"
            print(f"  {r.label:<{width}}  {reason}")
            continue
        print(f"  {r.label:<{width}}  {_fmt(r.halt_time, d, inf='never'):>13}  "
              f"{_fmt(r.halt_position, d):>17}")

    if args.turning > 0:
        ts, xs = matched.turning_t[:args.turning], matched.turning_x[:args.turning]
        shown = int(np.sum(np.isfinite(ts)))
        print()
        if shown < args.turning:
            print(f"  turning points of the matched ansatz (v = 0, t > 0): only {shown} "
                  f"before it halts at t = {_fmt(matched.halt_time, d)} s")
        else:
            print(f"  turning points of the matched ansatz (v = 0, t > 0), first {shown}:")
        if shown:
            print(f"  {'n':>3}  {'t [s]':>10}  {'x [m]':>10}  {'x/x0':>10}")
        for i in range(shown):
            rel = xs[i] / x0 if x0 != 0 else math.nan
            print(f"  {i + 1:>3}  {_fmt(ts[i], d):>10}  {_fmt(xs[i], d):>10}  "
                  f"{_fmt(rel, d):>10}")

    if args.plot:
        path = plot_results(run, args.plot)
        print()
        print(f"  plot written to {path}")
    return 0


#: name -> (add_arguments(parser), run(args) -> exit status); the first docstring line of
#: ``run`` is the subcommand's help.
SUBCOMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                             Callable[[argparse.Namespace], int]]] = {
    "solve": (_add_solve_arguments, _run_solve),
}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one subparser per entry of :data:`SUBCOMMANDS`.

    Returns:
        An ``argparse.ArgumentParser``; parsed arguments carry the subcommand's ``run``.
    """
    from . import __version__

    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Harmonic oscillator with Coulomb, viscous and quadratic damping: analytic "
                    "models (Lelas & Pezer; Rizcallah) against the exact motion.",
        epilog="Each run compiles the models with JAX (often 10 s or more); set "
               "JAX_COMPILATION_CACHE_DIR to a folder to reuse part of that work across runs.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (add_arguments, run) in SUBCOMMANDS.items():
        summary = (run.__doc__ or "").strip().splitlines()[0] if run.__doc__ else None
        p = sub.add_parser(name, help=summary, description=summary)
        add_arguments(p)
        p.set_defaults(run=run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``dampax`` command line.

    Arguments:
        argv: the arguments without the program name; default ``sys.argv[1:]``.

    Returns:
        The exit status: 0 on success, 2 on invalid input (one line on stderr). Syntax errors
        and ``--help`` exit through argparse (SystemExit with status 2 / 0).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (ValueError, OSError) as err:
        message = " ".join(str(err).split())
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
