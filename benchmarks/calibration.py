"""Calibration of the intervals (issue 11, item 6): how often do they contain the truth?

    python benchmarks/calibration.py [--traces 40] [--posterior 12] [--level 0.9]

Synthetic traces from the reference integrator (eq. 3, exact stick-slip; the documented example
oscillator: m = 0.2 kg, k = 15 N/m, mu = 0.002, D = 0.02 kg/m, x0 = 5 cm, 100 samples/s for
20 s) plus AR(1) noise with coefficient 0.9 (marginal sd 0.2 mm), one noise realisation per
trace (fixed seeds). All traces are fitted in ONE vmapped call of the pure core
(``fit_arrays``, the ansatz, w0 fitted, m known), then per trace:

- the delta-method interval value +- z stderr (white-noise assumption),
- ``conf_interval``'s interval: the Newey-West (HAC) sandwich of ``_intervals``,
- (first ``--posterior`` traces) the central interval of ``dp.posterior`` (NUTS, AR(1) noise;
  2 chains x ``--draws`` draws after ``--warmup`` steps, to keep the run short).

Prints the coverage of mu and D for each (the goal for conf_interval and the posterior: 80-97 %
at a 90 % level) and the binomial standard error of each rate. Not a test: run by hand, the
numbers go to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import math
import time
from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np

import dampax as dp
from dampax._fit import PARAMS, fit_arrays, initial_guess
from dampax._fit._intervals import hac_covariance

TRUTH = dict(m=0.2, k=15.0, mu=0.002, b=0.0, D=0.02, x0=0.05, v0=0.0)
RATE, T_END, SD, PHI = 100.0, 20.0, 2e-4, 0.9
FREE = ("mu", "D")


def reference_curve(t):
    osc = dp.Oscillator(m=TRUTH["m"], k=TRUTH["k"], mu=TRUTH["mu"], D=TRUTH["D"])
    w0 = math.sqrt(TRUTH["k"] / TRUTH["m"])
    sol = dp.solve(osc, TRUTH["x0"], TRUTH["v0"], method="reference", t_end=float(t[-1]) + 0.01,
                   max_swings=int(1.2 * T_END * w0 / math.pi) + 8)
    return np.asarray(sol.x(jnp.asarray(t)))


def ar1(n, seed):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal(n) * SD * math.sqrt(1 - PHI ** 2)
    e = np.empty(n)
    e[0] = rng.standard_normal() * SD
    for i in range(1, n):
        e[i] = PHI * e[i - 1] + z[i]
    return e


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--traces", type=int, default=40)
    ap.add_argument("--posterior", type=int, default=12,
                    help="traces that also get a posterior (0: none)")
    ap.add_argument("--level", type=float, default=0.9)
    ap.add_argument("--draws", type=int, default=500, help="posterior draws per chain")
    ap.add_argument("--warmup", type=int, default=300, help="posterior warm-up steps")
    args = ap.parse_args()
    z = NormalDist().inv_cdf(0.5 + 0.5 * args.level)
    t = np.arange(0.0, T_END, 1.0 / RATE)
    clean = reference_curve(t)
    xs = np.stack([clean + ar1(t.size, 1000 + i) for i in range(args.traces)])
    osc = dp.Oscillator(m=TRUTH["m"], k=TRUTH["k"])
    p0 = np.stack([initial_guess(t, x, free=FREE, oscillator=osc, fit_omega0=True) for x in xs])
    batch = jax.jit(jax.vmap(lambda x, p: fit_arrays(t, x, p, free=FREE, fit_omega0=True,
                                                     m=TRUTH["m"])))
    began = time.perf_counter()
    out = batch(jnp.asarray(xs), jnp.asarray(p0))
    jax.block_until_ready(out.params)
    print(f"{args.traces} vmapped fits (compilation included): {time.perf_counter() - began:.1f} s;"
          f" converged: {int(np.sum(np.asarray(out.success)))}")
    params, stderr = np.asarray(out.params), np.asarray(out.stderr)
    idx = [PARAMS.index(n) for n in FREE]
    varied = [i for i, n in enumerate(PARAMS) if n in FREE or n in ("w0", "offset", "x0", "v0")]
    per_period = 2 * math.pi / math.sqrt(TRUTH["k"] / TRUTH["m"]) * RATE
    hits = {"delta": np.zeros((args.traces, 2), bool), "hac": np.zeros((args.traces, 2), bool)}
    width = {"delta": [], "hac": []}
    for j in range(args.traces):
        J = np.asarray(out.jac[j])[:, varied]
        r = np.asarray(out.resid[j])
        cov, _ = hac_covariance(J, r, period_samples=per_period)
        sd_hac = np.sqrt(np.diag(cov))
        for k, i in enumerate(idx):
            truth = TRUTH[PARAMS[i]]
            hits["delta"][j, k] = abs(params[j, i] - truth) < z * stderr[j, i]
            s = sd_hac[varied.index(i)]
            hits["hac"][j, k] = abs(params[j, i] - truth) < z * s
            width["delta"].append(stderr[j, i] / truth)
            width["hac"].append(s / truth)
    post_hits = []
    if args.posterior:
        began = time.perf_counter()
        for j in range(min(args.posterior, args.traces)):
            post = dp.posterior(t, xs[j], oscillator=osc, free=FREE, fit_omega0=True,
                                start="data", num_samples=args.draws, num_chains=2,
                                num_warmup=args.warmup, seed=j)
            s = post.summary(args.level)
            post_hits.append([s[n]["lo"] < TRUTH[n] < s[n]["hi"] for n in FREE])
        print(f"{len(post_hits)} posteriors (2 chains x {args.draws} draws): "
              f"{time.perf_counter() - began:.1f} s")
    n = args.traces
    print(f"\ncoverage of the {100 * args.level:g} % intervals (truth inside), AR(1) noise "
          f"phi = {PHI}, {n} traces:")
    for name, h in hits.items():
        for k, p in enumerate(FREE):
            rate = h[:, k].mean()
            se = 100 * math.sqrt(rate * (1 - rate) / n)
            print(f"  {name:<9} {p:<3} {100 * rate:5.1f} %  (+- {se:.1f})")
    if post_hits:
        h = np.asarray(post_hits)
        for k, p in enumerate(FREE):
            rate = h[:, k].mean()
            print(f"  posterior {p:<3} {100 * rate:5.1f} %  (+- "
                  f"{100 * math.sqrt(rate * (1 - rate) / len(h)):.1f}, {len(h)} traces)")
    for k, i in enumerate(idx):
        est = params[:, i] / TRUTH[PARAMS[i]] - 1
        wd = np.median(np.asarray(width["delta"])[k::2])
        wh = np.median(np.asarray(width["hac"])[k::2])
        print(f"  {PARAMS[i]}: estimate / truth - 1: mean {est.mean():+.4f}, sd "
              f"{est.std(ddof=1):.4f}; median relative sd claimed: delta {wd:.4f}, HAC {wh:.4f}")


if __name__ == "__main__":
    main()
