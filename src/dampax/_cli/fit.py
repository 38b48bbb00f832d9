"""``dampax fit``: fit damping constants to a measured trace (or a table of maxima), print the
lmfit-style report and the ranking of the candidate damping models, write fit.json and
fit.png."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

from .._fit import (
    FIT_MODELS,
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
from .._oscillator import Oscillator
from .._trace import load_trace
from ._common import PROG, fmt, split_names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dampax fit``."""
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
    osc = parser.add_argument_group("oscillator (fixed constants)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=1.0,
                     help="stiffness [N/m] (default: %(default)s; use --fit-omega0 when "
                          "unknown)")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2], converts the Coulomb term d0 "
                          "to mu (default: %(default)s)")
    model = parser.add_argument_group("model and fit")
    model.add_argument("--free", default="mu,D",
                       help="damping constants to fit, comma list of mu, b, D "
                            "(default: %(default)s)")
    model.add_argument("--model", default="ansatz", choices=MODELS,
                       help="; ".join(f"{name}: {FIT_MODELS[name].description}"
                                      for name in MODELS) + " (default: %(default)s)")
    model.add_argument("--fit-omega0", action="store_true",
                       help="also fit w0 (k = m w0^2); needed when k/m is not known exactly")
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


def run(args: argparse.Namespace) -> int:
    """Fit damping constants to a measured trace; print the report and the model ranking."""
    free = check_free(split_names(args.free))
    if not free:
        raise ValueError("--free: name at least one of mu, b, D")
    if args.example == bool(args.path):
        raise ValueError("give a PATH or --example (one of them)")
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out: {str(out_dir)!r} exists and is not a folder")
    start = _parse_start(args.start)
    truth = None
    if args.example:
        print(f"{PROG} fit --example: generating the synthetic trace with the reference "
              "integrator ...")
        trace, truth = example_trace()
        osc = Oscillator(m=truth["m"], k=truth["k"])
    else:
        trace = load_trace(args.path, time=args.time, position=args.position,
                           rate=_parse_rate(args.rate), delimiter=args.delimiter,
                           scale=args.scale)
        osc = Oscillator(m=args.m, k=args.k, g=args.g)
    print(f"{PROG} fit: {trace!r}")
    if trace.n_dropped:
        print(f"{PROG}: note: {trace.n_dropped} unreadable rows were dropped", file=sys.stderr)
    began = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if args.envelope:
            kw = dict(omega0=args.omega0, oscillator=osc, offset=False, loss=args.loss,
                      optimizer=args.optimizer)
            result = fit_envelope(trace, free=free, **kw)
            comparison = None if args.no_compare else compare_envelope_models(trace, **kw)
        else:
            kw = dict(oscillator=osc, fit_omega0=args.fit_omega0, offset=not args.no_offset,
                      start=start, end=args.end, loss=args.loss, optimizer=args.optimizer)
            result = fit(trace, free=free, model=args.model, **kw)
            comparison = None if args.no_compare else compare_models(trace, model="ansatz",
                                                                     **kw)
    for w in {str(w.message) for w in caught}:
        print(f"{PROG}: warning: {w}", file=sys.stderr)
    elapsed = time.perf_counter() - began
    print()
    print(result.report())
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
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {"fit": result.to_dict(), "ranking": comparison.to_dict() if comparison else None,
               "truth": truth, "trace": {"source": trace.source, "n": len(trace),
                                         "n_dropped": trace.n_dropped, "rate": trace.rate}}
    (out_dir / "fit.json").write_text(json.dumps(summary, indent=2))
    result.plot(out_dir / "fit.png")
    print()
    print(f"  {elapsed:.1f} s (compilation included); written: {out_dir / 'fit.json'}, "
          f"{out_dir / 'fit.png'}")
    return 0
