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

from ._fit import add_arguments as _add_fit_arguments
from ._fit import run as _run_fit
from ._sensitivity import add_arguments as _add_sensitivity_arguments
from ._sensitivity import run as _run_sensitivity

PROG = "dampax"


def _fmt(value: float, digits: int, *, inf: str = "inf", nan: str = "-") -> str:
    """A number with ``digits`` significant digits; inf / nan spelled out."""
    if math.isnan(value):
        return nan
    if math.isinf(value):
        return inf if value > 0 else f"-{inf}"
    text = f"{value:.{digits}g}"
    return "0" if text in ("-0", "0") else text


def add_oscillator_arguments(parser: argparse.ArgumentParser, *, mu: float = 0.0,
                             D: float = 0.0,
                             start_title: str = "initial state (default: the papers' block)"):
    """Options --m --k --mu --b --D --g --x0 --v0 shared by the subcommands."""
    osc = parser.add_argument_group("oscillator (m x'' = -k x - mu m g sgn(x') - b x' - D x'|x'|)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=30.0,
                     help="spring stiffness [N/m] (default: %(default)s)")
    osc.add_argument("--mu", type=float, default=mu,
                     help="Coulomb friction coefficient (default: %(default)s)")
    osc.add_argument("--b", type=float, default=0.0,
                     help="viscous damping [kg/s] (default: %(default)s)")
    osc.add_argument("--D", type=float, default=D,
                     help="quadratic drag [kg/m] (default: %(default)s)")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2] (default: %(default)s)")
    start = parser.add_argument_group(start_title)
    start.add_argument("--x0", type=float, default=0.2,
                       help="initial displacement [m] (default: %(default)s)")
    start.add_argument("--v0", type=float, default=0.0,
                       help="initial velocity [m/s] (default: %(default)s)")


def _add_solve_arguments(parser: argparse.ArgumentParser) -> None:
    add_oscillator_arguments(parser)
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


# ----------------------------------------------------------------------------------------------
# dampax errormap

#: Grid and settings of ``dampax errormap`` (a few minutes on 2 cores with the reference) and
#: of ``--quick`` (a smoke run). The grids include d0 = 0 and d2 = 0 for the summary table.
ERRORMAP_DEFAULTS = dict(d0="0:0.1:16", d1="0", d2="0:0.75:16", phi0="0:7*pi/8:8",
                         periods=20.0, samples_per_period=64, chunk_size=128)
ERRORMAP_QUICK = dict(d0="0:0.1:4", d1="0", d2="0:0.75:4", phi0="0,pi/2",
                      periods=10.0, samples_per_period=32, chunk_size=32)

# the paper's stated ranges (Lelas & Pezer, Part I), per model: (d2 at d0 = 0, d0 at d2 = 0)
_PAPER_RANGES = {
    "matched": ("0.5 (III)", "0.05 (IV)*"),
    "undamped": ("0.1 (eq. 25)", "0.03 (eq. 25)"),
    "matched_tail": ("0.5 (III)", "0.05 (IV)"),
    "rizcallah": ("-", "-"),
    "coulomb_exact": ("-", "exact"),
}


def _add_errormap_arguments(parser: argparse.ArgumentParser) -> None:
    grid = parser.add_argument_group(
        "grid of dimensionless ratios (START:STOP:N = N values, both ends included; or a "
        "comma list; pi allowed, e.g. 0:7*pi/8:8; write a negative start as --phi0=-pi:0:5)")
    d = ERRORMAP_DEFAULTS
    q = ERRORMAP_QUICK
    grid.add_argument("--d0", metavar="START:STOP:N",
                      help=f"Coulomb ratio d0/(w0 A0) (default: {d['d0']}; quick: {q['d0']})")
    grid.add_argument("--d2", metavar="START:STOP:N",
                      help=f"quadratic ratio d2 A0/w0 (default: {d['d2']}; quick: {q['d2']})")
    grid.add_argument("--phi0", metavar="START:STOP:N",
                      help=f"initial phase [rad] (default: {d['phi0']}; quick: {q['phi0']}; "
                           "phi0 + pi gives the mirror-image motion)")
    grid.add_argument("--d1", metavar="START:STOP:N",
                      help=f"viscous ratio d1/w0 (default: {d['d1']})")
    grid.add_argument("--quick", action="store_true",
                      help="a 4 x 4 x 2 smoke run over 10 periods (explicit options win)")
    run = parser.add_argument_group("models and reference")
    run.add_argument("--models", default="matched,undamped,matched_tail,rizcallah",
                     help="comma list of matched, undamped, matched_tail, rizcallah, "
                          "coulomb_exact (default: %(default)s)")
    run.add_argument("--reference", default="reference", choices=("reference", "coulomb_exact"),
                     help="diffrax integration of eq. 3, or the exact half-swings (D = 0 only, "
                          "fast) (default: %(default)s)")
    run.add_argument("--periods", type=float,
                     help=f"time window cap in undamped periods (default: {d['periods']:g}; "
                          f"quick: {q['periods']:g})")
    run.add_argument("--samples-per-period", type=int, metavar="N",
                     help=f"time samples per period (default: {d['samples_per_period']}; "
                          f"quick: {q['samples_per_period']})")
    run.add_argument("--chunk-size", type=int, metavar="N",
                     help=f"grid points per device evaluated at once; bounds the memory "
                          f"(default: {d['chunk_size']})")
    out = parser.add_argument_group("output")
    out.add_argument("--out", default="errormap", metavar="DIR",
                     help="folder for errormap.nc and the heat maps (default: %(default)s)")
    out.add_argument("--no-progress", action="store_true", help="no progress bar")


