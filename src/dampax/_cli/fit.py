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
import contextlib
import json
import math
import sys
import time
import warnings

import numpy as np

from dampax_cli import _figures
from dampax_cli._arguments import add_fit_arguments as add_arguments  # noqa: F401 (SUBCOMMANDS)

from .._fit import (
    FREE,
    LeastSquares,
    Window,
    check_free,
    compare_envelope_models,
    compare_models,
    example_trace,
    fit,
    fit_envelope,
    full_starts,
)
from .._fit._api import spacing_omega0
from .._io import atomic_path, write_text
from .._oscillator import Oscillator
from .._plot_fit import figure_data, import_figure_modules, plot_fit, plot_joint_fit
from .._trace import load_trace
from ._common import (
    PROG,
    beside,
    compile_clock,
    error,
    fmt,
    not_used,
    prepare_out_dir,
    split_names,
)


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

#: global starts of each candidate of ``--example``'s ranking (its numbers are those of 32
#: starts: every start of the example's fit reaches the same optimum)
EXAMPLE_RANKING_STARTS = 1


def _cli_words(text: str) -> str:
    """A library message with the Python argument names replaced by the command's flags."""
    for api, flag in (("fit_omega0=True", "--fit-omega0"), ("fit_omega0=False", "--k"),
                      ("the stiffness (the oscillator's k)", "the stiffness (--m and --k)"),
                      ("hold k3 (k3=...)", "drop k3 from --free"),
                      ("fit_omega0", "--fit-omega0"), ("loss=", "--loss "),
                      ("load_trace(rate=...), ", ""),
                      ("load_trace(time=..., position=...), ", ""),
                      ("LeastSquares.max_steps", "--max-steps"),
                      ("max_steps", "--max-steps"), ("LeastSquares.starts", "--starts"),
                      ("LeastSquares.", "--"), ("Window.", "--")):
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
    """:func:`run_fit`, with the library's argument names in its errors replaced by the
    command's flags (``Window.end`` -> ``--end``, ``LeastSquares.seed`` -> ``--seed``)."""
    try:
        return run_fit(args)
    except ValueError as err:
        raise ValueError(_cli_words(str(err))) from None


