"""Benchmark (issue 35 item 2): where the fused kernel's time goes, variant by variant, in one run.

The kernel (`dampax._reference._kernel.run_blocks`) on benchmarks/gpu.py's random oscillators
(Coulomb, viscous and quadratic damping, 5 s, rtol 1e-10, atol 1e-12, 24 half-swings, 288 rows;
x and v at 1,000 sorted samples written inside the loop), float64, best of ``--repeat`` calls:

- ``base``: as the twenty-fourth session's kernel ran (128 lanes, 16 samples a pass, the row
  table written); ``default``: as ``dp.solve(..., engine="pallas")`` runs it now (32 lanes, 2
  samples a pass: `_kernel.BLOCK`, `_kernel.SAMPLES_PER_PASS`);
- ``norows``: the row table left out (``keep_rows=False``: only the samples are read, as in an
  error map) -- the pre-filled table alone is n x 288 x 10 float64 (3 GB at 131,072);
- ``norows-b32`` / ``norows-b64``: programs of 32 or 64 lanes (1 or 2 warps) instead of 128;
- ``...-sppN``: N sample times per pass of the sampling loop instead of 16;
- ``nosamples``: neither rows nor samples (the integration and the turning points alone);
- ``xla``: the XLA engine (``dp.solve(..., engine="dampax")``), the peer in the same run.

Each variant reports its first call (Triton compiling the whole loop), its best time, ns per
trajectory, ns per lane-step (the time over the steps taken, ``n_rows``), and the largest
difference of its samples from ``base``'s (benchmarks/gpu_kernel_session.sh adds ncu's
counters: registers, spills). The figures: benchmarks/README.md, issue 35's twenty-sixth session.

    python benchmarks/gpu_kernel.py --n 4096 131072
    python benchmarks/gpu_kernel.py --cpu --n 16 --variants base norows   # a check, interpreted
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

import dampax as dp
from dampax._reference import _kernel

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gpu import ATOL, RTOL, SAMPLES, T_END, M, random_problem, timed  # noqa: E402

MAX_SWINGS, ROWS = 24, 288
VARIANTS = {
    "base": dict(block=128, spp=16),
    "default": dict(),
    "norows": dict(keep_rows=False, block=128, spp=16),
    "norows-b32": dict(keep_rows=False, block=32, spp=16),
    "norows-b64": dict(keep_rows=False, block=64, spp=16),
    "norows-spp4": dict(keep_rows=False, block=128, spp=4),
    "nosamples": dict(keep_rows=False, ts=False, block=128),
    "spp4": dict(block=128, spp=4),
    "spp2": dict(block=128, spp=2),
    "spp1": dict(block=128, spp=1),
    "norows-spp2": dict(keep_rows=False, block=128, spp=2),
    "norows-spp1": dict(keep_rows=False, block=128, spp=1),
    "norows-b32-spp2": dict(keep_rows=False, block=32, spp=2),
    "norows-b64-spp2": dict(keep_rows=False, block=64, spp=2),
    "b32-spp4": dict(block=32, spp=4),
    "b32-spp2": dict(block=32, spp=2),
    "norows-b32-spp4": dict(keep_rows=False, block=32, spp=4),
    "norows-b32-spp8": dict(keep_rows=False, block=32, spp=8),
    "nosamples-b32": dict(keep_rows=False, ts=False, block=32),
    "xla": dict(engine="dampax"),
}


def program(name, interpret, keep_rows=True, block=None, spp=None, ts=True, engine=None):
    """A jitted kernel run of one variant (named ``kernel_<name>`` for XLA's dumps)."""
    if engine is not None:
        def solve(k, mu, b, D, x0, v0, times):
            sol = dp.solve(dp.Oscillator(m=M, k=k, mu=mu, b=b, D=D), x0, v0,
                           method="reference", t_end=T_END, rtol=RTOL, atol=ATOL, ts=times,
                           engine=engine, max_swings=MAX_SWINGS)
            return sol.x(times), sol.n_rows

        return jax.jit(solve)

    def run(k, mu, b, D, x0, v0, times):
        osc = dp.Oscillator(m=M, k=k, mu=mu, b=b, D=D)
        inputs, _, _ = _kernel.prepare(osc, x0, v0, jnp.full_like(x0, T_END))
        out = _kernel.run_blocks(inputs, times if ts else None, rtol=RTOL, atol=ATOL,
                                 max_swings=MAX_SWINGS, rows=ROWS, interpret=interpret,
                                 block=block, keep_rows=keep_rows,
                                 samples_per_pass=spp or _kernel.SAMPLES_PER_PASS)
        return out.get("xs", out["x"]), out["n_rows"]

    run.__name__ = run.__qualname__ = "kernel_" + name.replace("-", "_")
    return jax.jit(run)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[4096, 131072])
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS),
                   default=["base", "default", "norows-b32-spp2", "nosamples-b32", "xla"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--cpu", action="store_true", help="run interpreted on the CPU (a check)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    native = _kernel.available()
    if not native and not args.cpu:
        print("benchmarks/gpu_kernel.py: no CUDA GPU here; pass --cpu to check the script "
              "interpreted")
        return 0
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind}; jax {jax.__version__}", flush=True)
    ts = jnp.linspace(0.0, T_END, SAMPLES)
    results = {"device": dev.device_kind, "jax": jax.__version__}
    for n in args.n:
        prob = random_problem(n)
        ref = None
        for name in args.variants:
            fn = program(name, not native, **VARIANTS[name])
            try:
                first, best, (xs, steps) = timed(lambda fn=fn, prob=prob: fn(*prob, ts),
                                                 args.repeat)
            except Exception as err:  # noqa: BLE001 - a variant that does not lower: say so
                print(f"  n={n} {name}: failed ({type(err).__name__}: {str(err)[:300]})",
                      flush=True)
                results[f"{n}/{name}"] = dict(error=str(err)[:2000])
                continue
            steps = np.asarray(steps)
            xs = np.asarray(xs)
            if name == "base":
                ref = xs
            diff = (float(np.nanmax(np.abs(xs - ref))) if ref is not None
                    and xs.shape == ref.shape else None)
            per_step = best / float(steps.sum()) * 1e9 * 132  # per lane-step per SM (H100/200)
            line = (f"  n={n} {name}: first {first:.2f} s, best {best * 1e3:.3g} ms, "
                    f"{best / n * 1e9:.4g} ns/trajectory, steps mean {steps.mean():.1f} max "
                    f"{steps.max()}, {best / steps.max() * 1e6:.3g} us per step of the "
                    f"longest, {per_step:.3g} ns per lane-step per SM"
                    + (f", max |x - base| {diff:.2g}" if diff is not None else ""))
            print(line, flush=True)
            results[f"{n}/{name}"] = dict(first_s=first, best_s=best, steps_mean=steps.mean(),
                                          steps_max=int(steps.max()), diff=diff)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
