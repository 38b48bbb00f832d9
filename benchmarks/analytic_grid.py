"""Cost of evaluating the matched ansatz x(t) on a grid, against a bare fused kernel.

Both kernels are jitted, vmapped over the grid points and reduced to one scalar (max |x|), so
the timing is that of the fused evaluation, not of moving 64 x 64 x 16 x 1000 numbers around:

    bare:     0.2 cos(w0 t + phi) / (1 + d t)                (one cos, one division)
    matched:  dp.solve(osc, x0, v0).x(t) = A f(t) cos(w0 t + phi), with A, phi from the quartic
              (eq. 22, per point) and f(t) in closed form (tan/tanh regimes, clamp at the halt)
    lean:     the same x(t) from the same solution, but with the per-point constants
              (q = sqrt|b'^2/4 - ac|, c + b'/2, a + b'/2, tau) computed once per point and a
              lean per-sample formula, f = (1 - K1 T)/(1 + K2 T), T = tan(q t)/q or tanh(q t)/q,
              i.e. without the series branch and the per-sample square roots and masks that
              keep the library's f(t) differentiable across the regime boundaries (a proposal
              for a value-only fast path in _ansatz.py; checked against sol.x below)

Run:  python benchmarks/analytic_grid.py [--grid 64x64x16] [--samples 1000] [--repeats 5]
The paper's block: m = 1 kg, k = 30 N/m, A0 = 0.2 m; d0/(w0 A0) in [0, 0.1], d2 A0/w0 in
[0, 0.75], phi0 in [0, 2 pi), t over 10 undamped periods.
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import dampax as dp


def timings(kernels: dict, repeats: int) -> dict[str, tuple[float, float]]:
    """Per kernel: (first call incl. compilation, best of ``repeats`` further calls) [s].

    The kernels are timed in turns (bare, matched, bare, matched, ...) so that a busy machine
    slows them alike; the best time of each is the least disturbed one.
    """
    first, best = {}, {}
    for name, (fn, args) in kernels.items():
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        first[name] = time.perf_counter() - start
        best[name] = math.inf
    for _ in range(repeats):
        for name, (fn, args) in kernels.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: (first[name], best[name]) for name in kernels}


def lean_x(sol, t):
    """x(t) of a matched AnsatzSolution (values only, t >= 0) with a lean per-sample formula."""
    a, bp, c, tau = sol.a, sol.bp, sol.c, sol.halt_time
    Q = 0.25 * bp * bp - a * c  # per point
    q = jnp.sqrt(jnp.abs(Q))
    q_safe = jnp.where(q > 0.0, q, 1.0)
    K1, K2 = c + 0.5 * bp, a + 0.5 * bp
    te = jnp.minimum(t, tau)  # per sample from here on
    z = q_safe * te
    T = jnp.where(Q > 0.0, jnp.tanh(z), jnp.tan(z)) / q_safe
    T = jnp.where(Q == 0.0, te, T)
    f = (1.0 - K1 * T) / (1.0 + K2 * T)
    f = jnp.where(t >= tau, 0.0, jnp.maximum(f, 0.0))
    return jnp.where(sol.valid, sol.A * f * jnp.cos(sol.omega0 * t + sol.phi), jnp.nan)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default="64x64x16", help="d0 x d2 x phi0 (default: %(default)s)")
    parser.add_argument("--samples", type=int, default=1000, help="times per point")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    n0, n2, nph = (int(v) for v in args.grid.lower().split("x"))

    m, k, A0 = 1.0, 30.0, 0.2
    w0 = math.sqrt(k / m)
    d0r, d2r, ph = np.meshgrid(np.linspace(0.0, 0.1, n0), np.linspace(0.0, 0.75, n2),
                               np.linspace(0.0, 2 * math.pi, nph, endpoint=False),
                               indexing="ij")
    d0r, d2r, ph = (jnp.asarray(a.ravel()) for a in (d0r, d2r, ph))
    t = jnp.linspace(0.0, 10 * 2 * math.pi / w0, args.samples)
    n = d0r.size

    @jax.jit
    def bare(d0r, d2r, ph, t):
        d = d0r * w0  # an amplitude decay rate of the right size

        def one(phi, d):
            return jnp.max(jnp.abs(0.2 * jnp.cos(w0 * t + phi) / (1.0 + d * t)))

        return jnp.max(jax.vmap(one)(ph, d))

    def solve_point(d0, d2, phi):
        osc = dp.from_ratios(d0, 0.0, d2, m=m, k=k, A0=A0)
        return dp.solve(osc, A0 * jnp.cos(phi), -w0 * A0 * jnp.sin(phi))

    @jax.jit
    def matched(d0r, d2r, ph, t):
        def one(d0, d2, phi):
            sol = solve_point(d0, d2, phi)
            return jnp.max(jnp.abs(jnp.where(sol.valid, sol.x(t), 0.0)))

        return jnp.max(jax.vmap(one)(d0r, d2r, ph))

    @jax.jit
    def lean(d0r, d2r, ph, t):
        def one(d0, d2, phi):
            sol = solve_point(d0, d2, phi)
            return jnp.max(jnp.abs(jnp.where(sol.valid, lean_x(sol, t), 0.0)))

        return jnp.max(jax.vmap(one)(d0r, d2r, ph))

    @jax.jit
    def solve_only(d0r, d2r, ph):
        sols = jax.vmap(solve_point)(d0r, d2r, ph)
        return jnp.max(jnp.where(sols.valid, sols.amplitude, 0.0))

    print(f"{n} points x {args.samples} samples = {n * args.samples / 1e6:.1f} M evaluations; "
          f"{jax.devices()[0].device_kind} ({jax.device_count()} device(s)), float64")
    sub = slice(None, None, 37)  # the lean formula against the library on every 37th point
    sols = jax.jit(jax.vmap(solve_point))(d0r[sub], d2r[sub], ph[sub])
    diff = jnp.abs(jax.vmap(lambda s: s.x(t))(sols) - jax.vmap(lambda s: lean_x(s, t))(sols))
    print(f"  lean vs library x(t): max |difference| = {float(jnp.nanmax(diff)):.1e} m")
    kernels = {"bare kernel": (bare, (d0r, d2r, ph, t)),
               "matched ansatz x(t)": (matched, (d0r, d2r, ph, t)),
               "matched, lean formula": (lean, (d0r, d2r, ph, t)),
               "matched: A, phi, tau only": (solve_only, (d0r, d2r, ph))}
    results = {}
    for name, (first, best) in timings(kernels, args.repeats).items():
        results[name] = best
        per = best / (n * args.samples) * 1e9
        print(f"  {name:<26} best {best:8.3f} s  ({per:6.2f} ns/sample)   first call "
              f"{first:6.2f} s")
    for name in ("matched ansatz x(t)", "matched, lean formula"):
        print(f"  ratio {name} / bare = {results[name] / results['bare kernel']:.2f} "
              "(goal: <= 2)")


if __name__ == "__main__":
    main()
