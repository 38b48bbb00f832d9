"""Benchmark: the full fit of spring-mass run 1 (about 12,000 samples), dampax vs scipy.

    python benchmarks/fit.py [--data DIR] [--repeat N] [--quick]

Fits b and D (plus w0, the offset, x0 and v0) to ``spring_mass_airdrag/run1.csv`` with

- dampax.fit(model="ansatz"): the closed-form ansatz, optimistix Levenberg-Marquardt;
- dampax.fit(model="reference"): eq. 3 integrated by diffrax (started from the ansatz fit);
- scipy.optimize.least_squares driving scipy.integrate.solve_ivp (DOP853) on eq. 3 with the
  same parameters, from dampax's automatic initial guess, finite-difference Jacobian:
  "tuned" (rtol 1e-10, atol 1e-12, diff_step 1e-5: converges) and "default settings"
  (rtol 1e-8, atol 1e-10, default difference step: the Jacobian drowns in the solver's
  error and it stops early);
- lmfit leastsq (if importable) on the tuned solve_ivp residual (epsfcn 1e-10).

Reports the wall time after compilation (the best of --repeat calls for dampax; one call for
scipy and lmfit, which do not compile), the optima and their cost 0.5 sum r^2 evaluated with
one common residual (dampax's reference model at rtol 1e-10). Not a test. The data stay in
../shared/data beside the checkout (never copied into the repository).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import dampax as dp
from dampax._fit import fit, residual_function
from dampax._trace import load_trace

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
M, K = 0.2016, 14.91945  # from the file name
NAMES = ("b", "D", "w0", "offset", "x0", "v0")


def ode_residuals(t, x, m, rtol, atol):
    """Residual function of eq. 3 (mu = 0) by solve_ivp: p = (b, D, w0, offset, x0, v0)."""
    tau = t - t[0]

    def rhs(_, y, b, D, w0):
        pos, vel = y
        return [vel, -w0 * w0 * pos - (b / m) * vel - (D / m) * vel * abs(vel)]

    def fun(p):
        b, D, w0, off, x0, v0 = p
        sol = solve_ivp(rhs, (0.0, tau[-1]), [x0, v0], method="DOP853", t_eval=tau,
                        args=(b, D, w0), rtol=rtol, atol=atol)
        return sol.y[0] + off - x

    return fun


def timed(fn, repeat=1):
    best, out = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true",
                        help="only dampax and the tuned scipy fit")
    args = parser.parse_args()
    path = args.data / "spring_mass_airdrag" / "run1.csv"
    if not path.exists():
        raise SystemExit(f"data not found: {path} (the shared data folder beside the checkout)")
    trace = load_trace(path)
    osc = dp.Oscillator(m=M, k=K)
    kw = dict(oscillator=osc, free=("b", "D"), fit_omega0=True)
    rows = []

    for model in ("ansatz", "reference"):
        start = time.perf_counter()
        res = fit(trace, model=model, **kw)  # compiles
        first = time.perf_counter() - start
        wall, res = timed(lambda: fit(trace, model=model, **kw), args.repeat)  # noqa: B023
        rows.append((f"dampax.fit(model={model!r})", wall, first, res.n_iterations,
                     [res.params[n] for n in NAMES], res.success))
        if model == "ansatz":
            ansatz = res
    t, x = ansatz.t, ansatz.x
    p0 = np.array([ansatz.init[n] for n in NAMES])

    fun = ode_residuals(t, x, M, 1e-10, 1e-12)
    wall, sol = timed(lambda: least_squares(fun, p0, x_scale="jac", xtol=1e-10, ftol=1e-10,
                                            diff_step=1e-5))
    rows.append(("scipy least_squares + solve_ivp, tuned", wall, wall, f"{sol.nfev} fev",
                 list(sol.x), sol.success))
    if not args.quick:
        fun = ode_residuals(t, x, M, 1e-8, 1e-10)
        wall, sol = timed(lambda: least_squares(fun, p0, x_scale="jac", xtol=1e-10,
                                                ftol=1e-10))
        rows.append(("scipy ..., default settings", wall, wall, f"{sol.nfev} fev",
                     list(sol.x), sol.success))
        try:
            import lmfit
        except ImportError:
            print("lmfit is not installed: skipped")
        else:
            params = lmfit.Parameters()
            for name, value in zip(NAMES, p0, strict=True):
                params.add(name, value=value)
            fun2 = ode_residuals(t, x, M, 1e-10, 1e-12)

            def lm_res(p):
                return fun2([p[n].value for n in NAMES])

            wall, out = timed(lambda: lmfit.minimize(lm_res, params, method="leastsq",
                                                     epsfcn=1e-10, xtol=1e-10, ftol=1e-10))
            rows.append((f"lmfit {lmfit.__version__} leastsq + solve_ivp", wall, wall,
                         f"{out.nfev} fev", [out.params[n].value for n in NAMES],
                         out.success))

    cost_fn, _, names = residual_function(t, x, free=("b", "D"), oscillator=osc,
                                          fit_omega0=True, model="reference")
    assert tuple(names) == NAMES
    ref = rows[2]
    print(f"spring run 1: {len(t)} samples fitted from t0 = {ansatz.t_start:.3f} s "
          f"(m = {M} kg; b, D, w0, offset, x0, v0 free); {trace.source}")
    print()
    print(f"{'method':<40} {'wall [s]':>9} {'1st call':>9} {'vs scipy':>9}  {'b [kg/s]':>10} "
          f"{'D [kg/m]':>10} {'w0 [rad/s]':>10} {'cost':>10}  {'steps':>8}  b, D, w0 to 3 s.f.")
    for name, wall, first, steps, p, ok in rows:
        same = all(f"{a:.3g}" == f"{b:.3g}" for a, b in zip(p[:3], ref[4][:3], strict=True))
        cost = 0.5 * float(np.sum(cost_fn(np.asarray(p)) ** 2))
        print(f"{name:<40} {wall:>9.3f} {first:>9.2f} {ref[1] / wall:>8.1f}x  {p[0]:>10.5g} "
              f"{p[1]:>10.5g} {p[2]:>10.6g} {cost:>10.7g}  {str(steps):>8}  "
              f"{'same as tuned scipy' if same else 'differ'}"
              f"{'' if ok else ' (not converged)'}")
    print()
    print(f"wall: best of {args.repeat} calls after the first (which compiles) for dampax; one "
          "call for scipy / lmfit; cost = 0.5 sum r^2 [m^2] with dampax's reference residual.")


if __name__ == "__main__":
    main()
