"""Issue 24, items 1 and 2: what the reference's dense output and an error map cost against
the bare reference solve, all in one run (ratios of CPU time, best of --repeat calls after a
warm-up call that compiles).

Item 1 (samples): 1,024 random trajectories (k ~ U[10, 50], mu ~ U[0, 0.05], D ~ U[0, 3],
b ~ U[0, 0.5], x0 ~ U[-0.3, 0.3], v0 ~ U[-1, 1], 5 s), x at --samples sorted times:
  - bare:    dp.solve(osc, x0, v0, method="reference", t_end=5)
  - natural: the same, then sol.x(ts)         (the call a user writes; limit 1.5x bare)
  - ts=:     dp.solve(..., ts=ts), then sol.x(ts)
  - unsorted: sol.x(ts[::-1]) (the general path, for reference)

Item 2 (work that follows the motion): the default error-map grid (16 d0 x 16 d2 x 8 phi0,
the four default models, 64 samples per period) at periods = 20, 100 and 1000 (limit: 1000
costs at most 3x 20), and the map per point against a bare reference solve of the same points
over the same window (limit 2x).

    python benchmarks/engine.py                  # both
    python benchmarks/engine.py --only samples   # or --only map; --grid 8x8x4 for a quick run
"""

from __future__ import annotations

import argparse
import math
import time


def parse():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=("samples", "map"))
    p.add_argument("--n", type=int, default=1024)
    p.add_argument("--samples", type=int, default=1000)
    p.add_argument("--grid", default="16x16x8")
    p.add_argument("--periods", default="20,100,1000")
    p.add_argument("--repeat", type=int, default=5)
    return p.parse_args()


def best(fn, repeat):
    """Minimum CPU and wall seconds of fn() (blocked until ready) over `repeat` calls."""
    import jax

    jax.block_until_ready(fn())
    cpu, wall = [], []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        jax.block_until_ready(fn())
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return min(cpu), min(wall)


def samples(args):
    import jax.numpy as jnp
    import numpy as np

    import dampax as dp

    rng = np.random.default_rng(0)
    n = args.n
    k = rng.uniform(10, 50, n)
    mu = rng.uniform(0, 0.05, n)
    D = rng.uniform(0, 3, n)
    b = rng.uniform(0, 0.5, n)
    x0 = rng.uniform(-0.3, 0.3, n)
    v0 = rng.uniform(-1, 1, n)
    osc = dp.Oscillator(m=1.0, k=k, mu=mu, b=b, D=D)
    ts = jnp.asarray(np.linspace(0.0, 5.0, args.samples))
    back = ts[::-1]

    def bare():
        return dp.solve(osc, x0, v0, method="reference", t_end=5.0).halt_time

    def natural():
        return dp.solve(osc, x0, v0, method="reference", t_end=5.0).x(ts)

    def filled():
        return dp.solve(osc, x0, v0, method="reference", t_end=5.0, ts=ts).x(ts)

    sol = dp.solve(osc, x0, v0, method="reference", t_end=5.0)

    def unsorted():
        return sol.x(back)

    # the same samples (the filled path evaluates each sample's row in another fusion: the
    # last bits may differ)
    np.testing.assert_allclose(np.asarray(natural()), np.asarray(filled()), rtol=0,
                               atol=1e-14)
    np.testing.assert_allclose(np.asarray(unsorted())[:, ::-1], np.asarray(natural()),
                               rtol=0, atol=1e-15)
    rows = [("bare solve", bare), ("solve, then sol.x(ts)", natural),
            ("solve(ts=ts), then sol.x(ts)", filled)]
    base = None
    print(f"\nitem 1: {n} trajectories x {args.samples} sorted samples (5 s)")
    print(f"{'call':34s} {'CPU us/traj':>12s} {'wall us/traj':>13s} {'/ bare (CPU)':>13s}")
    for name, fn in rows:
        c, w = best(fn, args.repeat)
        base = base or c
        print(f"{name:34s} {c / n * 1e6:12.2f} {w / n * 1e6:13.2f} {c / base:13.2f}")
    c, w = best(unsorted, args.repeat)
    print(f"{'sol.x(reversed ts) (search path)':34s} {c / n * 1e6:12.2f} {w / n * 1e6:13.2f} "
          f"{'(' + format((c + base) / base, '.2f') + ' with the solve)':>13s}")
    print("limit: the natural call at most 1.5x the bare solve")


def map_costs(args):
    import jax
    import numpy as np

    import dampax as dp
    from dampax._oscillator import from_ratios
    from dampax._studies._maps import error_map

    n0, n2, nph = (int(v) for v in args.grid.lower().split("x"))
    axes = dict(d0_ratio=np.linspace(0.0, 0.1, n0), d2_ratio=np.linspace(0.0, 0.75, n2),
                phi0=np.linspace(0.0, 7 * math.pi / 8, nph))
    npts = n0 * n2 * nph
    print(f"\nitem 2: error map, grid {n0} x {n2} x {nph} = {npts} points, 64 samples/period")
    print(f"{'periods':>8s} {'map CPU s':>10s} {'map wall s':>11s} {'/ periods=20':>13s} "
          f"{'bare solve CPU s':>17s} {'map / bare':>11s} {'median window (T0)':>19s}")
    base = None
    for p in (float(v) for v in args.periods.split(",")):
        def run(p=p):
            return error_map(**axes, periods=p, progress=False)

        c, w = best(run, max(1, args.repeat // 2) if p > 100 else args.repeat)
        ds = run()
        base = base or c
        # the bare reference over the same points and window (w0 = A0 = 1, as the map)
        d0, d2, ph = np.meshgrid(axes["d0_ratio"], axes["d2_ratio"], axes["phi0"],
                                 indexing="ij")
        osc = from_ratios(d0.ravel(), 0.0, d2.ravel(), m=1.0, k=1.0, A0=1.0)
        x0, v0 = np.cos(ph.ravel()), -np.sin(ph.ravel())
        t_end = p * 2 * math.pi

        def bare(osc=osc, t_end=t_end, x0=x0, v0=v0):
            return dp.solve(osc, x0, v0, method="reference", t_end=t_end).halt_time

        cb, _ = best(bare, max(1, args.repeat // 2))
        win = float(np.nanmedian(np.asarray(ds["window"])))
        print(f"{p:8g} {c:10.2f} {w:11.2f} {c / base:13.2f} {cb:17.2f} {c / cb:11.2f} "
              f"{win:19.2f}")
        jax.clear_caches()
    print("limits: periods=1000 at most 3x periods=20; a map point at most 2x a bare solve")


def main():
    args = parse()
    import dampax  # noqa: F401  (x64, the cache)

    if args.only in (None, "samples"):
        samples(args)
    if args.only in (None, "map"):
        map_costs(args)


if __name__ == "__main__":
    main()
