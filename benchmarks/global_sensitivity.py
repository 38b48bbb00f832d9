"""Benchmark: Sobol' indices (S1, ST, bootstrap, DGSM) of the halt time, three parameters.

    python benchmarks/global_sensitivity.py [--n 4096] [--repeat 3] [--no-reference]

Problem: m = 1 kg, k = 30 N/m, released from rest; mu ~ U(0.01, 0.05), D ~ U(0.5, 3) kg/m,
x0 ~ U(0.15, 0.25) m; quantity: halt time. ``dp.global_sensitivity`` with n base samples draws
n (k + 2) = 5 n rows and n gradients (DGSM), and 100 bootstrap resamples.

Reports, for the matched ansatz and for the diffrax reference: the first call (compilation
included) and the best of --repeat calls after it, wall and CPU time (``time.process_time``:
the development machine is shared); the split of a call into the model evaluations (one
vmapped batch of 4096 rows at a time), the DGSM gradients and the estimation; and as peers
SALib's ``sobol.analyze`` on the same outputs (the estimation alone; SALib does not evaluate
the model) and the cost per model evaluation. Not a test.
"""

from __future__ import annotations

import argparse
import math
import time

import jax.numpy as jnp
import numpy as np

import dampax as dp
from dampax._studies import _global as _global

BOUNDS = {"mu": (0.01, 0.05), "D": (0.5, 3.0), "x0": (0.15, 0.25)}
OSC = dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=1.0)


def timed(fn, repeat=1):
    """(result, best wall [s], CPU of that call [s]) of ``repeat`` calls of fn()."""
    best, cpu, out = math.inf, math.nan, None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        if w < best:
            best, cpu = w, c
    return out, best, cpu


def study(method: str, n: int, repeat: int, **options) -> dict:
    def call(dgsm=True):
        return dp.global_sensitivity(bounds=BOUNDS, oscillator=OSC, x0=0.2, v0=0.0,
                                     method=method, n=n, seed=0, dgsm=dgsm, **options)

    ds, first, first_cpu = timed(call)
    ds, best, cpu = timed(call, repeat)
    _, best_nodgsm, cpu_nodgsm = timed(lambda: call(False), repeat)
    # model evaluations alone: the same jitted batches global_sensitivity runs
    model = _global._Model(osc=OSC, x0=jnp.asarray(0.2), v0=jnp.asarray(0.0),
                           t=jnp.asarray(0.0), names=tuple(BOUNDS), method=method,
                           options=tuple(sorted(dict(options, **(
                               {"adjoint": "forward"} if method == "reference" else {})
                           ).items())), quantity="halt_time", samples=200)
    X = ds.X.values
    _, evals, evals_cpu = timed(lambda: _global._batched(_global._apply_batch, model, X, 4096),
                                repeat)
    return dict(ds=ds, first=first, first_cpu=first_cpu, best=best, cpu=cpu,
                best_nodgsm=best_nodgsm, cpu_nodgsm=cpu_nodgsm, evals=evals,
                evals_cpu=evals_cpu, rows=X.shape[0])


def salib_time(ds, repeat: int) -> tuple[float, float]:
    from SALib.analyze import sobol

    problem = dict(num_vars=len(BOUNDS), names=list(BOUNDS),
                   bounds=[list(b) for b in BOUNDS.values()])
    si, best, cpu = timed(lambda: sobol.analyze(problem, ds.Y.values, calc_second_order=False,
                                                seed=0), repeat)
    assert np.allclose(si["S1"], ds.S1.values, atol=1e-10)
    assert np.allclose(si["ST"], ds.ST.values, atol=1e-10)
    return best, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=4096, help="base samples (default 4096)")
    parser.add_argument("--repeat", type=int, default=3, help="timed calls (default 3)")
    parser.add_argument("--no-reference", action="store_true", help="the ansatz only")
    args = parser.parse_args()
    methods = ["ansatz"] + ([] if args.no_reference else ["reference"])
    print(f"n = {args.n}, 3 parameters {list(BOUNDS)}, quantity halt time; "
          f"times: best of {args.repeat}, wall / CPU")
    for method in methods:
        r = study(method, args.n, args.repeat)
        s_wall, s_cpu = salib_time(r["ds"], args.repeat)
        print(f"\n{method}: {r['rows']} model evaluations + {args.n} gradients")
        print(f"  first call (compile + run):   {r['first']:8.2f} s / {r['first_cpu']:.2f} s")
        print(f"  after compilation, full:      {r['best']:8.3f} s / {r['cpu']:.3f} s"
              f"   (goal for the ansatz: < 10 s)")
        print(f"  after compilation, no DGSM:   {r['best_nodgsm']:8.3f} s / "
              f"{r['cpu_nodgsm']:.3f} s")
        print(f"  model evaluations alone:      {r['evals']:8.3f} s / {r['evals_cpu']:.3f} s"
              f"   = {1e6 * r['evals'] / r['rows']:.2f} us per evaluation")
        print(f"  SALib sobol.analyze, same Y:  {s_wall:8.3f} s / {s_cpu:.3f} s"
              f"   (dampax full / SALib analyze alone: {r['best'] / s_wall:.2f})")
        ds = r["ds"]
        for name in BOUNDS:
            row = ds.sel(parameter=name)
            print(f"    {name:3s} S1 = {float(row.S1):.3f} +- {float(row.S1_conf):.3f}, "
                  f"ST = {float(row.ST):.3f} +- {float(row.ST_conf):.3f}, "
                  f"DGSM = {float(row.DGSM):.3g}")


if __name__ == "__main__":
    main()
