"""Other realizations of the k3 test's posterior (issue 34): is its verdict robust to a GPU?

    python benchmarks/posterior_realizations.py [--seeds 0 100]

tests/models/test_cubic.py::test_fit_recovers_k3_of_a_synthetic_trace samples the posterior of
a synthetic trace with k3 (2 chains x 100 draws, 100 warm-up, seed 3) and asserts its 95 %
interval of k3 holds the truth, is narrower than 0.2 k3, and R-hat < its bound. A GPU rounds
the log-density's sums in another order; a leapfrog trajectory amplifies such last-bit
differences, so the GPU's chains are another realization of the same sampler, as another
seed is on this CPU. This script draws the same posterior with the seeds given and prints
each one's interval and R-hat, then the share of realizations each assertion fails. Not a
test; the numbers go to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import warnings

import numpy as np

import dampax as dp

M, K, A = 1.0, 30.0, 0.2  # as tests/models/test_cubic.py


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 100), metavar=("FIRST", "END"))
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    k3 = 0.05 * K / A ** 2
    osc = dp.Oscillator(m=M, k=K, b=0.05, D=0.3, k3=k3)
    t = np.arange(0.0, 12.0, 0.01)
    x = np.asarray(dp.solve(osc, A, 0.0, method="reference", t_end=12.5).x(t))
    x = x + np.random.default_rng(14).normal(0.0, 0.002 * A, t.size)
    res = dp.fit(t, x, free=("b", "D", "k3"), solver=dp.LeastSquares(starts=1), model="ansatz")
    rows = []
    for seed in range(*args.seeds):
        post = dp.posterior(t, x, free=("b", "D", "k3"), start_fit=res, num_samples=100,
                            num_chains=2, num_warmup=100, seed=seed, model="ansatz")
        s = post.summary(0.95)["k3"]
        rows.append(dict(seed=seed, lo=float(s["lo"]), hi=float(s["hi"]),
                         r_hat=float(s["r_hat"])))
        print(json.dumps(rows[-1]), flush=True)
    rh = np.array([r["r_hat"] for r in rows])
    lo, hi = np.array([r["lo"] for r in rows]), np.array([r["hi"] for r in rows])
    print(f"{len(rows)} realizations: truth outside the interval {np.sum((lo >= k3) | (hi <= k3))}"
          f", width >= 0.2 k3 {np.sum(hi - lo >= 0.2 * k3)}; R-hat median "
          f"{np.median(rh):.4f}, 95 % {np.quantile(rh, 0.95):.4f}, 99 % "
          f"{np.quantile(rh, 0.99):.4f}, max {rh.max():.4f}; >= 1.05: {np.sum(rh >= 1.05)}, "
          f">= 1.15: {np.sum(rh >= 1.15)}")


if __name__ == "__main__":
    main()
