"""What the ``dampax`` subcommands share: the program name, number formatting, the oscillator
options and the checks run before any computing."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

PROG = "dampax"


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


def add_oscillator_arguments(parser: argparse.ArgumentParser, *, mu: float = 0.0,
                             D: float = 0.0,
                             start_title: str = "initial state (default: the papers' block)"):
    """Options --m --k --mu --b --D --g --x0 --v0 shared by the subcommands."""
    osc = parser.add_argument_group("oscillator (m x'' = -k x - mu m g sgn(x') - b x' - D x'|x'|)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=30.0,
                     help="spring stiffness [N/m] (default: %(default)s)")
    osc.add_argument("--mu", type=float, default=mu,
                     help="Coulomb friction coefficient (default: %(default)s)")
    osc.add_argument("--b", type=float, default=0.0,
                     help="viscous damping [kg/s] (default: %(default)s)")
    osc.add_argument("--D", type=float, default=D,
                     help="quadratic drag [kg/m] (default: %(default)s)")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2] (default: %(default)s)")
    start = parser.add_argument_group(start_title)
    start.add_argument("--x0", type=float, default=0.2,
                       help="initial displacement [m] (default: %(default)s)")
    start.add_argument("--v0", type=float, default=0.0,
                       help="initial velocity [m/s] (default: %(default)s)")


def oscillator_from(args: argparse.Namespace):
    """The :class:`~dampax.Oscillator` of the options of :func:`add_oscillator_arguments`."""
    from .._oscillator import Oscillator

    return Oscillator(m=args.m, k=args.k, mu=args.mu, b=args.b, D=args.D, g=args.g)


def oscillator_text(args: argparse.Namespace) -> str:
    """One line naming the oscillator and the initial state of the options."""
    return (f"m = {args.m:g} kg, k = {args.k:g} N/m, mu = {args.mu:g}, b = {args.b:g} kg/s, "
            f"D = {args.D:g} kg/m, g = {args.g:g} m/s^2, x0 = {args.x0:g} m, "
            f"v0 = {args.v0:g} m/s")


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
