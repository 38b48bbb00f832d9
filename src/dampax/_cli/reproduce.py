"""``dampax reproduce``: the papers' figures and every quoted number."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import PROG, prepare_out_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax reproduce``."""
    parser.add_argument("--out", default="reproduce", metavar="DIR",
                        help="output folder (default: %(default)s)")
    parser.add_argument("--figures", default="all", metavar="LIST",
                        help="figures to draw: numbers 2-21, ranges (8-10), 'rizcallah', "
                             "'all' or 'none', comma-separated (default: %(default)s)")
    parser.add_argument("--no-numbers", action="store_true",
                        help="skip numbers.csv / numbers.md")
    parser.add_argument("--format", default="png", metavar="EXT",
                        help="image format: png, pdf, svg, ... (default: %(default)s)")
    parser.add_argument("--dpi", type=int, default=110, help="resolution (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Redraw Figures 2-21 of Lelas & Pezer and Rizcallah's comparison; recompute quoted numbers."""
    import time

    from .._reproduce import reproduce, select_figures

    if args.dpi <= 0:
        raise ValueError(f"--dpi must be > 0, got {args.dpi}")
    select_figures(args.figures)  # fail on a bad list before any work
    prepare_out_dir(args.out)
    start = time.perf_counter()
    res = reproduce(args.out, figures=args.figures, numbers=not args.no_numbers,
                    fmt=args.format, dpi=args.dpi, progress=not args.no_progress)
    elapsed = time.perf_counter() - start
    print(f"{PROG} reproduce: {len(res.figures)} figures"
          + (" and numbers.csv, numbers.md" if res.numbers_md else "")
          + f" in {Path(args.out)} ({elapsed:.0f} s)")
    if res.numbers:
        counts = {s: sum(r.status == s for r in res.numbers)
                  for s in ("ok", "explained", "MISMATCH")}
        print(f"  {len(res.numbers)} quoted values: {counts['ok']} within the printed rounding, "
              f"{counts['explained']} known discrepancies of the papers' text (see numbers.md), "
              f"{counts['MISMATCH']} mismatched")
        for r in res.numbers:
            if r.status == "MISMATCH":
                print(f"  MISMATCH: {r.source}: {r.quantity}: paper {r.quoted}, "
                      f"dampax {r.computed:.6g}")
        return 1 if counts["MISMATCH"] else 0
    return 0
