"""The parser of the ``dampax`` command line (argparse only: nothing of dampax or JAX is
imported), used by the launcher :func:`dampax_cli.main` and by :mod:`dampax._cli` alike."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

from ._arguments import COMMANDS

PROG = "dampax"


def version() -> str:
    """dampax's version, from ``dampax/_version.py`` (the one place it is written), without
    importing dampax; from the installed package's metadata where that file cannot be read."""
    import importlib.util

    spec = importlib.util.find_spec("dampax")  # a top-level name: finds, imports nothing
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = os.path.join(folder, "_version.py")
        if os.path.isfile(path):
            import runpy

            return runpy.run_path(path)["__version__"]
    from importlib.metadata import version as installed_version

    return installed_version("dampax")


class _VersionAction(argparse.Action):
    """``--version``: print ``dampax X.Y.Z`` and exit (the version is read only when asked)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show the version and exit"):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0,
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog} {version()}")  # on stdout, as argparse's own "version" action
        parser.exit()


def build_parser(commands: dict[str, Callable[[argparse.ArgumentParser], None]] | None = None
                 ) -> argparse.ArgumentParser:
    """The parser of the ``dampax`` command line, one subparser per entry of ``COMMANDS``.

    Arguments:
        commands: name -> add_arguments(parser) to use instead of the definitions of
            :mod:`dampax_cli._arguments` (dampax._cli passes its registry).

    Returns:
        An ``argparse.ArgumentParser``; parsed arguments name the subcommand in ``command``
        and carry ``quiet`` (every subcommand has ``-q/--quiet``).
    """
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Harmonic oscillator with Coulomb, viscous and quadratic damping: analytic "
                    "models (Lelas & Pezer; Rizcallah) against the exact motion.",
        epilog="The first run of a command compiles its models with JAX (often 10 s or more); "
               "later runs re-use them from the cache in ~/.cache/dampax (DAMPAX_CACHE=0: "
               "off; DAMPAX_CACHE_DIR: elsewhere). Progress bars are drawn only when stderr "
               "is a terminal. Exit status: 0 ok, 2 invalid input, 130 interrupted; "
               "fit: 3 failed, 4 inadequate; reproduce: 1 a quoted number mismatched.")
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (summary, add_arguments) in COMMANDS.items():
        p = sub.add_parser(name, help=summary, description=summary)
        (commands or {}).get(name, add_arguments)(p)
        p.add_argument("-q", "--quiet", action="store_true",
                       help="print nothing but errors (no results, notes, warnings or "
                            "progress; the exit status tells how it went)")
    return parser
