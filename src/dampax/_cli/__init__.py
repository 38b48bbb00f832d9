"""The ``dampax`` command line: one module per subcommand, shared options in ``_common``.

Each subcommand module has ``add_arguments(parser)`` and ``run(args) -> exit status`` and is
registered in :data:`SUBCOMMANDS`. A ValueError from dampax (bad input, a model that does not
exist) is reported as one line, ``dampax: error: <message>``, with exit status 2 (as argparse
does for bad syntax); Ctrl-C ends any command with one line and exit status 130.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable

from .._cache import keep_every_program
from .._version import __version__
from . import errormap, fit, reproduce, sensitivity, solve
from ._common import PROG

#: name -> (add_arguments(parser), run(args) -> exit status); the first docstring line of
#: ``run`` is the subcommand's help.
SUBCOMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                             Callable[[argparse.Namespace], int]]] = {
    name: (module.add_arguments, module.run)
    for name, module in (("solve", solve), ("errormap", errormap),
                         ("sensitivity", sensitivity), ("fit", fit), ("reproduce", reproduce))
}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one subparser per entry of :data:`SUBCOMMANDS`.

    Returns:
        An ``argparse.ArgumentParser``; parsed arguments carry the subcommand's ``run``.
    """
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Harmonic oscillator with Coulomb, viscous and quadratic damping: analytic "
                    "models (Lelas & Pezer; Rizcallah) against the exact motion.",
        epilog="The first run of a command compiles its models with JAX (often 10 s or more); "
               "later runs re-use them from the cache in ~/.cache/dampax (DAMPAX_CACHE=0: "
               "off; DAMPAX_CACHE_DIR: elsewhere). Exit status: 0 ok, 2 invalid input, "
               "130 interrupted.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (add_arguments, run) in SUBCOMMANDS.items():
        summary = (run.__doc__ or "").strip().splitlines()[0] if run.__doc__ else None
        p = sub.add_parser(name, help=summary, description=summary)
        add_arguments(p)
        p.set_defaults(run=run)
    return parser


@contextlib.contextmanager
def _exit_on_interrupt():
    """Ctrl-C (SIGINT) ends the process at once: one line, exit status 130, partial files gone.

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
            if signal.SIGINT in data:
                from .._io import remove_partial_files

                remove_partial_files()
                with contextlib.suppress(OSError):
                    os.write(2, f"\n{PROG}: interrupted\n".encode())
                os._exit(130)

    old_handler = signal.signal(signal.SIGINT, lambda signum, frame: None)
    old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(target=watch, name="dampax-sigint", daemon=True).start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(old_fd)
        signal.signal(signal.SIGINT, old_handler)
        os.close(write_fd)  # the watcher reads end-of-file and returns


def main(argv: list[str] | None = None) -> int:
    """Run the ``dampax`` command line.

    Arguments:
        argv: the arguments without the program name; default ``sys.argv[1:]``.

    Returns:
        The exit status: 0 on success, 2 on invalid input (one line on stderr), 130 when
        interrupted (Ctrl-C; no half-written file is left). Syntax errors and ``--help``
        exit through argparse (SystemExit with status 2 / 0).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        # keep_every_program: a repeated command compiles nothing, not even small programs
        with _exit_on_interrupt(), keep_every_program():
            return args.run(args)
    except (ValueError, OSError) as err:
        message = " ".join(str(err).split())
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # SIGINT raised in Python where no watcher could be installed
        print(f"\n{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