def run_fit(args: argparse.Namespace) -> int:
    """Fit damping constants to a measured trace; print the report and the model ranking.

    Returns:
        0 success; 3 the fit failed (``success = False``, the reason on the report's first
        line); 4 the fit converged but the model does not describe the data. Invalid input
        raises ValueError (status 2 from ``dampax._cli.main``).
    """
    free = check_free(split_names(args.free), allowed=FREE)
    if not free:
        raise ValueError("--free: name at least one of mu, b, D")
    paths = [args.path] if isinstance(args.path, str) else list(args.path or [])
    if args.example == bool(paths):
        raise ValueError("give a PATH or --example (one of them)")
    if not 0.0 < args.level < 1.0:  # (before any work, for a joint fit too)
        raise ValueError(f"--level must be in (0, 1), got {args.level}")
    if len(paths) > 1:
        return _run_joint(args, paths, free)
    if args.shared is not None:
        raise ValueError("--shared needs two or more trace files (a joint fit of several runs)")
    args.path = paths[0] if paths else None
    if args.example:  # (they were ignored: the example's trace and oscillator are its own)
        not_used(args, "--example", ("--envelope", "--m", "--k", "--g", "--scale", "--time",
                                     "--position", "--rate", "--delimiter"), add_arguments)
    if args.envelope:  # an envelope fit has no window, model, w0 fit or global starts
        not_used(args, "--envelope", ("--start", "--end", "--model", "--fit-omega0",
                                      "--starts", "--seed"), add_arguments)
    else:
        not_used(args, "a trace fit (it is --envelope's)", ("--omega0",), add_arguments)
    if args.m is None and args.g != 9.81:  # (per unit mass, yet reported in kg/s, kg/m)
        raise ValueError("--g needs --m: a fit without a mass is per unit mass (mu from the "
                         "friction deceleration mu g with g = 9.81 m/s^2)")
    out_dir = prepare_out_dir(args.out)
    if args.posterior and (args.envelope or args.draws < 10 or args.chains < 1
                           or args.warmup < 10):
        raise ValueError("--posterior needs a trace (not --envelope), --draws >= 10, "
                         "--chains >= 1 and --warmup >= 10")
    if (args.mu_s is not None or "mu_s" in free) and (args.model == "ansatz"
                                                       or args.envelope):
        raise ValueError("--mu-s and --free ...,mu_s (static friction) need the exact model "
                         "(--model auto or reference) and a trace (the ansatz assumes "
                         "mu_s = mu)")
    start = _parse_start(args.start)
    truth = None
    units = args.units
    try:  # the flags map onto dp.fit's option objects, checked when made
        window = Window(start=start, end=args.end, units=units).checked()
        solver = LeastSquares(loss=args.loss, optimizer=args.optimizer,
                              max_steps=args.max_steps, starts=args.starts,
                              seed=args.seed).checked()
    except ValueError as err:
        raise ValueError(_cli_words(str(err))) from None
    if args.example:
        print(f"{PROG} fit --example: generating the synthetic trace with the reference "
              "integrator ...")
        trace, truth = example_trace()
        osc, fit_omega0 = Oscillator(m=truth["m"], k=truth["k"]), bool(args.fit_omega0)
    else:
        with warnings.catch_warnings():  # (the dropped rows are noted below)
            warnings.simplefilter("ignore")
            trace = load_trace(args.path, time=args.time, position=args.position,
                               rate=_parse_rate(args.rate), delimiter=args.delimiter,
                               scale=args.scale)
        osc, fit_omega0 = _oscillator(args)
    print(f"{PROG} fit: {trace!r}")
    if trace.n_dropped:
        print(f"{PROG}: note: {trace.n_dropped} unreadable rows were dropped", file=sys.stderr)
    began = time.perf_counter()
    with compile_clock() as clock, warnings.catch_warnings(record=True) as caught, \
            _columns_named(None if args.example else trace):
        warnings.simplefilter("always")
        if args.envelope:
            # without --k the oscillator's k is a placeholder: w0 from the maxima's spacing
            omega0 = args.omega0 if args.omega0 is not None or args.k is not None else \
                spacing_omega0(trace.t, trace.x)
            kw = dict(omega0=omega0, oscillator=osc, offset=False, loss=args.loss,
                      optimizer=args.optimizer, max_steps=args.max_steps, units=units)
            result = fit_envelope(trace, free=free, **kw)

            def rest():
                return (None if args.no_compare else compare_envelope_models(trace, **kw)), None
        else:
            kw = dict(oscillator=osc, fit_omega0=fit_omega0, offset=not args.no_offset,
                      window=window, solver=solver)
            # the ranking (the ansatz's fits) does not wait for this fit unless it is one of
            # them: it runs beside it (two fits at once: _fit._linalg's note on threads)
            early = not args.no_compare and args.model != "ansatz"
            ranking = beside(_ranking_early, args, trace, kw) if early else _no_thread()
            # (the ranking builds the ansatz's program: the fit's start runs it too)
            with ranking as ranked, full_starts() if early else contextlib.nullcontext():
                result = fit(trace, free=free, model=args.model, mu_s=args.mu_s, **kw)

            def rest():
                comparison = ranked.result() if early else _ranking(args, trace, result, kw)
                return comparison, _posterior(args, trace, result, free, kw, start)
        with beside(_fit_figure, result, out_dir / "fit.png") as figure:
            comparison, post = rest()  # the ranking (and posterior) while the figure is drawn
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
        if result.model != "ansatz" and not args.envelope:
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
    failed = _write_outputs(args, result, post, summary, written, out_dir, elapsed, "fit",
                            compiling=clock.text(), figure=figure,
                            data="" if args.example else trace.describe_columns())
    if failed is not None:
        return failed
    if not result.adequate:
        error(f"{PROG}: the model does not describe the data: "
              f"{_cli_words('; '.join(result.inadequacy))}")
        return EXIT_INADEQUATE
    return 0


@contextlib.contextmanager
def _no_thread():
    """The stand-in for :func:`beside` where nothing runs beside the block (yields None)."""
    yield None


