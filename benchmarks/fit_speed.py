"""The default fit's speed (issue 36, item 2): dp.fit as a user calls it against scipy.

    python benchmarks/fit_speed.py [--n 20] [--quick] [--seed 0] [--no-cold] [--profile I]

One run measures:

1. A family of traces in the papers' regime (issue 36): Coulomb friction plus quadratic drag,
   d0/(w0 A0) log-uniform in [0.002, 0.06], d2 A0/w0 log-uniform in [0.01, 0.4] (eq. 21:
   d0 = 2 mu g/(pi w0), d2 = 4 D w0/(3 pi m), b = 0), w0 = 2 pi U(0.5, 2) rad/s,
   m U(0.1, 2) kg, A0 U(0.02, 0.3) m, any phase (x0 = A0 cos phi0, v0 = -w0 A0 sin phi0), an
   offset U(-0.2, 0.2) A0, 2-15 periods, 3000 samples, noise 0.5-3 % of A0 (log-uniform),
   white, or AR(1) with coefficient U(0.3, 0.9) for a third of the traces. Drawn from the
   INDEPENDENT scipy integrator with exact stick-slip of benchmarks/fit_calibration.py
   (DOP853, rtol 1e-11, atol 1e-13 A0, terminal events at v = 0), not from dampax.
2. dampax: ``dp.fit(t, x, oscillator=dp.Oscillator(m=..., k=...), free=("mu", "D"),
   model="auto")`` (the exact answer, issue 36; measured when it was the default: the
   README's first call then). Per trace: the first call (the very first
   of the process includes compiling), then warm: the best of 2 further calls. Which model
   answered (``result.model``), success, and whether the 90 % ``conf_interval`` covers the
   truth of mu and D. Then the first fit of traces of two other lengths (2,500 and 3,700
   samples) in the same process, and the cold first fit in a fresh process on an empty cache
   (``DAMPAX_CACHE_DIR`` set to a new temporary folder; ``src/dampax/_cachefiles.py``), then
   a second fresh process on that (now filled) cache.
3. The peer: ``scipy.optimize.least_squares`` (method "trf", x_scale="jac", finite-difference
   Jacobian with diff_step 1e-6, bounds mu, D >= 0) on a residual from ``solve_ivp`` (DOP853,
   rtol 1e-10, atol 1e-12 of the start's amplitude) with exact stick-slip events: the tests'
   ``helpers.scipy_stick_slip`` (swing by swing, terminal event at v = 0; at a velocity zero
   the block sticks for good where |k x| <= mu m g, else it goes on with the new sign).
   Parameters mu, D, offset, x0, v0 (x0, v0 at dampax's fit start ``result.t_start``), fitted
   on the same window as dampax (``result.t``, ``result.x``), from the same start dampax's
   pipeline starts from: the turning-point guess ``result.init``. One call (nothing to
   compile). Its rms against dampax's: equal when the ratio is within 1 +- 1e-3.

The main process keeps its compiled programs in a temporary cache folder of its own (so its
first call compiles, as a new user's would), unless ``--user-cache``. Wall-clock times on a
machine shared with other jobs: the load average is printed at the start and the end.
``--profile I`` runs cProfile on one more warm fit of trace I and prints where the time went.
Not a test; the numbers go to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from fit_calibration import ar1_noise, positions, stick_slip  # noqa: E402 (independent integrator)
from helpers import evaluate, scipy_stick_slip  # noqa: E402 (the tests' scipy integrator)

G = 9.81
D0_RATIO = (0.002, 0.06)  # d0 / (w0 A0), log-uniform
D2_RATIO = (0.01, 0.4)  # d2 A0 / w0, log-uniform
FREQ = (0.5, 2.0)  # w0 / (2 pi), Hz
MASS = (0.1, 2.0)  # kg
AMPLITUDE = (0.02, 0.3)  # m
PERIODS = (2.0, 15.0)
NOISE = (0.005, 0.03)  # of A0, log-uniform
AR1_SHARE, AR1_PHI = 1.0 / 3.0, (0.3, 0.9)
SAMPLES = 3000
OTHER_LENGTHS = (2500, 3700)
FREE = ("mu", "D")
EQUAL_RMS = 1e-3


# ----------------------------------------------------------------------------------------------
# the family


def _logu(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw(rng, n=SAMPLES) -> dict:
    """One trace of the papers' regime (issue 36): constants, start, window, noise."""
    w0 = 2.0 * math.pi * float(rng.uniform(*FREQ))
    m = float(rng.uniform(*MASS))
    A0 = float(rng.uniform(*AMPLITUDE))
    r0, r2 = _logu(rng, *D0_RATIO), _logu(rng, *D2_RATIO)
    # eq. 21 inverted by hand: d0 = 2 mu g / (pi w0), d2 = 4 D w0 / (3 pi m)
    mu = math.pi * w0 * (r0 * w0 * A0) / (2.0 * G)
    D = 3.0 * math.pi * m * (r2 * w0 / A0) / (4.0 * w0)
    phi0 = float(rng.uniform(0.0, 2.0 * math.pi))
    periods = float(rng.uniform(*PERIODS))
    ar1 = bool(rng.random() < AR1_SHARE)
    return dict(w0=w0, m=m, k=m * w0 * w0, A0=A0, r0=r0, r2=r2, mu=mu, D=D, phi0=phi0,
                x0=A0 * math.cos(phi0), v0=-w0 * A0 * math.sin(phi0),
                offset=float(rng.uniform(-0.2, 0.2)) * A0, periods=periods,
                span=periods * 2.0 * math.pi / w0, n=int(n),
                noise=_logu(rng, *NOISE) * A0,
                phi=float(rng.uniform(*AR1_PHI)) if ar1 else 0.0,
                noise_seed=int(rng.integers(2 ** 31)))


