"""Benchmark: dampax's diffrax reference integrator against scipy's DOP853, per trajectory.

Random oscillators with Coulomb friction and quadratic drag, 5 s of motion, rtol = 1e-10,
atol = 1e-12 for both. dampax solves all N trajectories in one jit(vmap) call; scipy solves
a subset one by one (solve_ivp, DOP853, terminal events at v = 0, stick or reverse) and its
time per trajectory is extrapolated. Compile time is reported separately.

    python benchmarks/reference.py --n 1024
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

from dampax._oscillator import Oscillator  # noqa: E402
from dampax._reference import solve_reference  # noqa: E402

G = 9.81
T_END = 5.0
RTOL, ATOL = 1e-10, 1e-12


def random_parameters(n, seed=0):
    """m = 1 kg; k, mu, D, x0, v0 drawn uniformly (Coulomb + quadratic damping)."""
    rng = np.random.default_rng(seed)
    return dict(
        k=rng.uniform(10.0, 50.0, n), mu=rng.uniform(0.0, 0.05, n), D=rng.uniform(0.0, 3.0, n),
        x0=rng.uniform(-0.3, 0.3, n), v0=rng.uniform(-1.0, 1.0, n),
    )


def scipy_solve(k, mu, D, x0, v0, m=1.0):
    """Swing-by-swing DOP853 solution; returns (halt_time or inf, turning points)."""
    xc = mu * m * G / k
    if v0 == 0.0 and abs(x0) <= xc:
        return 0.0, []
    t, x, v = 0.0, x0, v0
    s = np.sign(v) if v != 0.0 else -np.sign(x)
    turning = []
    while True:
        def rhs(_, y, s=s):
            return [y[1], -(k / m) * y[0] - s * mu * G - (D / m) * s * y[1] ** 2]

        def event(_, y, s=s):
            return s * y[1]

        event.terminal, event.direction = True, -1
        r = solve_ivp(rhs, (t, T_END), [x, v], method="DOP853", rtol=RTOL, atol=ATOL,
                      events=event)
        if r.status != 1:
            return np.inf, turning
        t, x, v = r.t_events[0][0], r.y_events[0][0][0], 0.0
        turning.append((t, x))
        if abs(x) <= xc:
            return t, turning
        s = -np.sign(x)


def make_dampax(max_swings, max_steps_per_swing, solver, root_finder):
    @jax.jit
    def run(k, mu, D, x0, v0):
        osc = Oscillator(m=1.0, k=k, mu=mu, b=0.0, D=D)
        sol = solve_reference(osc, x0, v0, t_end=T_END, rtol=RTOL, atol=ATOL,
                              max_swings=max_swings, max_steps_per_swing=max_steps_per_swing,
                              solver=solver, root_finder=root_finder)
        return sol.halt_time, sol.swing_times, sol.turning_x, sol.valid

    return run


def time_call(fn, *args, repeat):
    """Best wall-clock and process (CPU) time of `repeat` calls."""
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return min(walls), min(cpus)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1024, help="vmapped trajectories (dampax)")
    parser.add_argument("--n-scipy", type=int, default=32, help="trajectories for scipy")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--max-swings", type=int, default=24)
    parser.add_argument("--max-steps-per-swing", type=int, default=32)
    parser.add_argument("--solver", default="dopri8")
    parser.add_argument("--root-finder", default="newton")
    args = parser.parse_args()

    p = random_parameters(args.n)
    arrays = [jnp.asarray(p[name]) for name in ("k", "mu", "D", "x0", "v0")]
    run = make_dampax(args.max_swings, args.max_steps_per_swing, args.solver, args.root_finder)

    w, c = time.perf_counter(), time.process_time()
    compiled = run.lower(*arrays).compile()
    compile_wall, compile_cpu = time.perf_counter() - w, time.process_time() - c
    halt, swing_t, swing_x, valid = (np.asarray(a) for a in compiled(*arrays))
    assert valid.all(), "budget too small for some trajectory: raise --max-swings"
    dx_wall, dx_cpu = time_call(compiled, *arrays, repeat=args.repeat)

    m = args.n_scipy
    w, c = time.perf_counter(), time.process_time()
    ref = [scipy_solve(*(p[name][i] for name in ("k", "mu", "D", "x0", "v0"))) for i in range(m)]
    sp_wall, sp_cpu = time.perf_counter() - w, time.process_time() - c

    # both solve the same problem: compare turning points and halt times of the subset
    dev = 0.0
    for i, (t_halt, turning) in enumerate(ref):
        if turning:
            tp = np.array(turning)
            n = len(tp)
            dev = max(dev, np.max(np.abs(swing_t[i, :n] - tp[:, 0])),
                      np.max(np.abs(swing_x[i, :n] - tp[:, 1])))
        assert (t_halt == np.inf) == (halt[i] == np.inf)

    per_dx, per_sp = dx_wall / args.n, sp_wall / m
    per_dx_cpu, per_sp_cpu = dx_cpu / args.n, sp_cpu / m
    print(f"{args.n} trajectories x {T_END} s, rtol {RTOL}, solver {args.solver}, "
          f"root finder {args.root_finder}, max_swings {args.max_swings}, "
          f"max_steps_per_swing {args.max_steps_per_swing}")
    print(f"max deviation from scipy (turning times [s] / positions [m]): {dev:.1e}")
    print("| | per trajectory (wall) | per trajectory (CPU) |")
    print("|---|---|---|")
    print(f"| dampax, jit(vmap) of {args.n} | {per_dx * 1e3:.4f} ms | {per_dx_cpu * 1e3:.4f} ms |")
    print(f"| scipy DOP853, {m} in a loop | {per_sp * 1e3:.2f} ms | {per_sp_cpu * 1e3:.2f} ms |")
    print(f"| ratio scipy / dampax | {per_sp / per_dx:.0f}x | {per_sp_cpu / per_dx_cpu:.0f}x |")
    print(f"| dampax compile (once) | {compile_wall:.1f} s | {compile_cpu:.1f} s |")


if __name__ == "__main__":
    main()
