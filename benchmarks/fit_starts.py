"""Benchmark (issue 11, item 7): the cost of the global starts and of the posterior.

    python benchmarks/fit_starts.py [--data DIR] [--repeat 3] [--no-posterior]

On spring-mass run 1 (about 11,900 samples; ``../shared/data``, never copied into the repository):

1. ``dp.fit(trace, free=("b", "D"), starts=1)`` against ``starts=32`` (the 32 jittered starts
   optimised in one vmapped call on the thinned trace, then the best polished on the whole
   trace), the best of --repeat calls each, after compilation. Goal: 32 starts within 3x one.
2. ``dp.posterior`` of the same fit, 4 chains x 1000 draws (500 warm-up steps): wall time of
   the call, its compilation included, as a user sees it. Goal: within 2 minutes on 2 cores.

Also checks that the turning-point start alone reaches the same optimum as the 32 starts.
Not a test: the numbers go to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import dampax as dp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def best_time(fn, repeat):
    best, out = math.inf, None
    for _ in range(repeat):
        began = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - began)
    return best, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-posterior", action="store_true")
    args = ap.parse_args()
    path = args.data / "spring_mass_airdrag" / "run1.csv"
    if not path.is_file():
        raise SystemExit(f"spring run 1 not found at {path} (the shared data folder)")
    trace = dp.load_trace(path, time="time", position="position")
    warnings.simplefilter("ignore")
    for starts in (1, 32):  # compile both
        dp.fit(trace, free=("b", "D"), solver=dp.LeastSquares(starts=starts))
    t1, one = best_time(lambda: dp.fit(trace, free=("b", "D"),
                                       solver=dp.LeastSquares(starts=1)), args.repeat)
    t32, many = best_time(lambda: dp.fit(trace, free=("b", "D"),
                                         solver=dp.LeastSquares(starts=32)), args.repeat)
    print(f"spring run 1, {len(trace)} samples, ansatz, free b, D (per unit mass):")
    print(f"  1 start : {t1:.3f} s   cost {0.5 * one.chisqr:.8g}")
    print(f"  32 starts: {t32:.3f} s   cost {0.5 * many.chisqr:.8g}   ({many.starts.summary()})")
    print(f"  ratio 32 starts / 1 start = {t32 / t1:.2f}  (goal <= 3)")
    if not args.no_posterior:
        began = time.perf_counter()
        post = dp.posterior(trace, free=("b", "D"), start_fit=many, num_samples=1000,
                            num_chains=4, num_warmup=500)
        wall = time.perf_counter() - began
        print(f"\nposterior, 4 chains x 1000 draws (+500 warm-up), compilation included: "
              f"{wall:.1f} s  (goal <= 120 s)")
        print(post.report(0.95))


if __name__ == "__main__":
    main()
