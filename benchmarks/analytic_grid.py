"""Cost of evaluating the matched ansatz x(t) on a grid, against a bare fused kernel.

All kernels are jitted, vmapped over the grid points and reduced to one scalar (max |.|), so the
timing is that of the fused evaluation, not of moving 64 x 64 x 16 x 1000 numbers around:

    bare:      0.2 cos(w0 t + phi) / (1 + d t)               (one cos, one division)
    bare poly: the same with dampax's polynomial cos (dampax._trig.sincos, which the library
               uses since XLA's float64 cos is a scalar libm call on CPU): the honest floor
    library:   dp.solve(osc, x0, v0).x(t) = A f(t) cos(w0 t + phi), with A, phi from the quartic
               (eq. 22, per point) and f(t) = (1 - K1 T)/(1 + K2 T), T = tan(q t)/q or
               tanh(q t)/q (a series near Q t^2 = 0); q = sqrt|b'^2/4 - ac|, K1 = c + b'/2,
               K2 = a + b'/2 and tau once per point, tan as a vectorized rational function
    .v(t), .energy(t): the same f(t), f'(t), cos and sin shared (energy needs both x and v);
               "bare sin + cos" is the matching floor: the bare kernel with a sin added
    previous:  the library's formula before issue 12, reconstructed here for a before/after:
               per sample sqrt|Q|, regime masks and XLA's float64 tan (a scalar libm call on
               CPU), and energy(t) from x(t) and v(t) separately (f, cos, sin twice)

Run:  python benchmarks/analytic_grid.py [--grid 64x64x16] [--samples 1000] [--repeats 7]
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
from dampax._trig import sincos


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


_SERIES = 1e-4


def _previous_tanc(Q, t):
    """T(t) as the library computed it before issue 12: per-sample square roots and masks."""
    z = Q * t * t
    small = jnp.abs(z) < _SERIES
    pos = z >= _SERIES
    neg = z <= -_SERIES
    series = t * (1.0 - z / 3.0 + 2.0 * z * z / 15.0 - 17.0 * z**3 / 315.0)
    q_pos = jnp.sqrt(jnp.where(pos, Q, 1.0))
    q_neg = jnp.sqrt(jnp.where(neg, -Q, 1.0))
    t_pos = jnp.where(pos, t, 0.0)
    t_neg = jnp.where(neg, t, 0.0)
    return jnp.where(small, series,
                     jnp.where(pos, jnp.tanh(q_pos * t_pos) / q_pos,
                               jnp.tan(q_neg * t_neg) / q_neg))


def _previous_parts(sol, t):
    a, bp, c, tau = sol.a, sol.bp, sol.c, sol.halt_time
    t_eff = jnp.clip(t, 0.0, tau)
    T = _previous_tanc(0.25 * bp * bp - a * c, t_eff)
    f = (1.0 - (c + 0.5 * bp) * T) / (1.0 + (a + 0.5 * bp) * T)
    f = jnp.where(t < 0.0, jnp.nan, jnp.where(t > tau, 0.0, jnp.maximum(f, 0.0)))
    fp = jnp.where(f > 0.0, -(a * f * f + bp * f + c), 0.0)
    th = sol.omega0 * t + sol.phi
    return f, fp, jnp.cos(th), jnp.sin(th)


def previous_x(sol, t):
    """x(t) of a matched AnsatzSolution by the library's formula before issue 12."""
    f, _, cth, _ = _previous_parts(sol, t)
    return jnp.where(sol.valid, sol.A * f * cth, jnp.nan)


def previous_v(sol, t):
    """v(t) (eq. 12) by the library's formula before issue 12."""
    f, fp, cth, sth = _previous_parts(sol, t)
    return jnp.where(sol.valid, -sol.omega0 * sol.A * f * sth + sol.A * fp * cth, jnp.nan)