def _ratio_text(value) -> str:
    if value is None:
        return "n/a"
    return _fmt(value, 3, nan="none")


def _defined_along(ds, model: str, along: str) -> bool:
    """Whether the model is valid beyond the first point of ``along`` (other ratios at 0)."""
    sel = {}
    for axis in ("d0_ratio", "d1_ratio", "d2_ratio"):
        if axis != along:
            zero = np.flatnonzero(np.asarray(ds[axis]) == 0.0)
            if zero.size == 0:
                return True
            sel[axis] = int(zero[0])
    valid = np.asarray(ds["valid"].sel(model=model).isel(sel).all("phi0"))
    return valid.size < 2 or bool(np.any(valid[1:]))


def _print_errormap_summary(ds) -> None:
    """Per model: the largest d2 (at d0 = 0) and d0 (at d2 = 0) with max error < 1 % / 5 %."""
    from ._maps import largest_ratio_below, worst_in_box

    def step(axis: str) -> str:
        values = np.unique(np.asarray(ds[axis], dtype=float))
        return _fmt(float(np.min(np.diff(values))), 3) if values.size > 1 else "-"

    models = [str(m) for m in np.asarray(ds["model"])]
    w = max(13, *(len(m) for m in models))
    group = 8 + 1 + 8 + 1 + 14
    print("  Largest ratio up to which max |x - x_ref| / A0 stays below 1 % and 5 % for every "
          "phi0 (d1/w0 = 0),")
    print(f"  on grid steps of {step('d2_ratio')} in d2 A0/w0 and {step('d0_ratio')} in "
          "d0/(w0 A0); beside the paper's stated ranges (section):")
    print()
    print(f"  {'':<{w}}  {'d2 A0/w0 at d0 = 0':^{group}}  {'d0/(w0 A0) at d2 = 0':^{group}}  "
          f"{'worst max error':>17}")
    print(f"  {'model':<{w}}  {'< 1 %':>8} {'< 5 %':>8} {'paper':>14}  {'< 1 %':>8} "
          f"{'< 5 %':>8} {'paper':>14}  {'d0<=0.03,d2<=0.25':>17}")
    for model in models:
        cells = []
        for along in ("d2_ratio", "d0_ratio"):
            defined = _defined_along(ds, model, along)
            for level in (0.01, 0.05):
                value = largest_ratio_below(ds, level, along=along, model=model)
                cells.append(_ratio_text(value) if defined else "-")
        paper = _PAPER_RANGES.get(model, ("-", "-"))
        box = worst_in_box(ds, model=model, d0_max=0.03 + 1e-12, d2_max=0.25 + 1e-12)
        box_text = "-" if math.isnan(box) else f"{100 * box:.2g} %"
        print(f"  {model:<{w}}  {cells[0]:>8} {cells[1]:>8} {paper[0]:>14}  "
              f"{cells[2]:>8} {cells[3]:>8} {paper[1]:>14}  {box_text:>17}")
    print()
    for line in (
            "paper (Lelas & Pezer, Part I): quadratic damping, matched ansatz \"excellent\" up to",
            "d2 A0/w0 = 0.5 (III); Coulomb damping, matched + Coulomb tail up to d0/(w0 A0) = "
            "0.05 (IV;",
            "* the plain ansatz there \"until the last few half-periods\"); combined damping, "
            "good for",
            "d0/(w0 A0) <= 0.03 with d2 A0/w0 <= 0.25 (V; last column: the worst grid point in "
            "that box);",
            "undamped-phase ansatz (earlier approach) for d0/(w0 A0) <~ 0.03, d2 A0/w0 <~ 0.1 "
            "(eq. 25).",
            "\"none\": not even the first grid value; \"-\": the model is not defined there; "
            "\"n/a\": no 0 on",
            "the other axis of the grid."):
        print(f"  {line}")