def _ranking(args: argparse.Namespace, trace, result, kw: dict):
    """The candidate models' ranking with the ansatz (None with --no-compare); ``result``:
    this fit where it is the ansatz's and one of the candidates (not fitted again), else None.
    ``kw`` holds the fit's oscillator, fit_omega0, offset, window and solver."""
    if args.no_compare:
        return None
    done = {result.free: result} if result is not None and result.model == "ansatz" else None
    if args.example:
        # the example's cost is smooth: its fit's global starts all reach one optimum, and so
        # does each candidate's turning-point guess (the ranking is the same with 32 starts
        # per candidate, 6x the work); the reported fit keeps --starts
        kw = dict(kw, solver=kw["solver"]._replace(starts=EXAMPLE_RANKING_STARTS))
    return compare_models(trace, model="ansatz", fitted=done, **kw)


def _ranking_early(args: argparse.Namespace, trace, kw: dict):
    """:func:`_ranking` beside the fit, then, where no figure process draws the figure
    (``dampax_cli._figures``), the figure's matplotlib imported in the same thread (0.3-0.5 s
    of Python) while the fit still runs: the figure, drawn once the fit has ended, then only
    draws."""
    try:
        return _ranking(args, trace, None, kw)
    finally:
        if not _figures.running():  # (else the figure process draws)
            import_figure_modules()


def _fit_figure(result, path):
    """fit.png: drawn by the figure process that the console script forked before dampax
    loaded (``dampax_cli._figures``), where there is one, into a temporary file of this
    command's outputs; else (or where it fails) here. Its warnings are this thread's."""
    if _figures.running():
        try:
            with atomic_path(path) as tmp:
                for text in _figures.draw(figure_data(result), tmp):
                    warnings.warn(text, stacklevel=2)
            return path
        except _figures.Unavailable:
            pass
    return plot_fit(result, path)


def _posterior(args: argparse.Namespace, trace, result, free, kw: dict, start):
    """The posterior of a single-trace fit, started from it (None without --posterior)."""
    if not args.posterior:
        return None
    from .._fit import posterior

    return posterior(trace, oscillator=kw["oscillator"], free=free, model=result.model,
                     fit_omega0=kw["fit_omega0"], offset=not args.no_offset, start=start,
                     end=args.end, num_samples=args.draws, num_chains=args.chains,
                     num_warmup=args.warmup, seed=args.seed, units=args.units,
                     start_fit=result, mu_s=args.mu_s)


