"""``dampax fit``: fit damping constants to a measured trace (or a table of maxima), print the
lmfit-style report and the ranking of the candidate damping models, write fit.json and
fit.png (and with --posterior posterior.nc and corner.png).

Exit status: 0 the fit succeeded and the model describes the data; 2 invalid input (one line
on stderr, no traceback: also a trace without a free decay in it); 3 the fit failed (the reason
is the first line of the report); 4 the fit converged but the model does not describe the data.
The results are written in every case but 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings

import numpy as np

from .._fit import (
    FIT_MODELS,
    FREE,
    LOSSES,
    METHOD_NAMES,
    MODELS,
    OPTIMIZERS,
    check_free,
    compare_envelope_models,
    compare_models,
    example_trace,
    fit,
    fit_envelope,
)
from .._io import write_text
from .._oscillator import Oscillator
from .._trace import load_trace
from ._common import PROG, fmt, prepare_out_dir, split_names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dampax fit``."""
    parser.epilog = (
        "Without --k the fit is per unit mass: w0 is fitted, b/m [1/s] and D/m [1/unit].\n"
        "exit status:\n"
        "  0  the fit succeeded and the model describes the data\n"
        "  2  invalid input, one line on stderr (also a trace without a free decay in it)\n"
        "  3  the fit failed (the reason is the report's first line)\n"
        "  4  the fit converged but the model does not describe the data\n"
        "The results are written in every case but 2.")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("path", nargs="?", help="text file with the trace (time and position "
                        "columns), or with a table of maxima for --envelope")
    parser.add_argument("--example", action="store_true",
                        help="fit a synthetic trace with known constants (m = 0.2 kg, "
                             "k = 15 N/m, mu = 0.002, D = 0.02 kg/m, noise 0.2 mm)")
    read = parser.add_argument_group("reading the file")
    read.add_argument("--time", metavar="COL", help="time column, name or index (default: 0)")
    read.add_argument("--position", metavar="COL",
                      help="position column, name or index (default: 1)")
    read.add_argument("--rate", metavar="HZ|auto",
                      help="rebuild time from the sample index: a rate [1/s], or 'auto' for "
                           "buffered time stamps")
    read.add_argument("--delimiter", help="column separator (default: detected)")
    read.add_argument("--scale", type=float, default=1.0,
                      help="factor applied to the positions (default: %(default)s)")
    read.add_argument("--units", default=None,
                      help="unit of the positions, for the report (m, cm, mm, deg, rad, ...; "
                           "default: the unit in the position column's name, e.g. "
                           "'Angle(deg)', else m)")
    osc = parser.add_argument_group(
        "oscillator (fixed constants; without --k the fit is per unit mass: w0 fitted, "
        "b/m in 1/s and D/m in 1/unit)")
    osc.add_argument("--m", type=float, default=None,
                     help="mass [kg]; with it b and D are reported in kg/s and kg/m (positions "
                          "in lengths); default: unit mass, per-mass b/m and D/m")
    osc.add_argument("--k", type=float, default=None,
                     help="stiffness [N/m] (needs --m): w0 = sqrt(k/m) fixed unless "
                          "--fit-omega0; default: w0 fitted from the data")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2], converts the Coulomb term d0 "
                          "to mu (default: %(default)s)")
    model = parser.add_argument_group("model and fit")
    model.add_argument("--free", default="mu,D",
                       help="constants to fit, comma list of mu, b, D and k3 (the cubic "
                            "stiffness, profiled; trace fits only) (default: %(default)s)")
    model.add_argument("--model", default="ansatz", choices=MODELS,
                       help="; ".join(f"{name}: {FIT_MODELS[name].description}"
                                      for name in MODELS) + " (default: %(default)s)")
    model.add_argument("--fit-omega0", action="store_true",
                       help="with --m and --k: also fit w0 (k = m w0^2), needed when k/m is not "
                            "known exactly (without --k w0 is always fitted)")
    model.add_argument("--no-offset", action="store_true",
                       help="do not fit the equilibrium offset (envelope fits have none)")
    model.add_argument("--loss", default="linear", choices=LOSSES,
                       help="soft_l1 for traces with outliers (default: %(default)s)")
    model.add_argument("--optimizer", default="lm", choices=OPTIMIZERS,
                       help="; ".join(f"{name}: {METHOD_NAMES[name]}" for name in OPTIMIZERS)
                            + " (default: %(default)s)")
    model.add_argument("--start", default="auto",
                       help="fit start: auto (first extreme after the largest excursion), "
                            "data (first sample) or a time [s] (default: %(default)s)")
    model.add_argument("--end", type=float, default=None, help="fit end time [s]")
    model.add_argument("--envelope", action="store_true",
                       help="the file holds successive maxima (t, amplitude): envelope fit")
    model.add_argument("--omega0", type=float, default=None,
                       help="--envelope: angular frequency (default: from the peak spacing)")
    model.add_argument("--no-compare", action="store_true",
                       help="skip the ranking of candidate damping models")
    model.add_argument("--starts", type=int, default=32,
                       help="global starts: jittered starts around the turning-point guess, "
                            "optimised in one vmapped batch (default: %(default)s; 1: the "
                            "guess alone)")
    model.add_argument("--seed", type=int, default=0,
                       help="seed of the jittered starts and of the posterior's chains "
                            "(default: %(default)s)")
    model.add_argument("--max-steps", type=int, default=None,
                       help="optimizer step budget per optimisation (default: 256 for lm)")
    unc = parser.add_argument_group("uncertainty")
    unc.add_argument("--intervals", action="store_true",
                     help="print confidence intervals that allow for correlated residuals "
                          "(FitResult.conf_interval: Newey-West sandwich) at --level")
    unc.add_argument("--level", type=float, default=0.95,
                     help="two-sided level of --intervals and of the posterior summary "
                          "(default: %(default)s)")
    unc.add_argument("--posterior", action="store_true",
                     help="also sample the posterior with NUTS (blackjax, AR(1) noise) and "
                          "write posterior.nc and corner.png")
    unc.add_argument("--draws", type=int, default=1000,
                     help="--posterior: draws per chain (default: %(default)s)")
    unc.add_argument("--chains", type=int, default=4,
                     help="--posterior: chains (default: %(default)s)")
    out = parser.add_argument_group("output")
    out.add_argument("--out", metavar="DIR", default="fit",
                     help="folder for fit.json and fit.png (default: %(default)s)")