def simulate(spec: dict):
    """(t, x): the independent integrator (exact stick-slip), the offset and the noise."""
    t = np.linspace(0.0, spec["span"], spec["n"])
    seg, rest = stick_slip(spec["m"], spec["k"], spec["mu"], 0.0, spec["D"], spec["x0"],
                           spec["v0"], spec["span"] * (1 + 1e-9) + 1e-12)
    clean = positions(seg, rest, t) + spec["offset"]
    noise = ar1_noise(np.random.default_rng(spec["noise_seed"]), t.size, spec["noise"],
                      spec["phi"])
    spec["halt"] = None if rest is None else float(rest[0])
    return t, clean + noise


# ----------------------------------------------------------------------------------------------
# dampax, as the README's first call


def dampax_fit(spec, t, x):
    """The README's first call; returns (result, wall seconds, CPU seconds, compiled): the
    seconds XLA spent compiling in the call (persistent-cache hits not counted)."""
    import dampax as dp
    from dampax._cli._common import compile_clock

    w0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(), compile_clock() as clock:
        warnings.simplefilter("ignore")
        res = dp.fit(t, x, oscillator=dp.Oscillator(m=spec["m"], k=spec["k"]), free=FREE,
                     model="auto")
    return res, time.perf_counter() - w0, time.process_time() - c0, clock.seconds


def rms(r) -> float:
    r = np.asarray(r, dtype=float)
    return float(math.sqrt(np.mean(r * r)))


def covers(res, spec, level=0.90) -> dict:
    ci = res.conf_interval(level)
    return {name: bool(ci[name][0] <= spec[name] <= ci[name][1]) for name in FREE}


def swing_budget(spec, res) -> int:
    """The reference model's swing budget for this fit (a static size of its compiled
    programs: a fit with another budget compiles them again): dampax's own rule."""
    from dampax._fit._core import swing_budget as budget

    return budget(float(res.t[-1] - res.t[0]), math.sqrt(spec["k"] / spec["m"]), "starts")


def z_scores(res, spec, level=0.90) -> dict:
    """(estimate - truth) in the sd that the 90 % interval implies (its width / 3.29)."""
    ci = res.conf_interval(level)
    return {name: (res.params[name] - spec[name]) / ((ci[name][1] - ci[name][0]) / 3.29)
            for name in FREE}


# ----------------------------------------------------------------------------------------------
# the peer: least_squares on solve_ivp with stick-slip events