def previous_energy(sol, t):
    """energy(t) as before issue 12: x(t) and v(t) evaluated separately."""
    return sol.osc.energy(previous_x(sol, t), previous_v(sol, t))


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
    def bare_poly(d0r, d2r, ph, t):
        d = d0r * w0

        def one(phi, d):
            return jnp.max(jnp.abs(0.2 * sincos(w0 * t + phi)[1] / (1.0 + d * t)))

        return jnp.max(jax.vmap(one)(ph, d))

    @jax.jit
    def bare_sincos(d0r, d2r, ph, t):
        d = d0r * w0

        def one(phi, d):
            th = w0 * t + phi
            return jnp.max(jnp.abs(0.2 * (jnp.cos(th) + jnp.sin(th)) / (1.0 + d * t)))

        return jnp.max(jax.vmap(one)(ph, d))

    def grid_kernel(evaluate):
        @jax.jit
        def kernel(d0r, d2r, ph, t):
            def one(d0, d2, phi):
                sol = solve_point(d0, d2, phi)
                return jnp.max(jnp.abs(jnp.where(sol.valid, evaluate(sol, t), 0.0)))

            return jnp.max(jax.vmap(one)(d0r, d2r, ph))

        return kernel

    @jax.jit
    def solve_only(d0r, d2r, ph):
        sols = jax.vmap(solve_point)(d0r, d2r, ph)
        return jnp.max(jnp.where(sols.valid, sols.amplitude, 0.0))

    print(f"{n} points x {args.samples} samples = {n * args.samples / 1e6:.1f} M evaluations; "
          f"{jax.devices()[0].device_kind} ({jax.device_count()} device(s)), float64")
    sub = slice(None, None, 37)  # the library against the previous formula on every 37th point
    sols = jax.jit(jax.vmap(solve_point))(d0r[sub], d2r[sub], ph[sub])
    for name, lib, prev in (("x", lambda s: s.x(t), lambda s: previous_x(s, t)),
                            ("v", lambda s: s.v(t), lambda s: previous_v(s, t)),
                            ("energy", lambda s: s.energy(t), lambda s: previous_energy(s, t))):
        new, old = jax.vmap(lib)(sols), jax.vmap(prev)(sols)
        scale = jnp.nanmax(jnp.abs(old))
        print(f"  library vs previous {name}(t): max |difference| = "
              f"{float(jnp.nanmax(jnp.abs(new - old)) / scale):.1e} of max |{name}|, "
              f"{float(jnp.mean(new == old)):.0%} bitwise equal")
    kernels = {"bare kernel": (bare, (d0r, d2r, ph, t)),
               "bare poly kernel": (bare_poly, (d0r, d2r, ph, t)),
               "library x(t)": (grid_kernel(lambda s, t: s.x(t)), (d0r, d2r, ph, t)),
               "previous x(t)": (grid_kernel(previous_x), (d0r, d2r, ph, t)),
               "bare sin + cos": (bare_sincos, (d0r, d2r, ph, t)),
               "library v(t)": (grid_kernel(lambda s, t: s.v(t)), (d0r, d2r, ph, t)),
               "library energy(t)": (grid_kernel(lambda s, t: s.energy(t)), (d0r, d2r, ph, t)),
               "previous energy(t)": (grid_kernel(previous_energy), (d0r, d2r, ph, t)),
               "A, phi, tau only": (solve_only, (d0r, d2r, ph))}
    results = {}
    for name, (first, best) in timings(kernels, args.repeats).items():
        results[name] = best
        per = best / (n * args.samples) * 1e9
        print(f"  {name:<19} best {best:8.3f} s  ({per:6.2f} ns/sample)   first call "
              f"{first:6.2f} s")
    bare_time = results["bare kernel"]
    for name in ("library x(t)", "previous x(t)", "bare sin + cos", "library v(t)",
                 "library energy(t)", "previous energy(t)"):
        print(f"  ratio {name + ' / bare':<27} = {results[name] / bare_time:.2f}"
              + ("   (goal: <= 1.3)" if name.startswith("library") else ""))
    poly_time = results["bare poly kernel"]
    for name in ("library x(t)", "library v(t)", "library energy(t)"):
        print(f"  ratio {name + ' / bare poly':<27} = {results[name] / poly_time:.2f}")


if __name__ == "__main__":
    main()
