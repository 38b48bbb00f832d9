"""Calibration of ``_posterior.NARROW`` (issue 36): how narrow is a right posterior?

    python benchmarks/posterior_narrow.py [--n 20] [--seed 0] [--draws 200] [--warmup 200]

``dp.posterior`` warns when a constant's posterior sd is below ``NARROW`` (0.5) times the start
fit's HAC interval sd: the AR(1) noise model is then too simple for the residuals. Where the
noise IS AR(1) (white noise included: phi = 0) both estimate the same sd, so the ratio of a
right model should lie near 1 and far above NARROW. This script draws traces of issue 36's
family (``fit_speed.draw``: Coulomb friction plus quadratic drag, 2-15 periods, 3,000 samples,
noise 0.5-3 % of A0, AR(1) with coefficient 0.3-0.9 for a third), from the INDEPENDENT scipy
integrator with exact stick-slip, fits each by the default call (``free=("mu", "D")``, the
oscillator given), samples the posterior from that fit (2 chains), and prints each
constant's ratio posterior sd / HAC sd, its smallest value over the family, and how many
posteriors the warning named (a false warning: the noise model was right). Not a test; the
numbers go to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from fit_speed import draw, simulate  # noqa: E402 (the family and its independent integrator)

FREE = ("mu", "D")


def main() -> None:
    import dampax as dp
    from dampax._fit._posterior import NARROW

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=200)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(args.seed)
    specs = [draw(rng) for _ in range(args.n)]
    ratios, named = {n: [] for n in FREE}, 0
    for i, spec in enumerate(specs):
        t, x = simulate(spec)
        osc = dp.Oscillator(m=spec["m"], k=spec["k"])
        began = time.perf_counter()
        res = dp.fit(t, x, oscillator=osc, free=FREE)
        post = dp.posterior(t, x, oscillator=osc, free=FREE, start_fit=res,
                            num_samples=args.draws, num_chains=2, num_warmup=args.warmup,
                            seed=i)
        row = {}
        for name in FREE:
            sd = float(np.std(np.asarray(post.draws[name].values, dtype=float), ddof=1))
            row[name] = sd / res.hac_stderr[name]
            ratios[name].append(row[name])
        named += bool(post.narrow)
        print(json.dumps(dict(index=i, model=res.model, success=bool(res.success),
                              phi=spec["phi"], ratios=row, narrow=sorted(post.narrow),
                              r_hat=max(float(post.summary(0.9)[n]["r_hat"]) for n in FREE),
                              seconds=round(time.perf_counter() - began, 1))), flush=True)
    print(f"\n{args.n} posteriors of issue 36's family (2 chains x {args.draws} draws, "
          f"{args.warmup} warm-up): NARROW = {NARROW}")
    for name in FREE:
        r = np.asarray(ratios[name])
        print(f"  {name}: posterior sd / HAC sd: min {r.min():.3f}, 5 % {np.quantile(r, 0.05):.3f}"
              f", median {np.median(r):.3f}, max {r.max():.3f}")
    print(f"  posteriors whose warning named a constant (false warnings): {named} of {args.n}")


if __name__ == "__main__":
    main()
