"""How often pure noise passes the pure-noise check (``dampax._fit._noise``), at the samples'
own scale alone and at every scale of block means (1, 4, 16, ... samples, at least 64 blocks):
the coarser scales must not let more pure noise through (benchmarks/README.md, issue 36,
fifteenth session).

    python benchmarks/noise_scales.py [--draws 200] [--seed 0]

Prints, for white and AR(1) noise of several lengths, the share of traces that stand above
the noise's excursions at the first scale and at any scale.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.signal import lfilter

from dampax._fit._noise import excursions


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    print("| samples | AR(1) phi | passed at the samples' scale | passed at any scale |")
    print("|---|---|---|---|")
    for n in (300, 1000, 20000):
        for phi in (0.0, 0.3, 0.5, 0.7, 0.9):
            first = anywhere = 0
            for _ in range(args.draws):
                z = lfilter([math.sqrt(1.0 - phi * phi)], [1.0, -phi], rng.standard_normal(n))
                e = excursions(z)
                first += e[0][1] > e[0][2]
                anywhere += any(half > bound for _, half, bound in e)
            print(f"| {n} | {phi} | {100 * first / args.draws:.1f} % | "
                  f"{100 * anywhere / args.draws:.1f} % |")


if __name__ == "__main__":
    main()