def _run_joint(args: argparse.Namespace, paths: list, free: tuple) -> int:
    """``dampax fit run1.csv run2.csv --shared b,D``: a joint fit of several runs (the constants
    of ``--shared`` common to all, each run with its own start, offset and window); prints the
    report, writes fit.json and fit.png. Exit status as for one trace."""
    if args.example or args.envelope:
        raise ValueError("several files are a joint fit of traces: not with --example or "
                         "--envelope")
    if args.posterior and (args.draws < 10 or args.chains < 1 or args.warmup < 10):
        raise ValueError("--posterior needs --draws >= 10, --chains >= 1 and --warmup >= 10")
    if args.loss != "linear" or args.optimizer != "lm":
        raise ValueError("a joint fit is least squares: --loss linear, --optimizer lm")
    if args.mu_s is not None or "mu_s" in free:
        raise ValueError("--mu-s: static friction is not supported by a joint fit of several "
                         "runs; fit each run alone")
    not_used(args, "a joint fit of traces", ("--omega0",), add_arguments)
    out_dir = prepare_out_dir(args.out)
    traces = [load_trace(p, time=args.time, position=args.position, rate=_parse_rate(args.rate),
                         delimiter=args.delimiter, scale=args.scale) for p in paths]
    osc, fit_omega0 = _oscillator(args)
    for tr in traces:
        print(f"{PROG} fit: {tr!r}")
    began = time.perf_counter()
    with compile_clock() as clock, warnings.catch_warnings(record=True) as caught, \
            _columns_named(*traces):
        warnings.simplefilter("always")
        result = fit(traces, shared=split_names(args.shared) if args.shared else None,
                     free=free, oscillator=osc, fit_omega0=fit_omega0,
                     offset=not args.no_offset, model=args.model,
                     window=Window(start=_parse_start(args.start), end=args.end,
                                   units=args.units),
                     solver=LeastSquares(max_steps=args.max_steps, starts=args.starts,
                                         seed=args.seed))
        post = None
        if args.posterior:  # the joint fit's posterior, started from it
            from .._fit import posterior

            post = posterior(traces, free=free, model=result.model, num_samples=args.draws,
                             num_chains=args.chains, num_warmup=args.warmup, seed=args.seed,
                             start_fit=result)
    for w in {str(w.message) for w in caught}:
        print(f"{PROG}: warning: {_cli_words(w)}", file=sys.stderr)
    elapsed = time.perf_counter() - began
    print()
    print(_cli_words(result.report(args.level)))
    if args.intervals:
        print()
        print(f"  confidence intervals at {args.level:g} (allowing for correlated residuals):")
        for name, (lo, hi) in result.conf_interval(args.level, runs=True).items():
            print(f"    {name:<10} [{fmt(lo, 6)}, {fmt(hi, 6)}]   value "
                  f"{fmt(result.values[name], 6)}")
    summary = {"fit": result.to_dict(args.level),
               "traces": [{"source": tr.source, "n": len(tr), "n_dropped": tr.n_dropped,
                           "rate": tr.rate} for tr in traces]}
    written = [out_dir / "fit.json", out_dir / "fit.png"]
    failed = _write_outputs(args, result, post, summary, written, out_dir, elapsed, "joint fit",
                            compiling=clock.text(),
                            data="; ".join(tr.describe_columns() for tr in traces))
    if failed is not None:
        return failed
    if not result.adequate:
        error(f"{PROG}: the model does not describe every run")
        return EXIT_INADEQUATE
    return 0


def _jsonable(value):
    """json.dumps default: numpy numbers as floats (NaN as null)."""
    v = float(value)
    return v if math.isfinite(v) else None


def _write_outputs(args, result, post, summary, written, out_dir, elapsed, what: str, *,
                   compiling: str = "", data: str = "", figure=None):
    """The common end of a single and a joint fit: the posterior's report and files, fit.json,
    fit.png, the list of files; returns EXIT_FAILED (after the message) when the fit failed,
    else None.

    Arguments:
        compiling: " (3.1 s compiling)" when the fit compiled programs in this process, else
            "" (:func:`~dampax._cli._common.compile_clock`).
        data: which columns of which files were read (``Trace.describe_columns``), named in
            the message of a failed fit; "" for the example.
        figure: the Future of fit.png when it was drawn beside the ranking, else None (drawn
            here).
    """
    if post is not None:
        print()
        print(post.report(args.level))
        summary["posterior"] = post.summary(args.level)
        written += [post.to_netcdf(out_dir / "posterior.nc"),
                    post.corner(out_dir / "corner.png")]
    write_text(out_dir / "fit.json", json.dumps(summary, indent=2, default=_jsonable))
    if figure is not None:  # drawn beside the ranking (``_common.beside``); its error here
        figure.result()
    else:
        (plot_joint_fit if hasattr(result, "runs") else plot_fit)(result, out_dir / "fit.png")
    print()
    print(f"  {elapsed:.1f} s{compiling}; written: {', '.join(str(p) for p in written)}")
    if not result.success:
        read = f" (data: {data})" if data else ""
        error(f"{PROG}: {what} failed: {_cli_words(result.reason)}{read}")
        return EXIT_FAILED
    return None


@contextlib.contextmanager
def _columns_named(*traces):
    """Within the block, a ValueError about the data also says which columns of which file
    were read (a wrong column is the commonest cause: a time column read as the position
    gives "0 turning points"), and how to choose others."""
    try:
        yield
    except ValueError as err:
        read = "; ".join(tr.describe_columns() for tr in traces if tr is not None)
        if not read:
            raise
        raise ValueError(f"{err} (data: {read}; choose other columns with --time and "
                         "--position)") from None
