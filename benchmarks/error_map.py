"""Throughput of dampax.error_map: grid points per second, compilation timed separately.

Default: the grid of `dampax errormap` (16 d0 x 16 d2 x 8 phi0 = 2048 points, 20 periods,
64 samples per period, the four default models), once against the diffrax reference and once,
all analytic, against the exact half-swings (which have no quadratic drag, so that grid is
d0 in [0, 0.1] x d1/w0 in [0, 0.2] x phi0, the same number of points).

    python benchmarks/error_map.py                                   # both references
    python benchmarks/error_map.py --reference coulomb_exact --n 1000000 --chunk-size 4096
    python benchmarks/error_map.py --host-devices 2                  # CPU: one device per core

--n N picks a near-cubic d0 x d2 x phi0 grid of about N points (a 10^6-point analytic map on a
GPU); --grid D0xD2xPHI sets it exactly. --host-devices splits the CPU into N XLA devices (must
be set before jax is imported, so it is an option of this script, not of the library).
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import time


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grid", default="16x16x8", help="d0 x d2 x phi0 (default: %(default)s)")
    p.add_argument("--n", type=int, help="about this many points (near-cubic grid)")
    p.add_argument("--reference", default="both",
                   choices=("both", "reference", "coulomb_exact"))
    p.add_argument("--models", default="matched,undamped,matched_tail,rizcallah")
    p.add_argument("--periods", type=float, default=20.0)
    p.add_argument("--samples-per-period", type=int, default=64)
    p.add_argument("--chunk-size", type=int, help="points per device per step (default: 128 "
                   "with the diffrax reference, 2048 without; at most the grid / devices)")
    p.add_argument("--host-devices", type=int, help="CPU only: XLA host devices")
    p.add_argument("--no-bare", action="store_true",
                   help="skip timing the bare reference solve over the same grid")
    return p.parse_args()


def main() -> None:
    args = parse()
    if args.host_devices:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_"
                                   f"platform_device_count={args.host_devices}").strip()
    import jax
    import numpy as np

    import dampax as dp
    from dampax._studies._maps import error_map

    if args.n:
        side = max(2, round((args.n / 8) ** 0.5))  # d0 x d2 x 8 phi0 ... grows d0, d2
        side3 = max(2, round(args.n ** (1 / 3)))
        n0 = n2 = side3 if args.n > 8 * side3**2 else side
        nph = max(1, round(args.n / (n0 * n2)))
    else:
        n0, n2, nph = (int(v) for v in args.grid.lower().split("x"))
    phi0 = np.linspace(0.0, math.pi, nph, endpoint=False)
    grids = {  # the exact half-swings have no quadratic drag: map d0 x d1 there instead
        "reference": dict(d0_ratio=np.linspace(0.0, 0.1, n0), d1_ratio=0.0,
                          d2_ratio=np.linspace(0.0, 0.75, n2), phi0=phi0),
        "coulomb_exact": dict(d0_ratio=np.linspace(0.0, 0.1, n0),
                              d1_ratio=np.linspace(0.0, 0.2, n2), d2_ratio=0.0, phi0=phi0)}
    n = n0 * n2 * nph
    models = tuple(args.models.split(","))
    refs = ("reference", "coulomb_exact") if args.reference == "both" else (args.reference,)
    ndev = jax.local_device_count()
    print(f"dampax {dp.__version__}, jax {jax.__version__}: {ndev} x "
          f"{jax.devices()[0].device_kind}; grid {n0} d0 x {n2} d2 (d1 with the exact "
          f"reference) x {nph} phi0 = {n} points; "
          f"{args.periods:g} periods x {args.samples_per_period} samples; models "
          f"{', '.join(models)}")
    for ref in refs:
        chunk = args.chunk_size or min(128 if ref == "reference" else 2048, -(-n // ndev))
        common = dict(models=models, periods=args.periods, reference=ref,
                      samples_per_period=args.samples_per_period, chunk_size=chunk,
                      progress=False)
        one_step = dict(d0_ratio=np.linspace(0.0, 0.1, chunk * ndev), d2_ratio=0.3, phi0=0.4)
        start = time.perf_counter()
        error_map(**one_step, **common)
        first = time.perf_counter() - start
        start = time.perf_counter()
        error_map(**one_step, **common)
        step = time.perf_counter() - start
        elapsed = math.inf
        for _ in range(1 if n > 100_000 else 3):  # best of 3 (the machine may be shared)
            start = time.perf_counter()
            ds = error_map(**grids[ref], **common)
            elapsed = min(elapsed, time.perf_counter() - start)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        bad = int((~ds["reference_valid"]).sum())
        print(f"  reference={ref:<13} chunk {chunk:>5}/device: compile ~{first - step:5.1f} s; "
              f"{n} points in {elapsed:7.2f} s = {n / elapsed:8.0f} points/s; peak RSS "
              f"{rss:6.0f} MiB; reference invalid at {bad} points")
        if ref == "reference" and not args.no_bare:
            bare = bare_reference(grids[ref], chunk * ndev, args.periods,
                                  args.samples_per_period)
            print(f"    bare reference solve (halt time only, same grid, window, budget and "
                  f"chunks): {bare:7.2f} s; map / bare = {elapsed / bare:5.2f}")
        sys.stdout.flush()


def bare_reference(axes: dict, chunk: int, periods: float, spp: int) -> float:
    """Wall time of the reference solve alone over the map's grid (best of 2, compiled)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import dampax as dp

    values = [np.atleast_1d(np.asarray(axes[k], dtype=float))
              for k in ("d0_ratio", "d1_ratio", "d2_ratio", "phi0")]
    grid = np.stack([g.ravel() for g in np.meshgrid(*values, indexing="ij")], axis=-1)
    n_samples = int(math.floor(periods * spp + 1e-9)) + 1
    t_end = (n_samples - 1) * 2.0 * math.pi / spp
    opts = dict(t_end=t_end, max_swings=2 * math.ceil(periods) + 6, max_steps_per_swing=64)

    @jax.jit
    def solve(rows):
        osc = dp.from_ratios(rows[:, 0], rows[:, 1], rows[:, 2], m=1.0, k=1.0, A0=1.0)
        return dp.solve(osc, jnp.cos(rows[:, 3]), -jnp.sin(rows[:, 3]), method="reference",
                        **opts).halt_time

    pad = -len(grid) % chunk
    grid = np.concatenate([grid, np.repeat(grid[:1], pad, axis=0)])
    best = math.inf
    for _ in range(3):  # the first compiles
        start = time.perf_counter()
        jax.block_until_ready([solve(jnp.asarray(grid[i:i + chunk]))
                               for i in range(0, len(grid), chunk)])
        best = min(best, time.perf_counter() - start)
    return best


if __name__ == "__main__":
    main()
