"""The ``dampax`` console script: a launcher that imports dampax (and JAX) only for real work.

``import dampax`` imports JAX and switches it to float64, about a second; ``dampax --version``,
``dampax --help``, ``dampax SUBCOMMAND --help`` and syntax errors need none of that. So the
command line is parsed here, outside the dampax package (importing any ``dampax.*`` module runs
``dampax/__init__.py`` first), from the option definitions of :mod:`dampax_cli._arguments`,
which import nothing but argparse; only a parsed command is handed to
:func:`dampax._cli.run_parsed`. ``python -m dampax._cli`` and :func:`dampax._cli.main` parse
with the same definitions.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import os
import sys

from . import _figures
from ._parser import PROG as PROG
from ._parser import build_parser as build_parser
from ._parser import version as version

#: the command line :func:`main` runs (its arguments) while it runs, set before dampax is
#: imported: dampax's import loads the programs its last run used (``dampax._cachethreads``)
COMMAND: tuple[str, ...] | None = None


def main(argv: list[str] | None = None, *, figure_process: bool = False) -> int:
    """The ``dampax`` console script: parse here, import dampax only to run a command.

    Arguments:
        argv: the arguments without the program name; default ``sys.argv[1:]``.
        figure_process: fork the process that draws a fit's figure (``_figures``) before
            dampax is imported (:func:`console` only: a process with nothing else loaded).

    Returns:
        The exit status of :func:`dampax._cli.run_parsed`. ``--help``, ``--version`` and
        syntax errors exit through argparse (SystemExit with status 0 / 0 / 2) before
        anything heavy is imported.
    """
    global COMMAND
    args = build_parser().parse_args(argv)
    COMMAND = tuple(sys.argv[1:] if argv is None else argv)
    if args.quiet:  # XLA's own (C++) warnings, read when JAX loads
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    if figure_process and _figures.wanted(args):
        _figures.start()
    from dampax._cli import run_parsed

    try:
        return run_parsed(args)
    finally:
        COMMAND = None
        _figures.close()


def console() -> None:
    """The ``dampax`` console script: :func:`main`, then the end of the process without
    Python's finalization (:func:`leave`). ``--help``, ``--version`` and syntax errors exit
    through argparse as usual. The process's own settings (not :func:`main`'s, which a
    Python caller may run): one BLAS thread unless ``OPENBLAS_NUM_THREADS`` says otherwise
    (read when numpy and scipy load OpenBLAS: the command's host linear algebra is small, and
    after each call OpenBLAS's idle worker spins on a core, the one XLA's programs run and load
    on: 12-25 % of the CPU of a repeated ``dampax fit --example``;
    ``dampax._fit._linalg.one_blas_thread``), and Python's cyclic collector every 100,000
    allocations instead of 700 (tracing and a fit's results make many short-lived objects and
    few cycles: the example 5 % faster); and a fit's figure drawn by a process forked before
    dampax loads (``_figures``)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    gc.set_threshold(100_000, 50, 1000)
    leave(main(figure_process=True))


def leave(status: int) -> None:
    """End the process with ``status`` once a command has finished, skipping the
    interpreter's teardown of every module and object (JAX's, XLA's, matplotlib's): 0.2-0.45 s
    of a 4 s ``dampax fit --example`` (benchmarks/README.md, issue 36). What a normal exit does
    first is done here: programs still compiling in the background are finished and kept
    (``dampax._cache.finish_background``), the ``atexit`` handlers run (JAX's among them), and
    the standard streams are flushed; then ``os._exit``. The outputs are complete before:
    each was written and renamed into place by the command."""
    cache = sys.modules.get("dampax._cache")
    if cache is not None:
        cache.finish_background()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: nothing more to say
            stream.flush()
    os._exit(status if isinstance(status, int) else 0)
