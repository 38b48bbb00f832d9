"""Speed-up of an error map over several local processes (issue 26, item 1).

Times ``dp.error_map(...)`` (warm caches: every configuration runs once untimed first) in fresh
Python processes, each configuration the same map:

- ``1 proc x 2 cores``: one process, XLA's default threading on 2 cores (``taskset -c 0,1``);
- ``1 proc x 1 core``: one process, one core (``taskset -c 0``, XLA single-threaded);
- ``2 procs x 1 core``: ``error_map(..., processes=2)``, each worker single-threaded
  (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``) and pinned
  to its own core (``--pin``, the default: the caller's ``taskset`` is inherited, so workers are
  moved to core i after they start);
- ``2 procs x 1 thread, unpinned``: the same, workers left to the scheduler;
- ``2 procs, default``: ``processes=2`` with no flags (what ``dampax errormap --processes 2``
  does): both workers on both cores.

The 2-process times are the whole call as a user sees it: starting the workers (each imports
dampax), connecting, loading or compiling the step, computing, gathering and reading the map
back. The map of every configuration is checked bit for bit against the first. CPU time is
that of every process of the run (the timing script, its workers), imports included, from
``getrusage(RUSAGE_CHILDREN)``: on a machine shared with other jobs, wall-clock ratios say
little, CPU times say what each configuration costs.

    python benchmarks/distributed.py                      # the default grid of dampax errormap
    python benchmarks/distributed.py --grid 8x8x4 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys

SINGLE = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"

_RUN = r"""
import json, sys, time, os
spec = json.loads(sys.argv[1])
import numpy as np
import dampax as dp
import dampax._studies._distributed as dist

if spec.get("pin"):  # move each worker to its own core once it runs (Linux)
    import subprocess as sp
    original = sp.Popen.__init__
    count = [0]
    def popen(self, *a, **k):
        original(self, *a, **k)
        core = count[0] % os.cpu_count()
        count[0] += 1
        os.sched_setaffinity(self.pid, {core})
    sp.Popen.__init__ = popen
n0, n2, nph = spec["grid"]
kw = dict(d0_ratio=np.linspace(0.0, 0.1, n0), d2_ratio=np.linspace(0.0, 0.75, n2),
          phi0=np.linspace(0.0, 7 * np.pi / 8, nph), periods=spec["periods"],
          samples_per_period=spec["spp"], chunk_size=spec["chunk"], progress=False)
if spec["processes"] > 1:
    kw["processes"] = spec["processes"]
t0 = time.perf_counter()
ds = dp.error_map(**kw)
wall = time.perf_counter() - t0
np.save(spec["out"], np.stack([ds[k].values for k in ("max_error", "rms_error", "energy_error",
                                                      "halt_time_error")]))
print(json.dumps(dict(wall=wall)))
"""


def run(spec: dict, *, cores: str, flags: str | None) -> tuple[float, float]:
    """(wall seconds of the error_map call, CPU seconds of every process of the run)."""
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if flags:
        env["XLA_FLAGS"] = flags
    cmd = ["taskset", "-c", cores, sys.executable, "-c", _RUN, json.dumps(spec)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"failed: {cmd[:4]} {spec}\n{proc.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return json.loads(proc.stdout.strip().splitlines()[-1])["wall"], cpu


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grid", default="16x16x8", help="d0 x d2 x phi0 (default: %(default)s, "
                   "the grid of dampax errormap)")
    p.add_argument("--periods", type=float, default=20.0)
    p.add_argument("--samples-per-period", type=int, default=64)
    p.add_argument("--chunk-size", type=int, default=128)
    p.add_argument("--repeat", type=int, default=3, help="timed runs per configuration, "
                   "interleaved; the best is reported (default: %(default)s)")
    p.add_argument("--out", default="/tmp/dampax-bench-distributed")
    args = p.parse_args()
    import numpy as np

    os.makedirs(args.out, exist_ok=True)
    grid = [int(v) for v in args.grid.lower().split("x")]
    base = dict(grid=grid, periods=args.periods, spp=args.samples_per_period,
                chunk=args.chunk_size)
    configs = {
        "1 proc x 2 cores": (dict(processes=1), "0,1", None),
        "1 proc x 1 core": (dict(processes=1), "0", SINGLE),
        "2 procs x 1 core": (dict(processes=2, pin=True), "0,1", SINGLE),
        "2 procs x 1 thread, unpinned": (dict(processes=2), "0,1", SINGLE),
        "2 procs, default": (dict(processes=2), "0,1", None),
    }
    n = grid[0] * grid[1] * grid[2]
    print(f"grid {args.grid} = {n} points, {args.periods:g} periods x "
          f"{args.samples_per_period} samples, chunk {args.chunk_size}; {os.cpu_count()} cores; "
          f"load average {os.getloadavg()[0]:.1f}")
    times: dict[str, list[float]] = {name: [] for name in configs}
    cpus: dict[str, list[float]] = {name: [] for name in configs}
    for name, (extra, cores, flags) in configs.items():  # warm-up: caches written
        t, c = run(base | extra | dict(out=f"{args.out}/warm.npy"), cores=cores, flags=flags)
        print(f"  warm-up {name}: {t:.1f} s (CPU {c:.1f} s)", flush=True)
    first = None
    for r in range(args.repeat):
        for i, (name, (extra, cores, flags)) in enumerate(configs.items()):
            out = f"{args.out}/{i}.npy"
            t, c = run(base | extra | dict(out=out), cores=cores, flags=flags)
            times[name].append(t)
            cpus[name].append(c)
            values = np.load(out)
            if first is None:
                first = values
            assert values.tobytes() == first.tobytes(), f"{name}: not the same map"
        print(f"  round {r + 1} (load average {os.getloadavg()[0]:.1f}): "
              + ", ".join(f"{k} {v[-1]:.1f} s" for k, v in times.items()), flush=True)
    ref = min(times["1 proc x 2 cores"])
    print(f"\n| configuration | wall, best of {args.repeat} | all runs | speed-up over "
          "1 proc x 2 cores | CPU of all its processes (at the best) |")
    print("|---|---|---|---|---|")
    for name, ts in times.items():
        best = ts.index(min(ts))
        print(f"| {name} | {min(ts):.1f} s | {', '.join(f'{t:.1f}' for t in ts)} | "
              f"{ref / min(ts):.2f}x | {cpus[name][best]:.1f} s |")
    print(f"\nevery map bit for bit the same; load average now {os.getloadavg()[0]:.1f} "
          "(1-minute; other jobs included)")


if __name__ == "__main__":
    main()
