"""Benchmark (issue 36, sixth session): a joint fit's first call in a fresh process, with the
exact model's batch of starts run start by start through the single joint fit's program (what
dampax does on a CPU) against the same batch vmapped in a program of its own (before), in one
run, each arm in its own fresh process with an empty cache, then a warm repeat.

The job: spring runs 1-2 of ``../shared/data`` (or ``$DAMPAX_DATA``), their first 20 s, b and D
shared, w0 fitted, ``LeastSquares(starts=8, max_swings=64)`` (the shapes of
tests/fit/test_joint.py).

    python benchmarks/joint_cold.py            # both arms, sequential first
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def data_dir() -> Path:
    env = os.environ.get("DAMPAX_DATA")
    if env:
        return Path(env).expanduser()
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def child(arm: str) -> dict:
    """One arm in this (fresh) process: the cold joint fit, then the same fit warm."""
    began = time.perf_counter()
    import dampax as dp
    from dampax._fit import _joint_problem, _joint_stages

    if arm == "vmapped":  # the batch as it ran before: one vmapped program of its own
        _joint_stages.run_joint_batch = _joint_problem.vmapped_batch
    imported = time.perf_counter()
    osc = dp.Oscillator(m=0.2016, k=14.91945)
    traces = [dp.load_trace(data_dir() / "spring_mass_airdrag" / f"run{i}.csv") for i in (1, 2)]
    kw = dict(oscillator=osc, free=("b", "D"), shared=("b", "D"), fit_omega0=True,
              window=dp.Window(end=22.0), solver=dp.LeastSquares(starts=8, max_swings=64))
    t0 = time.perf_counter()
    res = dp.fit(traces, **kw)
    t1 = time.perf_counter()
    dp.fit(traces, **kw)
    t2 = time.perf_counter()
    return dict(arm=arm, import_s=imported - began, cold_s=t1 - t0, warm_s=t2 - t1,
                b=float(res.params["b"]), D=float(res.params["D"]), success=bool(res.success))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", choices=("sequential", "vmapped"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return
    if not (data_dir() / "spring_mass_airdrag" / "run1.csv").exists():
        sys.exit(f"no spring runs under {data_dir()} (set DAMPAX_DATA)")
    rows = []
    for arm in ("sequential", "vmapped"):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "DAMPAX_CACHE_DIR": cache}
            out = subprocess.run([sys.executable, __file__, "--child", arm], env=env,
                                 capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("joint fit of spring runs 1-2 (20 s each, b and D shared), fresh process, empty cache")
    print(f"{'exact batch of starts':<24} {'cold s':>8} {'warm s':>8}   b [kg/s]    D [kg/m]")
    for r in rows:
        print(f"{r['arm']:<24} {r['cold_s']:>8.1f} {r['warm_s']:>8.1f}   {r['b']:.7g}   "
              f"{r['D']:.7g}   success {r['success']}")
    seq, vm = rows
    print(f"vmapped / sequential: cold {vm['cold_s'] / seq['cold_s']:.2f}x, warm "
          f"{vm['warm_s'] / seq['warm_s']:.2f}x")


if __name__ == "__main__":
    main()
