"""Benchmark (issue 24): dampax's reference solve against a compiled scalar peer, whole job.

The job: solve eq. 3 (Coulomb friction, viscous and quadratic drag, exact stick-slip) for
N random trajectories over 5 s and return x at 1,000 uniform samples in [0, 5 s]. Contestants:

- numba: ``benchmarks/peers/dop853_numba.py``, a port of scipy's/Hairer's DOP853 with dense
  output and the same stick-slip events, looping over the trajectories on one thread;
- dampax: ``dp.solve(dp.Oscillator(...batched fields...), x0, v0, method="reference", ...)``
  then ``sol.x(ts)``, in one jitted function ("natural call"), and the same under ``jax.vmap``
  of a scalar solve;
- dampax with ``engine="diffrax"`` (issue 35): the same call integrated by diffrax's Dopri8
  swing by swing with its events (the design card's reference integrator), at its own
  loosest tolerance that meets the target;
- limits: a bare fused ``x0 cos(w0 t) exp(-t)`` over the same N x samples (jitted), and the
  scipy ``solve_ivp(DOP853)`` loop (timed on a few trajectories, extrapolated).

Accuracy first: the truth is scipy's DOP853 at rtol 1e-12, atol 1e-14 (terminal events, the
same stick-slip logic, dense output) on the first ``--check`` trajectories. Each contestant
runs at the loosest rtol of TOLERANCES (atol = rtol / 100) whose max |x - x_truth| over those
samples is <= 1e-10, and is timed there: best of ``--repeat`` calls after a warm-up call, wall
clock and process CPU time, per trajectory.

    python benchmarks/peer_race.py                    # --n 1024 --samples 1000 --check 64
    python benchmarks/peer_race.py --n 64 --rtol 1e-10

Needs the ``bench`` extra (numba, scipy). numba runs with NUMBA_NUM_THREADS=1.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # before numba is imported

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import dampax as dp  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from benchmarks.peers.dop853_numba import solve_many  # noqa: E402

G = 9.81
M = 1.0
T_END = 5.0
TOLERANCES = (1e-8, 3e-9, 1e-9, 3e-10, 1e-10, 3e-11, 1e-11)
TARGET = 1e-10
TRUTH_RTOL, TRUTH_ATOL = 1e-12, 1e-14
NAMES = ("k", "mu", "b", "D", "x0", "v0")


def random_problem(n, seed=0):
    """m = 1; k, mu, D, b, x0, v0 uniform (k3 = 0); drawn in this order."""
    rng = np.random.default_rng(seed)
    p = dict(k=rng.uniform(10.0, 50.0, n), mu=rng.uniform(0.0, 0.05, n),
             D=rng.uniform(0.0, 3.0, n), b=rng.uniform(0.0, 0.5, n),
             x0=rng.uniform(-0.3, 0.3, n), v0=rng.uniform(-1.0, 1.0, n))
    return {name: p[name] for name in NAMES}


def scipy_trajectory(k, mu, b, D, x0, v0, ts, rtol, atol):
    """x at ts: solve_ivp DOP853 swing by swing (terminal event s v = 0, then stick or
    reverse), sampled from each swing's dense output."""
    out = np.full(ts.shape, np.nan)
    out[ts == 0.0] = x0
    if v0 == 0.0 and abs(k * x0) <= mu * M * G:
        out[ts > 0.0] = x0
        return out
    t, x, v = 0.0, x0, v0
    s = np.sign(v) if v != 0.0 else -np.sign(x)
    while t < T_END:
        def rhs(_, y, s=s):
            return [y[1], -(k / M) * y[0] - s * mu * G - (b / M) * y[1] - (D / M) * s * y[1] ** 2]

        def event(_, y, s=s):
            return s * y[1]

        event.terminal, event.direction = True, -1
        r = solve_ivp(rhs, (t, T_END), [x, v], method="DOP853", rtol=rtol, atol=atol,
                      events=event, dense_output=True)
        t_stop = r.t_events[0][0] if r.status == 1 else T_END
        inside = (ts > t) & (ts <= t_stop)
        if inside.any():  # (a swing may fall between two samples)
            out[inside] = r.sol(ts[inside])[0]
        if r.status != 1:
            break
        t, x, v = t_stop, r.y_events[0][0][0], 0.0
        if abs(k * x) <= mu * M * G:
            out[ts > t] = x
            break
        s = -np.sign(x)
    return out


def scipy_many(p, ts, rtol, atol, count):
    return np.array([scipy_trajectory(*(p[name][i] for name in NAMES), ts, rtol, atol)
                     for i in range(count)])