def scipy_fit(spec, res):
    """least_squares (trf, x_scale="jac", 2-point differences) on a solve_ivp residual over
    dampax's window, from dampax's start ``res.init``. Returns a dict."""
    from scipy.optimize import least_squares

    m, k = spec["m"], spec["k"]
    t, x = np.asarray(res.t, dtype=float), np.asarray(res.x, dtype=float)
    tau = t - res.t_start
    t_end = tau[-1] * (1 + 1e-12) + 1e-12
    p0 = np.array([res.init[name] for name in ("mu", "D", "offset", "x0", "v0")], dtype=float)
    p0[:2] = np.maximum(p0[:2], 0.0)
    w0 = math.sqrt(k / m)
    scale = max(math.hypot(p0[3], p0[4] / w0), 1e-300)  # the start's amplitude
    atol = 1e-12 * scale
    calls = [0]

    def residual(p):
        mu, D, offset, x0, v0 = p
        calls[0] += 1
        seg, _, rest = scipy_stick_slip(m, k, mu, 0.0, D, x0, v0, t_end, rtol=1e-10,
                                        atol=atol)
        r = evaluate(seg, rest, tau)[0] + offset - x
        return np.where(np.isfinite(r), r, 1e3 * scale)

    lower = np.array([0.0, 0.0, -np.inf, -np.inf, -np.inf])
    w_start, c_start = time.perf_counter(), time.process_time()
    out = least_squares(residual, p0, method="trf", x_scale="jac", diff_step=1e-6,
                        bounds=(lower, np.full(5, np.inf)))
    wall, cpu = time.perf_counter() - w_start, time.process_time() - c_start
    return dict(wall=wall, cpu=cpu, rms=rms(out.fun), mu=float(out.x[0]), D=float(out.x[1]),
                nfev=calls[0], njev=int(out.njev or 0), status=int(out.status),
                success=bool(out.success))


# ----------------------------------------------------------------------------------------------
# a fresh process on an empty cache


def child(path: str) -> None:
    """In a fresh process: import dampax, fit the trace in ``path`` (npz) once, print JSON."""
    w0 = time.perf_counter()
    import dampax  # noqa: F401 (the import's own time)

    imported = time.perf_counter() - w0
    data = np.load(path)
    spec = {name: float(data[name]) for name in ("m", "k")}
    res, wall, cpu, compiled = dampax_fit(spec, data["t"], data["x"])
    print(json.dumps(dict(import_s=imported, fit_s=wall, fit_cpu_s=cpu, compile_s=compiled,
                          model=res.model,
                          success=bool(res.success), cache=os.environ.get("DAMPAX_CACHE_DIR"))))


def fresh_process(spec, t, x, cache_dir) -> dict:
    """Run :func:`child` in a new Python with ``DAMPAX_CACHE_DIR=cache_dir``."""
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "trace.npz")
        np.savez(path, t=t, x=x, m=spec["m"], k=spec["k"])
        env = dict(os.environ, DAMPAX_CACHE_DIR=str(cache_dir))
        env.pop("DAMPAX_CACHE", None)
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        start = time.perf_counter()
        out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", path],
                             env=env, capture_output=True, text=True, check=False)
        total = time.perf_counter() - start
    if out.returncode != 0:
        return dict(error=out.stderr.strip().splitlines()[-1:] or ["?"], process_s=total)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["process_s"] = total
    return result


