"""Benchmark (issue 34): what a GPU user gets, measured in one run.

On the machine's GPU (JAX's default backend), float64 as dampax always runs:

1. the reference (eq. 3, DOP853, exact stick-slip, rtol 1e-10, atol 1e-12) of random
   oscillators (the problem of benchmarks/peer_race.py: Coulomb, viscous and quadratic
   damping, 5 s) with x at 1,000 samples, for 4,096 and 131,072 trajectories in one call:
   the default engine (``engine="auto"``: the fused Pallas kernel where it passed its
   self-check, issue 35 item 2) and, where that is the kernel, the XLA engine beside it;
2. error maps: the default grid (16 x 16 x 8, as ``dampax errormap``) with the chunk size
   dampax chooses and with fixed ones (128, 1,024, 4,096), and a 128 x 128 x 8 grid;
3. the matched ansatz's x(ts) over the same 131,072 x 1,000 samples against the limit of
   writing as many float64 numbers (a kernel that writes one product per sample);
4. the peer: diffrax's Dopri8 (PID controller, the same tolerances; one swing per solve with
   an event at v = 0, stick or reverse, vmapped) on the same trajectories and samples, with
   its largest difference from dampax's samples.

Every item reports its first call (tracing and compilation; also through dampax's caches,
so a second run of this script shows what a repeated command costs) and the best of
``--repeat`` further calls, each waited for (``block_until_ready``).

    pip install -U "jax[cuda12]" diffrax    # the CUDA build of jax, and the peer
    python benchmarks/gpu.py                # about 2-4 minutes, most of it compiling
    python benchmarks/gpu.py --json gpu.json

On a machine without a GPU it says so and exits with status 0. ``--cpu`` runs the same
measurements on the CPU at small sizes (``--n 256 --big 512``...): a check of this script,
not a figure for a GPU.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import dampax as dp

M, T_END, SAMPLES = 1.0, 5.0, 1000
RTOL, ATOL = 1e-10, 1e-12
G = 9.81
PARTS = ("reference", "maps", "ansatz", "peer")


def random_problem(n, seed=0):
    """m = 1; k, mu, D, b, x0, v0 uniform, as benchmarks/peer_race.py draws them."""
    rng = np.random.default_rng(seed)
    p = dict(k=rng.uniform(10.0, 50.0, n), mu=rng.uniform(0.0, 0.05, n),
             D=rng.uniform(0.0, 3.0, n), b=rng.uniform(0.0, 0.5, n),
             x0=rng.uniform(-0.3, 0.3, n), v0=rng.uniform(-1.0, 1.0, n))
    return [jnp.asarray(p[name]) for name in ("k", "mu", "b", "D", "x0", "v0")]


def timed(fn, repeat):
    """(first call [s], best of ``repeat`` further calls [s], the last result)."""
    a = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - a
    best = math.inf
    for _ in range(repeat):
        a = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - a)
    return first, best, out


def reference_program(ts, engine="auto"):
    def f(k, mu, b, D, x0, v0):
        osc = dp.Oscillator(m=M, k=k, mu=mu, b=b, D=D)
        return dp.solve(osc, x0, v0, method="reference", t_end=T_END, rtol=RTOL, atol=ATOL,
                        ts=ts, engine=engine).x(ts)

    return jax.jit(f)


def ansatz_program(ts):
    def f(k, mu, b, D, x0, v0):
        osc = dp.Oscillator(m=M, k=k[:, None], mu=mu[:, None], b=b[:, None], D=D[:, None])
        return dp.solve(osc, x0[:, None], v0[:, None]).x(ts[None, :])

    return jax.jit(f)


def write_limit_program(ts):
    # one multiply per sample, written out: what storing N x samples float64 numbers costs
    return jax.jit(lambda x0, w0: x0[:, None] * (w0[:, None] * ts[None, :]))


def diffrax_program(ts, max_swings):
    """diffrax's Dopri8 on eq. 3, swing by swing (an event at v = 0 ends a swing; the block
    sticks where |x| <= mu g / w0^2, else reverses), x at ``ts``; vmapped over trajectories.
    At most 256 steps a swing (about 10-20 are taken at rtol 1e-10): the dense output of
    every step is kept, 131,072 trajectories x 256 steps take about 5 GB."""
    import diffrax as dfx
    import optimistix as optx

    def one(k, mu, b, D, x0, v0):
        def rhs(t, y, s):
            x, v = y[0], y[1]
            return jnp.stack([v, -(k / M) * x - s * mu * G - (b / M) * v - s * (D / M) * v * v])

        term, solver = dfx.ODETerm(rhs), dfx.Dopri8()
        ctrl = dfx.PIDController(rtol=RTOL, atol=ATOL)
        event = dfx.Event(lambda t, y, args, **kw: args * y[1], direction=False,
                          root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
        xc = mu * M * G / k
        s0 = jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0))
        stuck0 = (v0 == 0.0) & (jnp.abs(x0) <= xc)

        def swing(carry, _):
            t0, x, v, s, done, out = carry
            t0s = jnp.where(done, T_END - 1e-3, t0)  # a finished motion: a short dummy solve
            sol = dfx.diffeqsolve(term, solver, t0s, T_END, None, jnp.stack([x, v]), args=s,
                                  stepsize_controller=ctrl, event=event,
                                  saveat=dfx.SaveAt(t1=True, dense=True), max_steps=256)
            t1 = sol.ts[-1]
            inside = (ts >= t0) & (ts <= t1) & ~done
            # the swing's samples from its dense output
            xs = jax.vmap(lambda t: sol.evaluate(jnp.clip(t, t0s, t1))[0])(ts)
            out = jnp.where(inside, xs, out)
            x1 = sol.ys[-1, 0]
            ended = jnp.any(jnp.asarray(sol.event_mask))  # else it ran to T_END
            stick = ~ended | (jnp.abs(x1) <= xc)
            out = jnp.where((ts > t1) & ~done & stick & ended, x1, out)
            new = (jnp.where(done, t0, t1), jnp.where(done, x, x1), jnp.where(done, v, 0.0),
                   -s, done | stick, out)
            return new, None

        out = jnp.where(stuck0, x0, jnp.full(ts.shape, jnp.nan))
        init = (jnp.zeros(()), x0, v0, s0, stuck0, out)
        (_, _, _, _, _, out), _ = jax.lax.scan(swing, init, None, length=max_swings)
        return out

    return jax.jit(jax.vmap(one))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[4096, 131072],
                   help="trajectories of the reference and the peer (default: 4096 131072)")
    p.add_argument("--big", type=int, default=128, help="the big map: BIG x BIG x 8 (128)")
    p.add_argument("--chunks", type=int, nargs="+", default=[128, 1024, 4096],
                   help="fixed chunk sizes of the default map, beside dampax's choice")
    p.add_argument("--peer-n", type=int, nargs="+", default=None,
                   help="trajectories of the diffrax peer (default: those of --n)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS,
                   help="what to measure (default: all; the peer needs the reference)")
    p.add_argument("--json", help="also write the figures to this file")
    p.add_argument("--cpu", action="store_true",
                   help="measure on the CPU (small sizes: a check of this script)")
    args = p.parse_args(argv)

    backend = jax.default_backend()
    if backend == "cpu" and not args.cpu:
        print("benchmarks/gpu.py: no GPU here (JAX's default backend is the CPU); nothing "
              "measured. Install the CUDA build of "
              "jax (pip install -U \"jax[cuda12]\") on a machine with an NVIDIA GPU, or pass "
              "--cpu to run this script's measurements on the CPU at small sizes.")
        return 0
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({backend}, {len(jax.devices())} device(s)); "
          f"jax {jax.__version__}, dampax {dp.__version__}", flush=True)
    ts = jnp.linspace(0.0, T_END, SAMPLES)
    results = {"device": dev.device_kind, "backend": backend,
                         "jax": jax.__version__, "dampax": dp.__version__}

    def report(name, first, best, n=None, extra=""):
        per = f", {best / n * 1e6:.3g} us per trajectory" if n else ""
        print(f"  {name}: first call {first:.2f} s, best {best * 1e3:.3g} ms{per}{extra}",
              flush=True)
        results[name] = dict(first_s=first, best_s=best, n=n)

    # 1. the reference: the default engine ("auto": the fused kernel where it passed its
    # self-check) and the XLA engine, on the same trajectories
    from dampax._reference._solve import resolve_engine

    chosen = resolve_engine("auto")
    print(f"  engine='auto' runs {chosen!r} here", flush=True)
    results["auto_engine"] = chosen
    ref, xla = reference_program(ts), reference_program(ts, "dampax")
    ref_x = {}
    for n in args.n if "reference" in args.parts else ():
        prob = random_problem(n)
        first, best, out = timed(lambda prob=prob: ref(*prob), args.repeat)
        ref_x[n] = np.asarray(out[:64])
        report(f"reference, {n} trajectories x {SAMPLES} samples", first, best, n)
        if chosen != "dampax":
            first_x, best_x, out_x = timed(lambda prob=prob: xla(*prob), args.repeat)
            diff = float(np.nanmax(np.abs(np.asarray(out_x[:64]) - ref_x[n])))
            report(f"reference by the XLA engine, {n} trajectories", first_x, best_x, n,
                   f" ({best_x / best:.3g}x the kernel's time; max |x - kernel's| over 64 "
                   f"trajectories: {diff:.2g} m)")

    # 2. error maps
    kw = dict(d0_ratio=np.linspace(0.0, 0.1, 16), d2_ratio=np.linspace(0.0, 0.75, 16),
              phi0=np.linspace(0.0, 7 * np.pi / 8, 8), progress=False)
    for chunk in [None] + list(args.chunks) if "maps" in args.parts else ():
        first, best, ds = timed(lambda chunk=chunk: dp.error_map(**kw, chunk_size=chunk),
                                args.repeat)
        label = f"chosen: {ds.attrs['chunk_size']}" if chunk is None else str(chunk)
        report(f"default error map (16 x 16 x 8), chunk_size {label}", first, best)
    if "maps" in args.parts and args.big:
        big = dict(kw, d0_ratio=np.linspace(0.0, 0.1, args.big),
                   d2_ratio=np.linspace(0.0, 0.75, args.big))
        first, best, ds = timed(lambda: dp.error_map(**big), max(1, args.repeat - 2))
        report(f"error map {args.big} x {args.big} x 8, chunk_size chosen: "
               f"{ds.attrs['chunk_size']}", first, best)

    # 3. the analytic x(ts) against writing as many numbers
    if "ansatz" in args.parts:
        n = max(args.n)
        prob = random_problem(n)
        first, best, _ = timed(lambda: ansatz_program(ts)(*prob), args.repeat)
        report(f"matched ansatz x(ts), {n} x {SAMPLES}", first, best, n)
        lim_first, lim_best, _ = timed(lambda: write_limit_program(ts)(prob[4], prob[0]),
                                       args.repeat)
        gbytes = n * SAMPLES * 8 / 1e9
        report(f"limit: writing {n} x {SAMPLES} float64", lim_first, lim_best, n,
               f" ({gbytes / lim_best:.3g} GB/s; the ansatz at {gbytes / best:.3g} GB/s, "
               f"{best / lim_best:.2g}x the limit)")

    # 4. the peer
    diffrax = None
    if "peer" in args.parts:
        try:
            import diffrax
        except ImportError:
            print("  diffrax not installed: no peer (pip install diffrax)")
    if diffrax is not None:
        peer = diffrax_program(ts, max_swings=16)
        for n in args.peer_n or args.n:
            prob = random_problem(n)
            first, best, out = timed(lambda prob=prob: peer(*prob), max(1, args.repeat - 2))
            diff = float(np.nanmax(np.abs(np.asarray(out[:64]) - ref_x[n]))) \
                if n in ref_x else math.nan
            dampax_best = results.get(f"reference, {n} trajectories x {SAMPLES} samples", {})
            ratio = best / dampax_best["best_s"] if dampax_best else math.nan
            report(f"peer: diffrax {diffrax.__version__} Dopri8 vmapped, {n} trajectories",
                   first, best, n, f" ({ratio:.3g}x dampax's time; max |x - dampax| over 64 "
                                   f"trajectories: {diff:.2g} m)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
