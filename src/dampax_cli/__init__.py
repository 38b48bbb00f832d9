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

import os

from ._parser import PROG as PROG
from ._parser import build_parser as build_parser
from ._parser import version as version


def main(argv: list[str] | None = None) -> int:
    """The ``dampax`` console script: parse here, import dampax only to run a command.

    Arguments:
        argv: the arguments without the program name; default ``sys.argv[1:]``.

    Returns:
        The exit status of :func:`dampax._cli.run_parsed`. ``--help``, ``--version`` and
        syntax errors exit through argparse (SystemExit with status 0 / 0 / 2) before
        anything heavy is imported.
    """
    args = build_parser().parse_args(argv)
    if args.quiet:  # XLA's own (C++) warnings, read when JAX loads
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    from dampax._cli import run_parsed

    return run_parsed(args)