def _run_errormap(args: argparse.Namespace) -> int:
    """Error maps of the analytic models against the reference over a grid of damping ratios."""
    import time

    from ._maps import MODELS as MAP_MODELS
    from ._maps import _axis, error_map, parse_axis
    from ._plot import ERROR_MAP_METRICS, plot_error_map

    preset = ERRORMAP_QUICK if args.quick else ERRORMAP_DEFAULTS

    def pick(name):
        value = getattr(args, name)
        return preset[name] if value is None else value

    axes = {}
    for flag, name, ratio in (("--d0", "d0", True), ("--d1", "d1", True), ("--d2", "d2", True),
                              ("--phi0", "phi0", False)):
        axes[name] = _axis(flag, parse_axis(pick(name), flag), ratio=ratio)
    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    unknown = [m for m in models if m not in MAP_MODELS]
    if unknown or not models:
        raise ValueError(f"--models: unknown {unknown or args.models!r}; choose from "
                         f"{', '.join(MAP_MODELS)}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {str(out)!r} exists and is not a folder")
    periods = pick("periods")
    spp = pick("samples_per_period")
    chunk = pick("chunk_size")
    for flag, value, low in (("--periods", periods, 0.0), ("--samples-per-period", spp, 1),
                             ("--chunk-size", chunk, 0)):
        if not (math.isfinite(value) and value > low):
            raise ValueError(f"{flag} must be > {low:g}, got {value}")
    out.mkdir(parents=True, exist_ok=True)

    n = int(np.prod([a.size for a in axes.values()]))
    print(f"{PROG} errormap: {n} points ({axes['d0'].size} d0 x {axes['d1'].size} d1 x "
          f"{axes['d2'].size} d2 x {axes['phi0'].size} phi0), models {', '.join(models)}; "
          f"reference: {args.reference}; window <= {periods:g} periods, {spp} samples/period")
    start = time.perf_counter()
    ds = error_map(d0_ratio=axes["d0"], d1_ratio=axes["d1"], d2_ratio=axes["d2"],
                   phi0=axes["phi0"], models=models, periods=periods, samples_per_period=spp,
                   chunk_size=chunk, reference=args.reference, progress=not args.no_progress)
    elapsed = time.perf_counter() - start
    bad_ref = int((~ds["reference_valid"]).sum())
    if bad_ref:
        print(f"{PROG}: note: the reference is not valid at {bad_ref} of {n} points (budget or "
              "not defined there); their metrics are NaN", file=sys.stderr)
    path_nc = out / "errormap.nc"
    ds.to_netcdf(path_nc, engine="scipy")
    written = [path_nc]
    for metric in ERROR_MAP_METRICS:
        written.append(plot_error_map(ds, metric, out / f"{metric}.png"))
    print(f"  {n} points in {elapsed:.1f} s (compilation included); written: "
          + ", ".join(str(p) for p in written))
    print()
    _print_errormap_summary(ds)
    return 0


def _add_reproduce_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="reproduce", metavar="DIR",
                        help="output folder (default: %(default)s)")
    parser.add_argument("--figures", default="all", metavar="LIST",
                        help="figures to draw: numbers 2-21, ranges (8-10), 'rizcallah', "
                             "'all' or 'none', comma-separated (default: %(default)s)")
    parser.add_argument("--no-numbers", action="store_true",
                        help="skip numbers.csv / numbers.md")
    parser.add_argument("--format", default="png", metavar="EXT",
                        help="image format: png, pdf, svg, ... (default: %(default)s)")
    parser.add_argument("--dpi", type=int, default=110, help="resolution (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_reproduce(args: argparse.Namespace) -> int:
    """Redraw Figures 2-21 of Lelas & Pezer and Rizcallah's comparison; recompute quoted numbers."""
    import time

    from ._reproduce import reproduce, select_figures

    if args.dpi <= 0:
        raise ValueError(f"--dpi must be > 0, got {args.dpi}")
    select_figures(args.figures)  # fail on a bad list before any work
    start = time.perf_counter()
    res = reproduce(args.out, figures=args.figures, numbers=not args.no_numbers,
                    fmt=args.format, dpi=args.dpi, progress=not args.no_progress)
    elapsed = time.perf_counter() - start
    print(f"{PROG} reproduce: {len(res.figures)} figures"
          + (" and numbers.csv, numbers.md" if res.numbers_md else "")
          + f" in {Path(args.out)} ({elapsed:.0f} s)")
    if res.numbers:
        counts = {s: sum(r.status == s for r in res.numbers)
                  for s in ("ok", "explained", "MISMATCH")}
        print(f"  {len(res.numbers)} quoted values: {counts['ok']} within the printed rounding, "
              f"{counts['explained']} known discrepancies of the papers' text (see numbers.md), "
              f"{counts['MISMATCH']} mismatched")
        for r in res.numbers:
            if r.status == "MISMATCH":
                print(f"  MISMATCH: {r.source}: {r.quantity}: paper {r.quoted}, "
                      f"dampax {r.computed:.6g}")
        return 1 if counts["MISMATCH"] else 0
    return 0


#: name -> (add_arguments(parser), run(args) -> exit status); the first docstring line of
#: ``run`` is the subcommand's help.
SUBCOMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                             Callable[[argparse.Namespace], int]]] = {
    "solve": (_add_solve_arguments, _run_solve),
    "errormap": (_add_errormap_arguments, _run_errormap),
    "sensitivity": (_add_sensitivity_arguments, _run_sensitivity),
    "fit": (_add_fit_arguments, _run_fit),
    "reproduce": (_add_reproduce_arguments, _run_reproduce),
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
