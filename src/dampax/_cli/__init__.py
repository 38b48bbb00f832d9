"""The ``dampax`` command line: one module per subcommand, shared options in ``_common``.

Each subcommand module has ``add_arguments(parser)`` and ``run(args) -> exit status`` and is
registered in :data:`SUBCOMMANDS`. A ValueError from dampax (bad input, a model that does not
exist) is reported as one line, ``dampax: error: <message>``, with exit status 2 (as argparse
does for bad syntax); Ctrl-C ends any command with one line and exit status 130.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

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
        return args.run(args)
    except (ValueError, OSError) as err:
        message = " ".join(str(err).split())
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: one line; outputs are written whole or not at all
        print(f"\n{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
