"""The ``dampax`` command line: one module per subcommand, shared code in ``_common``.

The options are defined in :mod:`dampax_cli._arguments`, outside this package, so that the
``dampax`` console script (:func:`dampax_cli.main`) answers ``--help`` and ``--version``
without importing dampax and JAX; it hands a parsed command to :func:`run_parsed`.
:func:`main` (``python -m dampax._cli``) parses with the same definitions.

Each subcommand module has ``add_arguments(parser)`` and ``run(args) -> exit status`` and is
registered in :data:`SUBCOMMANDS`. A ValueError from dampax (bad input, a model that does not
exist) is reported as one line, ``dampax: error: <message>``, with exit status 2 (as argparse
does for bad syntax); Ctrl-C (SIGTERM) ends any command with one line and exit status 130
(143), removing what it was writing; a command's output files replace the earlier ones together,
once all are complete. ``--quiet``
(every subcommand) prints nothing but errors.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable

from dampax_cli._arguments import COMMANDS
from dampax_cli._parser import build_parser as _build_parser

from .._cache import exported_dir, keep_every_program
from .._cachethreads import recording
from .._io import all_or_nothing
from ._common import PROG, silenced


def _run_of(name: str) -> Callable[[argparse.Namespace], int]:
    """``run`` of the subcommand module ``name``, imported only when the command runs: ``dampax
    solve`` does not import the fitting stack (``dampax._fit``) that ``dampax fit`` needs."""

    def run(args: argparse.Namespace) -> int:
        return importlib.import_module(f"{__name__}.{name}").run(args)

    run.__qualname__ = run.__name__ = f"run_{name}"
    return run


#: name -> (add_arguments(parser), run(args) -> exit status); the help of each subcommand is
#: its summary in ``dampax_cli._arguments.COMMANDS`` (whose ``add_arguments`` each module
#: re-exports), and its module is imported when it runs.
SUBCOMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                             Callable[[argparse.Namespace], int]]] = {
    name: (add_arguments, _run_of(name)) for name, (_, add_arguments) in COMMANDS.items()
}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one subparser per entry of :data:`SUBCOMMANDS`.

    Returns:
        An ``argparse.ArgumentParser`` (:func:`dampax_cli.build_parser` with the
        ``add_arguments`` of :data:`SUBCOMMANDS`); parsed arguments name the subcommand in
        ``command``.
    """
    return _build_parser({name: add for name, (add, _) in SUBCOMMANDS.items()})


@contextlib.contextmanager
def _exit_on_interrupt():
    """Ctrl-C (SIGINT) or SIGTERM ends the process at once: one line, exit status 130 / 143,
    partial files and temporary folders gone (``dampax._io.PARTIAL``).

    Python raises KeyboardInterrupt only when the main thread runs Python code again (not
    during a long XLA compilation), may raise it inside a garbage-collector callback where it is
    ignored, and JAX can crash at exit after an interrupted computation. So the signal is
    routed to a watcher thread (``signal.set_wakeup_fd``) that removes the temporary files of
    unfinished writes, prints one line and leaves with ``os._exit(130)``. Outside the main
    thread (where signals cannot be handled) nothing is changed.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)

    def watch():
        while True:
            try:
                data = os.read(read_fd, 64)
            except OSError:
                return
            if not data:
                return  # the pipe was closed: the command is over
            for signum, word in ((signal.SIGINT, "interrupted"), (signal.SIGTERM, "terminated")):
                if signum in data:
                    from .._io import remove_partial_files

                    remove_partial_files()
                    with contextlib.suppress(OSError):
                        os.write(2, f"\n{PROG}: {word}\n".encode())
                    os._exit(128 + signum)

    handled = (signal.SIGINT, signal.SIGTERM)
    old_handlers = {signum: signal.signal(signum, lambda signum, frame: None)
                    for signum in handled}
    old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(target=watch, name="dampax-signals", daemon=True).start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(old_fd)
        for signum, handler in old_handlers.items():
            signal.signal(signum, handler)
        os.close(write_fd)  # the watcher reads end-of-file and returns


def main(argv: list[str] | None = None) -> int:
    """Run the ``dampax`` command line.

    Arguments:
        argv: the arguments without the program name; default ``sys.argv[1:]``.

    Returns:
        The exit status of :func:`run_parsed`. Syntax errors and ``--help`` exit through
        argparse (SystemExit with status 2 / 0).
    """
    return run_parsed(build_parser().parse_args(argv))


def run_parsed(args: argparse.Namespace) -> int:
    """Run the subcommand ``args.command`` of :data:`SUBCOMMANDS` on parsed arguments.

    Arguments:
        args: arguments parsed by :func:`build_parser` or :func:`dampax_cli.build_parser`.

    Returns:
        The exit status: 0 on success, 2 on invalid input (one line on stderr), 130 when
        interrupted (Ctrl-C; no half-written file is left); a subcommand may return others
        (``dampax fit``: 3, 4); 1 for any other exception (one line naming its type: no
        traceback reaches the user unless ``DAMPAX_TRACEBACK=1``). With ``--quiet`` only
        error lines are printed.
    """
    run = SUBCOMMANDS[args.command][1]
    try:
        # keep_every_program: a repeated command compiles nothing, not even small programs
        # all_or_nothing: a command's outputs replace the earlier ones together, when complete
        # recording: the kept programs it used load ahead of its next run (_cachethreads)
        with _exit_on_interrupt(), keep_every_program(), recording(exported_dir), \
                all_or_nothing(), silenced(getattr(args, "quiet", False)):
            return run(args)
    except (ValueError, OSError) as err:
        message = " ".join(str(err).split())
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # SIGINT raised in Python where no watcher could be installed
        print(f"\n{PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # an input no check caught, or a bug: one line, no traceback
        if os.environ.get("DAMPAX_TRACEBACK"):
            raise
        message = " ".join(str(err).split()) or "(no message)"
        print(f"{PROG}: error: unexpected {type(err).__name__}: {message} (set "
              f"DAMPAX_TRACEBACK=1 for the traceback, and please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
