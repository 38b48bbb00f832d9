"""``dampax reproduce``: the papers' figures and every quoted number."""

from __future__ import annotations

import argparse
from pathlib import Path

from dampax_cli._arguments import add_reproduce_arguments as add_arguments  # noqa: F401 (SUBCOMMANDS)

from ._common import PROG, error, prepare_out_dir, show_progress


def run(args: argparse.Namespace) -> int:
    """Redraw Figures 2-21 of Lelas & Pezer and Rizcallah's comparison; recompute quoted numbers."""
    import time

    from .._paper._reproduce import reproduce, select_figures

    if args.dpi <= 0:
        raise ValueError(f"--dpi must be > 0, got {args.dpi}")
    args.format = str(args.format).lower()  # PNG is png
    from matplotlib.backend_bases import FigureCanvasBase

    if args.format not in FigureCanvasBase.get_supported_filetypes():
        raise ValueError(f"--format: unsupported image format {args.format!r}")
    if not select_figures(args.figures) and args.no_numbers:  # (a bad list fails here)
        raise ValueError("--figures none with --no-numbers: nothing to reproduce")
    prepare_out_dir(args.out)
    start = time.perf_counter()
    res = reproduce(args.out, figures=args.figures, numbers=not args.no_numbers,
                    fmt=args.format, dpi=args.dpi, progress=show_progress(args))
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
        if counts["MISMATCH"]:
            error(f"{PROG} reproduce: {counts['MISMATCH']} quoted values mismatched (see "
                  f"{Path(args.out) / 'numbers.md'})")
            return 1
    return 0