# ----------------------------------------------------------------------------------------------


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} ({os.cpu_count()} CPUs)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=20, help="traces of 3000 samples (default 20)")
    ap.add_argument("--quick", action="store_true", help="5 traces")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-cold", action="store_true", help="skip the fresh processes")
    ap.add_argument("--user-cache", action="store_true",
                    help="the main process uses the user's dampax cache (default: a new one)")
    ap.add_argument("--profile", type=int, default=None, metavar="I",
                    help="cProfile one more warm fit of trace I")
    ap.add_argument("--json", default=None, help="write the rows as JSON to this file")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child)
        return
    n = 5 if args.quick else args.n

    tmp = tempfile.TemporaryDirectory(prefix="dampax-fit-speed-")
    if not args.user_cache:  # before dampax is imported: this process compiles its programs
        os.environ["DAMPAX_CACHE_DIR"] = str(Path(tmp.name) / "main")
        os.environ.pop("DAMPAX_CACHE", None)
        os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)
    print(f"start: {load()}", flush=True)

    rng = np.random.default_rng(args.seed)
    specs = [draw(rng) for _ in range(n)]
    others = [draw(rng, n=length) for length in OTHER_LENGTHS]
    traces = [simulate(s) for s in specs]
    other_traces = [simulate(s) for s in others]

    w_import = time.perf_counter()
    import dampax as dp

    print(f"dampax {dp.__version__} from {Path(dp.__file__).parent}; import "
          f"{time.perf_counter() - w_import:.1f} s; cache "
          f"{os.environ.get('DAMPAX_CACHE_DIR', 'the user default')}", flush=True)

    head = (f"{'#':>2} {'d0/w0A':>7} {'d2A/w0':>7} {'per':>5} {'noise':>6} {'AR1':>4} "
            f"{'halt':>5} {'n fit':>5} {'budg':>4} {'model':>9} {'ok':>2} {'first':>6} "
            f"{'(comp)':>6} "
            f"{'warm':>6} {'cpu':>6} {'scipy':>6} {'nfev':>4} {'x':>5} {'rms s/d':>8} "
            f"{'z mu':>6} {'z D':>6} {'in 90%':>6}")
    print(head)
    rows = []
    for i, (spec, (t, x)) in enumerate(zip(specs, traces, strict=True)):
        res, first, _, first_compile = dampax_fit(spec, t, x)
        warm = [dampax_fit(spec, t, x) for _ in range(2)]
        best = min(warm, key=lambda w: w[1])
        res = best[0]
        cov, z = covers(res, spec), z_scores(res, spec)
        peer = scipy_fit(spec, res)
        d_rms = rms(res.residuals)
        row = dict(i=i, r0=spec["r0"], r2=spec["r2"], periods=spec["periods"],
                   noise=spec["noise"] / spec["A0"], ar1=spec["phi"],
                   halt=spec["halt"] is not None and spec["halt"] < spec["span"],
                   model=res.model, success=bool(res.success), reason=res.reason,
                   first_s=first, first_compile_s=first_compile, warm_s=best[1],
                   warm_cpu_s=best[2], warm_compile_s=max(w[3] for w in warm),
                   warm_all_s=[w[1] for w in warm], scipy=peer, dampax_rms=d_rms,
                   rms_ratio=peer["rms"] / d_rms, cover=cov, z=z,
                   mu_err=res.params["mu"] / spec["mu"] - 1, D_err=res.params["D"] / spec["D"] - 1,
                   window=(float(res.t[0]), float(res.t[-1])), ndata=int(res.ndata),
                   budget=swing_budget(spec, res))
        rows.append(row)
        print(f"{i:>2} {spec['r0']:7.4f} {spec['r2']:7.3f} {spec['periods']:5.1f} "
              f"{100 * row['noise']:5.2f}% {spec['phi']:4.2f} "
              f"{'yes' if row['halt'] else 'no':>5} {res.ndata:5d} "
              f"{row['budget']:4d} {res.model:>9} {'y' if res.success else 'N':>2} {first:6.2f} "
              f"{first_compile:6.2f} {best[1]:6.2f} {best[2]:6.2f} {peer['wall']:6.2f} "
              f"{peer['nfev']:4d} {peer['wall'] / best[1]:5.2f} {row['rms_ratio']:8.5f} "
              f"{z['mu']:6.2f} {z['D']:6.2f} "
              f"{'/'.join('y' if cov[k] else 'N' for k in FREE):>6}", flush=True)
        if not res.success:
            print(f"   reason: {res.reason}", flush=True)

    other_rows = []
    for spec, (t, x) in zip(others, other_traces, strict=True):
        res, first, _, compiled = dampax_fit(spec, t, x)
        _, again, _, _ = dampax_fit(spec, t, x)
        other_rows.append(dict(n=spec["n"], budget=swing_budget(spec, res), first_s=first,
                               first_compile_s=compiled,
                               warm_s=again, model=res.model, success=bool(res.success),
                               cover=covers(res, spec)))
        print(f"another length, {spec['n']} samples: first fit {first:.2f} s ({compiled:.2f} s "
              f"compiling; swing budget {swing_budget(spec, res)}), repeated {again:.2f} s "
              f"({res.model}, success {res.success}, mu/D in 90 %: "
              f"{covers(res, spec)})", flush=True)

    cold = []
    if not args.no_cold:
        cache = Path(tmp.name) / "cold"
        t, x = traces[0]
        for label in ("fresh process, empty cache", "fresh process, same cache again"):
            out = fresh_process(specs[0], t, x, cache)
            cold.append(dict(label=label, **out))
            if "error" in out:
                print(f"{label}: FAILED {out['error']}", flush=True)
            else:
                print(f"{label}: fit {out['fit_s']:.2f} s ({out['compile_s']:.1f} s "
                      f"compiling; import {out['import_s']:.1f} s, "
                      f"process {out['process_s']:.1f} s; {out['model']}, success "
                      f"{out['success']})", flush=True)

    warm = np.array([r["warm_s"] for r in rows])
    sci = np.array([r["scipy"]["wall"] for r in rows])
    ratio = np.array([r["rms_ratio"] for r in rows])
    print(f"\nsummary over {n} traces of {SAMPLES} samples:")
    print(f"  dampax warm: median {np.median(warm):.2f} s, max {warm.max():.2f} s "
          f"(CPU median {np.median([r['warm_cpu_s'] for r in rows]):.2f} s)")
    print(f"  dampax first call: very first {rows[0]['first_s']:.2f} s "
          f"({rows[0]['first_compile_s']:.1f} s compiling), others "
          f"median {np.median([r['first_s'] for r in rows[1:]] or [math.nan]):.2f} s, max "
          f"{max([r['first_s'] for r in rows[1:]] or [math.nan]):.2f} s")
    for r in other_rows:
        print(f"  first fit of another length ({r['n']} samples): {r['first_s']:.2f} s")
    for c in cold:
        if "fit_s" in c:
            print(f"  {c['label']}: fit {c['fit_s']:.2f} s (+ import {c['import_s']:.1f} s)")
    sci_cpu = np.array([r["scipy"]["cpu"] for r in rows])
    warm_cpu = np.array([r["warm_cpu_s"] for r in rows])
    print(f"  scipy least_squares: median {np.median(sci):.2f} s, max {sci.max():.2f} s "
          f"(CPU median {np.median(sci_cpu):.2f} s)")
    print(f"  ratio scipy/dampax (wall, medians): {np.median(sci) / np.median(warm):.2f} "
          f"(CPU {np.median(sci_cpu) / np.median(warm_cpu):.2f}); per trace: median "
          f"{np.median(sci / warm):.2f}, range {np.min(sci / warm):.2f}-"
          f"{np.max(sci / warm):.2f}")
    print(f"  rms scipy/dampax: median {np.median(ratio):.5f}, range "
          f"{ratio.min():.5f}-{ratio.max():.5f}; equal (within 1 +- {EQUAL_RMS:g}) in "
          f"{int(np.sum(np.abs(ratio - 1) <= EQUAL_RMS))} of {n}, scipy higher in "
          f"{int(np.sum(ratio > 1 + EQUAL_RMS))}, lower in {int(np.sum(ratio < 1 - EQUAL_RMS))}")
    models = {m: sum(r["model"] == m for r in rows) for m in sorted({r["model"] for r in rows})}
    print(f"  model answered: {models}; success {sum(r['success'] for r in rows)} of {n}")
    for name in FREE:
        print(f"  90 % interval covers the true {name}: {sum(r['cover'][name] for r in rows)} "
              f"of {n}")
    print(f"end: {load()}")

    if args.profile is not None:
        import cProfile
        import pstats

        spec, (t, x) = specs[args.profile], traces[args.profile]
        prof = cProfile.Profile()
        prof.enable()
        _, wall, _, _ = dampax_fit(spec, t, x)
        prof.disable()
        print(f"\ncProfile of trace {args.profile} (warm, {wall:.2f} s):")
        pstats.Stats(prof).sort_stats("cumulative").print_stats(40)

    if args.json:
        Path(args.json).write_text(json.dumps(dict(rows=rows, other=other_rows, cold=cold),
                                              indent=1, default=str))
    tmp.cleanup()


if __name__ == "__main__":
    main()