def max_error(xs, truth):
    """max |x - x_truth| over the checked rows; inf if a value is NaN where truth is not."""
    diff = np.abs(np.asarray(xs)[:truth.shape[0]] - truth)
    return float("inf") if np.isnan(diff).any() else float(diff.max())


def best_of(fn, repeat):
    """(wall, CPU) of the fastest of `repeat` calls (after one warm-up call)."""
    jax.block_until_ready(fn())
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return min(walls), min(cpus)


def pick(tolerances, error_at, label):
    """The loosest tolerance whose error is <= TARGET (the tightest if none); prints each."""
    tried = []
    for rtol in tolerances:
        err = error_at(rtol)
        tried.append((rtol, err))
        print(f"  {label}: rtol {rtol:.0e}: max error {err:.2e}", flush=True)
        if err <= TARGET:
            return rtol, err, True
    rtol, err = min(tried, key=lambda a: a[1])
    return rtol, err, False


class Dampax:
    """Compiled dampax programs f(k, mu, b, D, x0, v0) -> x (N, samples), one per rtol."""

    def __init__(self, ts, vmapped, with_ts=None, engine="dampax"):
        self.ts, self.vmapped, self.with_ts, self.engine = ts, vmapped, with_ts, engine
        self.compiled, self.compile_s = {}, {}

    def _function(self, rtol, with_ts):
        ts, extra = self.ts, ({"ts": self.ts} if with_ts else {})
        extra["engine"] = self.engine

        def f(k, mu, b, D, x0, v0):
            osc = dp.Oscillator(m=M, k=k, mu=mu, b=b, D=D)
            sol = dp.solve(osc, x0, v0, method="reference", t_end=T_END, rtol=rtol,
                           atol=rtol * 1e-2, **extra)
            return sol.x(ts)

        return jax.jit(jax.vmap(f) if self.vmapped else f)

    def get(self, rtol, args):
        if rtol not in self.compiled:
            w = time.perf_counter()
            for with_ts in ((True, False) if self.with_ts is None else (self.with_ts,)):
                try:
                    compiled = self._function(rtol, with_ts).lower(*args).compile()
                except (TypeError, ValueError) as err:
                    if not with_ts or self.with_ts is not None:
                        raise
                    print(f"  dampax: solve(..., ts=) not supported ({type(err).__name__}: "
                          f"{str(err)[:100]}); sol.x(ts) alone", flush=True)
                    continue
                self.with_ts = with_ts
                break
            self.compiled[rtol] = compiled
            self.compile_s[rtol] = time.perf_counter() - w
        return self.compiled[rtol]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1024, help="trajectories")
    parser.add_argument("--samples", type=int, default=1000, help="uniform samples in [0, 5 s]")
    parser.add_argument("--check", type=int, default=64,
                        help="trajectories compared to the scipy truth")
    parser.add_argument("--rtol", type=float, default=None,
                        help="force this rtol (atol = rtol / 100) for numba and dampax")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--scipy-n", type=int, default=8,
                        help="trajectories of the timed scipy loop (extrapolated)")
    parser.add_argument("--no-vmap", action="store_true",
                        help="skip the jax.vmap-of-a-scalar-solve variant")
    parser.add_argument("--no-diffrax", action="store_true",
                        help="skip dampax's diffrax engine (engine='diffrax')")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    n, check = args.n, min(args.check, args.n)
    tolerances = TOLERANCES if args.rtol is None else (args.rtol,)

    p = random_problem(n, args.seed)
    ts = np.linspace(0.0, T_END, args.samples)
    arrays = [jnp.asarray(p[name]) for name in NAMES]
    print(f"{n} trajectories, {args.samples} samples in [0, {T_END} s], truth on {check}; "
          f"jax {jax.__version__} on {jax.devices()[0].platform}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; dampax "
          f"{dp.__version__} from {os.path.dirname(dp.__file__)}", flush=True)

    w = time.perf_counter()
    truth = scipy_many(p, ts, TRUTH_RTOL, TRUTH_ATOL, check)
    print(f"truth (scipy DOP853, rtol {TRUTH_RTOL:g}): {time.perf_counter() - w:.1f} s",
          flush=True)

    rows = {}  # name -> (rtol, error, met, wall, cpu)

    # numba peer
    def numba_run(rtol, count):
        return solve_many(*(p[name][:count] for name in NAMES), m=M, g=G, t_end=T_END, ts=ts,
                          rtol=rtol, atol=rtol * 1e-2, return_stats=True)

    w = time.perf_counter()
    numba_run(1e-8, 1)
    print(f"numba: first call (compile): {time.perf_counter() - w:.1f} s")
    rtol, err, met = pick(tolerances, lambda r: max_error(numba_run(r, check)[0], truth), "numba")
    steps = numba_run(rtol, n)[1]
    wall, cpu = best_of(lambda: numba_run(rtol, n), args.repeat)
    rows["numba DOP853, 1 thread"] = (rtol, err, met, wall, cpu)
    print(f"  numba at rtol {rtol:.0e}: {steps[:, 0].mean():.1f} accepted + "
          f"{steps[:, 1].mean():.1f} rejected steps and {steps[:, 2].mean():.1f} swings per "
          f"trajectory; {wall / n * 1e6:.1f} us per trajectory", flush=True)
    numba_rtol = rtol

    # dampax: the natural call (batched fields) and jax.vmap of a scalar solve
    variants = [("dampax, batched fields", False, "dampax")]
    if not args.no_vmap:
        variants.append(("dampax, jax.vmap(scalar)", True, "dampax"))
    if not args.no_diffrax:
        variants.append(("dampax engine='diffrax', batched fields", False, "diffrax"))
    dampax_rtol = with_ts = None
    for name, vmapped, engine in variants:
        prog = Dampax(ts, vmapped, with_ts, engine)
        if dampax_rtol is None or engine != "dampax":  # each engine at its own tolerance
            rtol, err, met = pick(
                tolerances, lambda r, p=prog: max_error(p.get(r, arrays)(*arrays), truth),
                f"dampax ({engine})")
            dampax_rtol = dampax_rtol or rtol
        else:  # the vmapped variant at the natural call's tolerance
            rtol = dampax_rtol
            err = max_error(prog.get(rtol, arrays)(*arrays), truth)
            met = err <= TARGET
        compiled = prog.get(rtol, arrays)
        wall, cpu = best_of(lambda c=compiled: c(*arrays), args.repeat)
        rows[name] = (rtol, err, met, wall, cpu)
        with_ts = prog.with_ts
        print(f"  {name}: solve(ts=) used: {prog.with_ts}; compile {prog.compile_s[rtol]:.1f} s"
              f" at rtol {rtol:.0e}; {wall / n * 1e6:.1f} us per trajectory", flush=True)

    # the limit: a bare fused cos over the same samples
    x0, w0 = jnp.asarray(p["x0"]), jnp.sqrt(jnp.asarray(p["k"]) / M)
    t_dev = jnp.asarray(ts)
    bare = jax.jit(lambda x0, w0, t: x0[:, None] * jnp.cos(w0[:, None] * t) * jnp.exp(-t))
    wall, cpu = best_of(lambda: bare(x0, w0, t_dev), args.repeat)
    rows["limit: bare fused x0 cos(w0 t) exp(-t)"] = (None, None, True, wall, cpu)

    # scipy loop, at the numba peer's tolerance (the same algorithm), extrapolated
    m = min(args.scipy_n, n)
    w, c = time.perf_counter(), time.process_time()
    scipy_many(p, ts, numba_rtol, numba_rtol * 1e-2, m)
    wall, cpu = (time.perf_counter() - w) * n / m, (time.process_time() - c) * n / m
    rows[f"scipy solve_ivp loop ({m} timed)"] = (numba_rtol, None, True, wall, cpu)

    ref = {key: rows[key] for key in ("numba DOP853, 1 thread",
                                      f"scipy solve_ivp loop ({m} timed)",
                                      "limit: bare fused x0 cos(w0 t) exp(-t)")}
    print(f"\nwhole job: solve + x at {args.samples} samples, {n} trajectories; max error "
          f"against scipy rtol {TRUTH_RTOL:g} on {check} trajectories; per trajectory = best "
          f"of {args.repeat} / {n}")
    print("| | rtol | max error | per trajectory, wall / CPU | / numba | / scipy | / cos |")
    print("|---|---|---|---|---|---|---|")
    for name, (rtol, err, met, wall, cpu) in rows.items():
        tol = "" if rtol is None else f"{rtol:.0e}"
        e = "" if err is None else f"{err:.1e}" + ("" if met else " (> 1e-10)")
        ratios = " | ".join(f"{wall / r[3]:.3g} / {cpu / r[4]:.3g}" for r in ref.values())
        print(f"| {name} | {tol} | {e} | {wall / n * 1e6:.2f} / {cpu / n * 1e6:.2f} us | "
              f"{ratios} |")
    d, nb = rows["dampax, batched fields"], rows["numba DOP853, 1 thread"]
    print(f"\ndampax / numba (wall): {d[3] / nb[3]:.2f} (issue 24 goal <= 1.0, moonshot 0.5)")


if __name__ == "__main__":
    main()
