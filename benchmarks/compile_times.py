"""Benchmark (issue 24): cold compile times of a reference solve, an error-map step and a fit.

Each is measured in a fresh Python process with a fresh, empty cache directory
(``DAMPAX_CACHE_DIR``; importing dampax turns JAX's persistent compilation cache on there), so
nothing compiled before helps:

- solve: ``dp.solve(dp.Oscillator(m=1, k=30, mu=0.03, D=2.95), 0.2, 0.0, method="reference")``
  then ``sol.x(np.linspace(0, 3, 600))``;
- map: ``dp.error_map(...)`` on a 2 x 2 grid (default models, periods, samples); the step's
  compile (``dampax._studies._maps._executable``) is also timed on its own where the module has it;
- fit: ``dp.fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=("mu", "D"),
  model="reference")`` on a synthetic trace: a reference solve (k = 30, mu = 0.003,
  D = 0.295, x0 = 0.2, v0 = 0), 3 s at 500 Hz, plus 1 mm of Gaussian noise (seed 0), made
  beforehand in another process.

Each child times the first (cold) call and then the same call again (warm); cold - warm is
about the compile. The import of dampax is timed separately and not counted.

    python benchmarks/compile_times.py               # all three
    python benchmarks/compile_times.py --only fit
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

# the numbers: before (diffrax engine) and target, seconds
BEFORE = {"solve": 5.3, "map": 22.0, "fit": 75.0}
TARGET = {"solve": 3.0, "map": 8.0, "fit": 15.0}
OSC = dict(m=1.0, k=30.0, mu=0.03, D=2.95)
# the fit's trace: with OSC's damping the block halts after about one period (too few zero
# crossings for dp.fit), so a tenth of it: a free decay over the 3 s (2.6 periods)
TRACE_OSC = dict(m=1.0, k=30.0, mu=0.003, D=0.295)
X0 = 0.2


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c


def _child(which, trace_path):
    w = time.perf_counter()
    import jax
    import numpy as np

    import dampax as dp

    out = {"import": time.perf_counter() - w, "cache": str(jax.config.jax_compilation_cache_dir),
           "dampax": os.path.dirname(dp.__file__)}
    if which == "trace":
        t = np.arange(1500) / 500.0
        sol = dp.solve(dp.Oscillator(**TRACE_OSC), X0, 0.0, method="reference")
        x = np.asarray(sol.x(t)) + np.random.default_rng(0).normal(0.0, 1e-3, t.size)
        np.savez(trace_path, t=t, x=x)
    elif which == "solve":
        ts = np.linspace(0.0, 3.0, 600)

        parts = []

        def call():
            w = time.perf_counter()
            sol = dp.solve(dp.Oscillator(**OSC), X0, 0.0, method="reference")
            jax.block_until_ready(sol.halt_time)
            parts.append(time.perf_counter() - w)
            jax.block_until_ready(sol.x(ts))

        out["cold"], out["warm"] = _timed(call), _timed(call)
        out["parts"] = f"of the cold call, dp.solve {parts[0]:.1f} s, sol.x the rest"
    elif which == "map":
        from dampax._studies import _maps as _maps

        compiles = []
        if hasattr(_maps, "_executable"):  # time the step's compile inside the call
            original = _maps._executable

            def executable(*args, **kwargs):
                w = time.perf_counter()
                result = original(*args, **kwargs)
                compiles.append(time.perf_counter() - w)
                return result

            _maps._executable = executable

        def call():
            dp.error_map(d0_ratio=(0.01, 0.02), d2_ratio=(0.1, 0.2), phi0=0.0, progress=False)

        out["cold"] = _timed(call)
        out["compile"] = compiles[0] if compiles else None
        out["warm"] = _timed(call)
    elif which == "fit":
        data = np.load(trace_path)
        result = []

        def call():
            result.append(dp.fit(data["t"], data["x"], oscillator=dp.Oscillator(m=1.0, k=30.0),
                                 free=("mu", "D"), model="reference"))

        out["cold"], out["warm"] = _timed(call), _timed(call)
        r = result[0]
        true = TRACE_OSC
        out["fit"] = (f"success {r.success}, mu {float(r.params['mu']):.4g} (true {true['mu']}),"
                      f" D {float(r.params['D']):.4g} (true {true['D']})")
    print("RESULT " + json.dumps(out), flush=True)


def _run_fresh(which, trace_path):
    """Run the child for `which` in a new process with a new, empty cache directory."""
    cache = tempfile.mkdtemp(prefix=f"dampax-cold-{which}-")
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "DAMPAX_CACHE")}
    env["DAMPAX_CACHE_DIR"] = cache
    try:
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", which,
                               "--trace", trace_path], env=env, capture_output=True, text=True)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode or not lines:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise RuntimeError(f"the {which} child failed (exit code {proc.returncode})")
    return json.loads(lines[-1][len("RESULT "):])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("solve", "map", "fit"), default=None)
    parser.add_argument("--child", choices=("trace", "solve", "map", "fit"), help=argparse.SUPPRESS)
    parser.add_argument("--trace", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child, args.trace)
        return

    which = (args.only,) if args.only else ("solve", "map", "fit")
    print(f"cold compile times, each in a fresh process with an empty cache "
          f"({os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f})", flush=True)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        trace = os.path.join(tmp, "trace.npz")
        if "fit" in which:
            _run_fresh("trace", trace)
        for name in which:
            results[name] = r = _run_fresh(name, trace)
            extra = f"; step compile {r['compile']:.1f} s" if r.get("compile") else ""
            print(f"  {name}: import {r['import']:.1f} s, cold call {r['cold'][0]:.1f} s wall / "
                  f"{r['cold'][1]:.1f} s CPU, warm call {r['warm'][0]:.2f} s{extra}"
                  + "".join(f"; {r[key]}" for key in ("parts", "fit") if key in r)
                  + f" (dampax from {r['dampax']}, cache {r['cache']})", flush=True)

    print("\n| | cold call, wall / CPU | warm call | cold - warm | before | target | met |")
    print("|---|---|---|---|---|---|---|")
    for name, r in results.items():
        cold, warm = r["cold"], r["warm"][0]
        label = {"solve": "reference solve + x(600 samples)", "map": "error map, 2 x 2 grid",
                 "fit": "fit, model reference"}[name]
        if r.get("compile"):
            label += f" (step compile {r['compile']:.1f} s)"
        print(f"| {label} | {cold[0]:.1f} s / {cold[1]:.1f} s | {warm:.2f} s | "
              f"{cold[0] - warm:.1f} s | {BEFORE[name]:g} s | <= {TARGET[name]:g} s | "
              f"{'yes' if cold[0] <= TARGET[name] else 'no'} |")


if __name__ == "__main__":
    main()