def _parse_rate(text):
    """--rate: None, "auto" or a rate > 0 [1/s]."""
    if text is None or text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--rate must be a number or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--rate must be > 0, got {text!r}")
    return value


def _parse_start(text):
    """--start: "auto", "data" or a time [s]."""
    if text in ("auto", "data"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--start must be auto, data or a time, got {text!r}") from None


#: exit status of a fit that failed / of a model that does not describe the data
EXIT_FAILED, EXIT_INADEQUATE = 3, 4


def _cli_words(text: str) -> str:
    """A library message with the Python argument names replaced by the command's flags."""
    for api, flag in (("fit_omega0=True", "--fit-omega0"), ("fit_omega0=False", "--k"),
                      ("fit_omega0", "--fit-omega0"), ("loss=", "--loss "),
                      ("load_trace(rate=...), ", ""), ("max_steps", "--max-steps")):
        text = text.replace(api, flag)
    return text


def _oscillator(args):
    """(oscillator or None, fit_omega0) from --m, --k, --g, --fit-omega0: no --k means a fit
    per unit mass (or per the given --m) with w0 from the data."""
    if args.k is not None and args.m is None:
        raise ValueError("--k needs --m (w0 = sqrt(k/m)); without both, w0 is fitted per "
                         "unit mass")
    if args.m is None:
        if args.g != 9.81:
            return Oscillator(m=1.0, k=1.0, g=args.g), True
        return None, True
    if args.k is None:  # mass known, w0 from the data (k is a placeholder, not used)
        return Oscillator(m=args.m, k=args.m, g=args.g), True
    return Oscillator(m=args.m, k=args.k, g=args.g), bool(args.fit_omega0)


def run(args: argparse.Namespace) -> int:
    """Fit damping constants to a measured trace; print the report and the model ranking.

    Returns:
        0 success; 3 the fit failed (``success = False``, the reason on the report's first
        line); 4 the fit converged but the model does not describe the data. Invalid input
        raises ValueError (status 2 from ``dampax._cli.main``).
    """
    free = check_free(split_names(args.free), allowed=FREE)
    if not free:
        raise ValueError("--free: name at least one of mu, b, D")
    if args.example == bool(args.path):
        raise ValueError("give a PATH or --example (one of them)")
    out_dir = prepare_out_dir(args.out)
    if args.starts < 1:
        raise ValueError(f"--starts must be >= 1, got {args.starts}")
    if args.max_steps is not None and args.max_steps < 1:
        raise ValueError(f"--max-steps must be >= 1, got {args.max_steps}")
    if not 0.0 < args.level < 1.0:
        raise ValueError(f"--level must be in (0, 1), got {args.level}")
    if args.posterior and (args.envelope or args.draws < 10 or args.chains < 1):
        raise ValueError("--posterior needs a trace (not --envelope), --draws >= 10 and "
                         "--chains >= 1")
    start = _parse_start(args.start)
    truth = None
    units = args.units
    if args.example:
        print(f"{PROG} fit --example: generating the synthetic trace with the reference "
              "integrator ...")
        trace, truth = example_trace()
        osc, fit_omega0 = Oscillator(m=truth["m"], k=truth["k"]), bool(args.fit_omega0)
    else:
        trace = load_trace(args.path, time=args.time, position=args.position,
                           rate=_parse_rate(args.rate), delimiter=args.delimiter,
                           scale=args.scale)
        osc, fit_omega0 = _oscillator(args)
    print(f"{PROG} fit: {trace!r}")
    if trace.n_dropped:
        print(f"{PROG}: note: {trace.n_dropped} unreadable rows were dropped", file=sys.stderr)
    began = time.perf_counter()
    post = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if args.envelope:
            kw = dict(omega0=args.omega0, oscillator=osc, offset=False, loss=args.loss,
                      optimizer=args.optimizer, max_steps=args.max_steps, units=units)
            result = fit_envelope(trace, free=free, **kw)
            comparison = None if args.no_compare else compare_envelope_models(trace, **kw)
        else:
            kw = dict(oscillator=osc, fit_omega0=fit_omega0, offset=not args.no_offset,
                      start=start, end=args.end, loss=args.loss, optimizer=args.optimizer,
                      max_steps=args.max_steps, units=units, starts=args.starts,
                      seed=args.seed)
            result = fit(trace, free=free, model=args.model, **kw)
            # the ranking fits the candidates with the ansatz: this fit is one of them
            done = {free: result} if args.model == "ansatz" else None
            comparison = None if args.no_compare else compare_models(
                trace, model="ansatz", fitted=done, **kw)
            if args.posterior:
                from .._fit import posterior

                post = posterior(trace, oscillator=osc, free=free, fit_omega0=fit_omega0,
                                 offset=not args.no_offset, start=start, end=args.end,
                                 num_samples=args.draws, num_chains=args.chains,
                                 seed=args.seed, units=units, start_fit=result)
    for w in {str(w.message) for w in caught}:
        print(f"{PROG}: warning: {_cli_words(w)}", file=sys.stderr)
    elapsed = time.perf_counter() - began
    print()
    print(_cli_words(result.report()))
    if args.intervals:
        print()
        print(f"  confidence intervals at {args.level:g} (allowing for correlated residuals):")
        for name, (lo, hi) in result.conf_interval(args.level).items():
            print(f"    {name:<7} [{fmt(lo, 6)}, {fmt(hi, 6)}]   value "
                  f"{fmt(result.params[name], 6)}   delta-method stderr "
                  f"{fmt(result.stderr[name], 3)}")
    if truth is not None:
        print()
        print("  truth vs estimate (synthetic example):")
        for name in ("mu", "D"):
            est, err = result.params[name], result.stderr[name]
            print(f"    {name:<3} true {fmt(truth[name], 6)}   fitted {fmt(est, 6)} +/- "
                  f"{fmt(err, 2)}   ({(est - truth[name]) / err:+.2f} stderr)")
        print(f"    noise true {fmt(truth['noise'], 3)}   rms residual {fmt(result.rms, 3)}")
    if comparison is not None:
        print()
        if args.model != "ansatz" and not args.envelope:
            print("(ranking with the ansatz model)")
        print(comparison.report())
    summary = {"fit": result.to_dict(), "ranking": comparison.to_dict() if comparison else None,
               "truth": truth, "trace": {"source": trace.source, "n": len(trace),
                                         "n_dropped": trace.n_dropped, "rate": trace.rate}}
    written = [out_dir / "fit.json", out_dir / "fit.png"]
    if args.intervals or not args.envelope:
        try:
            summary["fit"]["conf_interval"] = {
                "level": args.level,
                "intervals": {k: list(v) for k, v in result.conf_interval(args.level).items()}}
        except (ValueError, np.linalg.LinAlgError):
            pass
    if post is not None:
        print()
        print(post.report(args.level))
        summary["posterior"] = post.summary(args.level)
        written += [post.to_netcdf(out_dir / "posterior.nc"),
                    post.corner(out_dir / "corner.png")]
    write_text(out_dir / "fit.json", json.dumps(summary, indent=2, default=_jsonable))
    result.plot(out_dir / "fit.png")
    print()
    print(f"  {elapsed:.1f} s (compilation included); written: "
          f"{', '.join(str(p) for p in written)}")
    if not result.success:
        print(f"{PROG}: fit failed: {_cli_words(result.reason)}", file=sys.stderr)
        return EXIT_FAILED
    if not result.adequate:
        print(f"{PROG}: the model does not describe the data: "
              f"{_cli_words('; '.join(result.inadequacy))}", file=sys.stderr)
        return EXIT_INADEQUATE
    return 0


def _jsonable(value):
    """json.dumps default: numpy numbers as floats (NaN as null)."""
    v = float(value)
    return v if math.isfinite(v) else None
