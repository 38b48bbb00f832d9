"""Cost of sampling the reference at given times, against the bare reference solve.

The problem of issue 12: 2,048 trajectories (d0/(w0 A0) in [0, 0.1], d2 A0/w0 in [0, 0.75],
phi0 in [0, 2 pi), w0 = A0 = 1), 20 undamped periods, vmapped in chunks like an error map. In
the same run, best of --repeat calls after compiling, CPU time (all threads) and wall time:

    bare:    solve_reference(...).halt_time                       (no dense output)
    grid:    solve_reference(...).state(t, grid=(0, dt))          (1,280 sorted samples, merged)
    search:  solve_reference(...).state(t)  under jit             (a binary search per sample)

    python benchmarks/dense_output.py [--n 2048] [--chunk 128] [--repeat 5]
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import dampax as dp


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=2048)
    p.add_argument("--chunk", type=int, default=128, help="trajectories per vmapped call")
    p.add_argument("--periods", type=int, default=20)
    p.add_argument("--samples-per-period", type=int, default=64)
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    n, chunk = args.n, args.chunk
    rows = np.stack([rng.uniform(0, 0.1, n), rng.uniform(0, 0.75, n),
                     rng.uniform(0, 2 * np.pi, n)], axis=-1)
    dt = 2 * math.pi / args.samples_per_period
    t = jnp.arange(args.periods * args.samples_per_period) * dt
    opts = dict(t_end=float(t[-1]), max_swings=2 * args.periods + 6, max_steps_per_swing=64)

    def solve(r):
        osc = dp.from_ratios(r[:, 0], 0.0, r[:, 1], m=1.0, k=1.0, A0=1.0)
        return dp.solve(osc, jnp.cos(r[:, 2]), -jnp.sin(r[:, 2]), method="reference", **opts)

    kernels = {
        "bare solve (halt time only)": jax.jit(lambda r: solve(r).halt_time),
        "solve + x, v on the grid (merged)": jax.jit(
            lambda r: jnp.sum(jnp.nan_to_num(solve(r).state(t, grid=(0.0, dt))[0]), -1)),
        "solve + x, v (binary search)": jax.jit(
            lambda r: jnp.sum(jnp.nan_to_num(solve(r).state(t)[0]), -1)),
    }
    chunks = [jnp.asarray(rows[i:i + chunk]) for i in range(0, n, chunk)]
    best = {}
    for name, fn in kernels.items():
        jax.block_until_ready([fn(c) for c in chunks])  # compile
        best[name] = (math.inf, math.inf)
    for _ in range(args.repeat):  # in turns, so that load slows all alike
        for name, fn in kernels.items():
            w, c = time.perf_counter(), time.process_time()
            jax.block_until_ready([fn(c_) for c_ in chunks])
            w, c = time.perf_counter() - w, time.process_time() - c
            best[name] = (min(best[name][0], w), min(best[name][1], c))
    bare = best["bare solve (halt time only)"]
    print(f"{n} trajectories in chunks of {chunk}, {t.size} samples each; "
          f"{jax.devices()[0].device_kind}")
    for name, (w, c) in best.items():
        print(f"  {name:<36} {w / n * 1e3:7.4f} ms wall, {c / n * 1e3:7.4f} ms CPU per "
              f"trajectory; x bare: {w / bare[0]:5.2f} wall, {c / bare[1]:5.2f} CPU")


if __name__ == "__main__":
    main()
