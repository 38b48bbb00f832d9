"""How far the halt search's held fits get in how many steps (issue 36): the data behind the
step budget of ``_halts._held_fit``.

    python benchmarks/halt_steps.py [--n 200] [--seed 0] [--only 0,2,4] [--out FILE.jsonl]

The search of a fit for a motion that halts at a neighbouring turning point
(``_halts.search_other_halts``) fits the exact model with mu held just past each threshold, for
``HALT_STEPS`` (64) Levenberg-Marquardt steps, and continues a fit only where its cost is then
within ``NEAR_RISE`` (100) noise variances of the optimum's. This script fits the draws of
``fit_calibration.py``'s family (the independent scipy integrator; the default call) whose fit
has mu free, and for every held fit of the search also runs the same fit from the same start
with budgets of 8, 16 and 32 steps (Levenberg-Marquardt is deterministic: a budget of k
follows the first k steps of the 64-step fit), recording the cost after each budget against
the optimum's, in units of that band. It prints, per budget k, the largest (cost_k - best) /
band among the held fits that end within the band after 64 steps (the fits that matter) and
how many held fits lie above given multiples of the band after k steps (the steps a rule
"stop after k steps above F bands" would save). Not a test; the table goes to
benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fit_calibration as fc  # noqa: E402  (the family and the independent integrator)

BUDGETS = (8, 16, 32)
FACTORS = (10.0, 100.0, 1e3, 1e4)


def _instrumented(records: list, index: list):
    """``_halts._held_fit`` that also records the cost of the same held fit after each of
    :data:`BUDGETS` steps (and of the unchanged fit itself)."""
    from dampax._fit import _halts

    real = _halts._held_fit

    def held_fit(held, full, best, mu_alt, last):
        start = _halts.predicted_start(best, "mu", mu_alt)
        name, fs = last.model, last.fs
        costs = {}
        for k in BUDGETS:
            out = held.solve(start, name, fs, like=last, budget=k).out
            costs[k] = float(out.chisqr)
        first = held.solve(start, name, fs, like=last).out
        costs[_halts.HALT_STEPS] = float(first.chisqr)
        out = real(held, full, best, mu_alt, last)
        c0 = float(best.chisqr)
        band = _halts.NEAR_RISE * _halts._noise_variance(full, best)
        records.append(dict(
            index=index[0], mu_alt=float(mu_alt), best=c0, band=band,
            steps=int(first.steps), converged=not _halts._unfinished(first),
            rise={str(k): (c - c0) / band for k, c in costs.items()},
            final=(float(out.out.chisqr) - c0) / band))
        return out

    _halts._held_fit = held_fit


def summary(records: list) -> list[str]:
    """The table: per budget, the worst rise of the fits that matter, and how many fits lie
    above each multiple of the band."""
    last = str(max(int(k) for k in records[0]["rise"])) if records else "64"
    matter = [r for r in records if r["rise"][last] < 1.0]
    lines = [f"{len(records)} held fits of {len({r['index'] for r in records})} draws; "
             f"{len(matter)} end within the band after {last} steps "
             f"({sum(r['final'] < 1.0 for r in records)} after the continuation); "
             f"{sum(r['converged'] for r in records)} converged within {last} steps", "",
             "| after k steps | largest rise of the fits that end within the band (bands) | "
             + " | ".join(f"fits above {f:g} bands" for f in FACTORS) + " |",
             "|---|---|" + "---|" * len(FACTORS)]
    for k in (*map(str, BUDGETS), last):
        worst = max((r["rise"][k] for r in matter), default=math.nan)
        above = [sum(r["rise"][k] > f and not r["converged"] for r in records)
                 for f in FACTORS]
        lines.append(f"| {k} | {worst:.3g} | " + " | ".join(map(str, above)) + " |")
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default=None, help="comma-separated draw indices")
    ap.add_argument("--out", type=Path, default=None, help="write every held fit (JSON lines)")
    args = ap.parse_args(argv)
    records, index = [], [0]
    _instrumented(records, index)
    specs, _ = fc.traces("default", args.n, args.seed)
    only = None if args.only is None else {int(k) for k in args.only.split(",")}
    began = time.perf_counter()
    for i, spec in enumerate(specs):
        if (only is not None and i not in only) or "mu" not in spec["free"]:
            continue
        index[0] = i
        t, x = fc.simulate(spec)
        n = len(records)
        fc.run_case(spec, t, x, "default")
        print(f"{i:4d} {len(records) - n} held fits", flush=True)
    if args.out:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in records))
    print(f"\n{time.perf_counter() - began:.0f} s\n")
    print("\n".join(summary(records)))


if __name__ == "__main__":
    main()
