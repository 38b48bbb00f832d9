"""What the ``dampax`` subcommands share: the program name, number formatting, the oscillator
of the options (defined in :mod:`dampax_cli._arguments`), the checks run before any computing,
and what ``--quiet`` and ``--no-progress`` switch off."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import warnings
from pathlib import Path

PROG = "dampax"

#: where :func:`error` writes: the command's stderr, kept while ``--quiet`` silences the rest
_ERROR_STREAMS: list = []


def error(text: str) -> None:
    """Print a line that explains a failure (a non-zero exit status) on stderr, also under
    ``--quiet``; the "dampax: error: ..." of invalid input is printed by dampax._cli."""
    print(text, file=_ERROR_STREAMS[-1] if _ERROR_STREAMS else sys.stderr)


@contextlib.contextmanager
def silenced(quiet: bool):
    """``--quiet``: inside the block stdout and stderr go nowhere (results, notes, warnings,
    Python's warnings and logging below ERROR) but :func:`error` still reaches stderr."""
    if not quiet:
        yield
        return
    _ERROR_STREAMS.append(sys.stderr)
    disabled = logging.root.manager.disable
    with (open(os.devnull, "w") as null, contextlib.redirect_stdout(null),
          contextlib.redirect_stderr(null), warnings.catch_warnings()):
        warnings.simplefilter("ignore")
        logging.disable(logging.WARNING)
        try:
            yield
        finally:
            logging.disable(disabled)
            _ERROR_STREAMS.pop()


#: JAX's monitoring events: the duration of a compilation request (an XLA compilation, or
#: the time to read the program from the persistent cache) and a persistent-cache hit
_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"


class CompileClock:
    """The XLA compilations of this process while a :func:`compile_clock` block runs.

    Attributes:
        count: programs compiled (a program read from JAX's persistent cache, or run from
            dampax's kept executables, is not compiled and not counted).
        seconds: the time they took to compile [s].
    """

    def __init__(self):
        self.count = 0
        self.seconds = 0.0

    def text(self) -> str:
        """" (3.1 s compiling)" when something was compiled in the block, else ""."""
        if not self.count:
            return ""
        s = self.seconds
        return f" ({s:.1f} s compiling)" if s >= 1.0 else f" ({s:.2g} s compiling)"


@contextlib.contextmanager
def compile_clock():
    """Count what XLA compiles in this process inside the block (for the commands' timings).

    JAX reports every compilation request as a duration event; a request answered from the
    persistent compilation cache reports a cache hit first, in the same thread, and is not
    counted. Programs compiled by other processes (``dampax errormap --processes``) are not
    seen.

    Yields:
        A :class:`CompileClock`, filled in as the block runs.
    """
    import threading

    import jax

    clock = CompileClock()
    hit: dict = {}
    lock = threading.Lock()

    def on_event(event, **_):
        if event == _CACHE_HIT_EVENT:
            with lock:
                hit[threading.get_ident()] = True

    def on_duration(event, duration_secs, **_):
        if event != _COMPILE_EVENT:
            return
        with lock:
            if hit.pop(threading.get_ident(), False):
                return
            clock.count += 1
            clock.seconds += float(duration_secs)

    jax.monitoring.register_event_listener(on_event)
    jax.monitoring.register_event_duration_secs_listener(on_duration)
    try:
        yield clock
    finally:
        jax.monitoring.unregister_event_listener(on_event)
        jax.monitoring.unregister_event_duration_listener(on_duration)


@contextlib.contextmanager
def beside(fn, *args):
    """Run ``fn(*args)`` in a thread while the block runs; yields its Future (``result()``
    returns its value or raises its error). Leaving the block, also by an error, waits for it:
    no thread writes after the command has ended.

    For a fit's figure, drawn while the model ranking runs: the figure is Python (matplotlib's
    Agg canvas, no pyplot), the ranking mostly compiled programs that release Python's lock
    (``dampax fit --example`` repeated: median 3.29 -> 3.02 s, benchmarks/README.md, issue 36,
    twenty-seventh session).
    """
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dampax-cli")
    try:
        yield pool.submit(fn, *args)
    finally:
        pool.shutdown(wait=True)


def show_progress(args: argparse.Namespace, stream=None) -> bool:
    """Whether to draw progress bars: only when stderr (``stream``) is a terminal, and neither
    ``--no-progress`` nor ``--quiet`` was given (no bars in logs and pipes)."""
    if getattr(args, "no_progress", False) or getattr(args, "quiet", False):
        return False
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (ValueError, OSError):  # a closed stream
        return False


def fmt(value: float, digits: int, *, inf: str = "inf", nan: str = "-") -> str:
    """A number with ``digits`` significant digits; inf / nan spelled out.

    Arguments:
        value: the number.
        digits: significant digits.
        inf: the word for +inf (``-`` + inf for -inf).
        nan: the word for NaN.

    Returns:
        The text, "0" for a (signed) zero.
    """
    if math.isnan(value):
        return nan
    if math.isinf(value):
        return inf if value > 0 else f"-{inf}"
    text = f"{value:.{digits}g}"
    return "0" if text in ("-0", "0") else text


def split_names(text: str) -> list[str]:
    """Names of a comma list, stripped, empty entries dropped."""
    return [s.strip() for s in text.split(",") if s.strip()]


def check_digits(digits: int) -> None:
    """ValueError naming --digits unless 1 <= digits <= 17."""
    if not 1 <= digits <= 17:
        raise ValueError(f"--digits must be between 1 and 17, got {digits}")


def oscillator_from(args: argparse.Namespace):
    """The :class:`~dampax.Oscillator` of the options of
    :func:`dampax_cli._arguments.add_oscillator_arguments`."""
    import jax
    import numpy as np

    from .._oscillator import Oscillator

    given = dict(m=args.m, k=args.k, mu=args.mu, b=args.b, D=args.D, g=args.g, k3=0.0)
    if getattr(args, "mu_s", None) is not None:
        given["mu_s"] = args.mu_s
    try:
        # float64 arrays put on the device as they are: Oscillator's jnp.asarray(value, float)
        # then converts nothing, where a Python float would compile a conversion (issue 26)
        return Oscillator(**{name: jax.device_put(np.asarray(value, dtype=float))
                             for name, value in given.items()})
    except ValueError:
        return Oscillator(**given)  # the same error, naming the value as it was given


def oscillator_text(args: argparse.Namespace) -> str:
    """One line naming the oscillator and the initial state of the options."""
    return (f"m = {args.m:g} kg, k = {args.k:g} N/m, mu = {args.mu:g}, b = {args.b:g} kg/s, "
            f"D = {args.D:g} kg/m, g = {args.g:g} m/s^2, "
            + ("" if getattr(args, "mu_s", None) is None else f"mu_s = {args.mu_s:g}, ")
            + f"x0 = {args.x0:g} m, v0 = {args.v0:g} m/s")


def check_plot_path(path: str, flag: str = "--plot") -> None:
    """Fail before any computing when a figure cannot be written (folder, file format).

    Arguments:
        path: the output file.
        flag: the option named in the error.

    Raises:
        ValueError: the folder does not exist or cannot be written, or matplotlib cannot
            write the suffix.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    from .._io import check_writable_dir

    target = Path(path)
    check_writable_dir(target.parent, flag)
    if target.is_dir():
        raise ValueError(f"{flag}: {path!r} is a folder, not a file")
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = target.suffix.lstrip(".").lower()
    if suffix not in formats:
        raise ValueError(f"{flag}: unsupported file type {target.suffix!r} of {path!r}; "
                         f"use one of {', '.join('.' + f for f in sorted(formats))}")


def prepare_out_dir(path, flag: str = "--out") -> Path:
    """Create the output folder (with parents) and check it can be written, before computing.

    Arguments:
        path: the folder.
        flag: the option named in errors.

    Returns:
        The folder as a Path.

    Raises:
        ValueError: the path is a file, or the folder cannot be created or written.
    """
    from .._io import check_writable_dir

    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{flag}: {str(out)!r} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{flag}: cannot create {str(out)!r} ({err.strerror})") from None
    check_writable_dir(out, flag)
    return out


def not_used(args: argparse.Namespace, what: str, flags: tuple, add_arguments) -> None:
    """ValueError naming the ``flags`` given, away from their defaults in the command's own
    definitions (``add_arguments``, the subcommand's), that ``what`` does not use: they were
    ignored without a word."""
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser)
    actions = parser._option_string_actions
    given = [flag for flag in flags
             if getattr(args, actions[flag].dest) != actions[flag].default]
    if given:
        raise ValueError(f"{', '.join(given)}: not used by {what}")
