"""Calibration of the joint fits of several runs (issue 25, item 2): do their intervals cover?

    python benchmarks/joint_calibration.py [--n 30] [--seed 0] [--model reference]

Each set is 2 or 3 runs of one oscillator (the damping constants shared), drawn from the
INDEPENDENT integrator of ``benchmarks/fit_calibration.py`` (scipy DOP853 with terminal events
at v = 0 and exact stick-slip): w0, m, the damping ratios d0/(w0 A0) in [0, 0.15],
d1/w0 in [0, 0.1], d2 A0/w0 in [0, 0.6] (each term absent with probability 1/4, at least one
present) as there; each run its own amplitude (0.5-1 A0), starting phase, offset, noise
(0.3-3 % of A0, white or AR(1) up to 0.9) and window (2-30 half swings, 600-2000 samples).
Half of the sets are fitted with the oscillator given (w0 known), half per unit mass with a
shared w0. ``dp.fit([run1, run2, ...], shared=...)`` with all three terms free and shared (an
absent one has the truth 0; one compiled layout per number of runs) and w0 when fitted,
``start="data"``, a swing budget of 64.

Measured: the share of sets fitted with success, the truth of every shared parameter inside
the 99 % interval, and the coverage of the 90 % ``conf_interval`` per shared parameter (goal
85-95 %). The reference model by default (exact: the intervals alone decide the coverage).
tests/fit/test_joint.py fits a small fixed-seed sample of this family.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _calibration():
    spec = importlib.util.spec_from_file_location("fit_calibration",
                                                  HERE / "fit_calibration.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


CAL = _calibration()
G = CAL.G


def draw(rng, n_runs=None, free=None) -> dict:
    """One set: the oscillator, the damping constants and 2-3 runs.

    Arguments:
        rng: a numpy Generator.
        n_runs: the number of runs (default 2 or 3).
        free: the damping terms present and fitted (default: each present with probability
            3/4, all three fitted: an absent one has the truth 0).
    """
    w0 = CAL._logu(rng, 2.0, 20.0)
    m = CAL._logu(rng, 0.1, 5.0)
    k = m * w0 * w0
    A0 = CAL._logu(rng, 0.01, 0.5)
    if free is None:
        present = rng.random(3) >= 0.25
        if not present.any():
            present[rng.integers(3)] = True
    else:
        present = np.array([n in free for n in ("mu", "b", "D")])
    r = {name: (float(rng.uniform(0.0, hi)) if on else 0.0)
         for (name, hi), on in zip(CAL.RATIO_MAX.items(), present, strict=True)}
    mu = math.pi * w0 * r["d0"] * w0 * A0 / (2.0 * G)
    b = 2.0 * m * r["d1"] * w0
    D = 3.0 * math.pi * m * (r["d2"] * w0 / A0) / (4.0 * w0)
    n_runs = int(rng.integers(2, 4)) if n_runs is None else n_runs
    runs = []
    for _ in range(n_runs):
        amp = A0 * float(rng.uniform(0.5, 1.0))
        phi0 = float(rng.uniform(0.0, 2.0 * math.pi))
        half_swings = CAL._logu(rng, 2.0, 30.0)
        runs.append(dict(x0=amp * math.cos(phi0), v0=-w0 * amp * math.sin(phi0),
                         offset=float(rng.uniform(-1.0, 1.0) * A0),
                         noise=CAL._logu(rng, 3e-3, 3e-2) * A0,
                         phi=float(rng.uniform(0.0, 0.9)) if rng.random() < 0.5 else 0.0,
                         span=half_swings * math.pi / w0, n=int(rng.integers(600, 2001)),
                         noise_seed=int(rng.integers(2 ** 31))))
    if free is None:  # every term fitted: one compiled layout per number of runs
        free = ("mu", "b", "D")
    return dict(w0=w0, m=m, k=k, A0=A0, ratios=r, mu=mu, b=b, D=D, runs=runs, free=free,
                given=bool(rng.random() < 0.5))


def simulate(spec: dict):
    """[(t, x)] of the runs of a set."""
    out = []
    for run in spec["runs"]:
        t = np.linspace(0.0, run["span"], run["n"])
        seg, rest = CAL.stick_slip(spec["m"], spec["k"], spec["mu"], spec["b"], spec["D"],
                                   run["x0"], run["v0"], run["span"] * (1 + 1e-9) + 1e-12)
        clean = CAL.positions(seg, rest, t)
        rng = np.random.default_rng(run["noise_seed"])
        out.append((t, clean + run["offset"] + CAL.ar1_noise(rng, t.size, run["noise"],
                                                             run["phi"])))
    return out


def truth_of(spec: dict) -> dict:
    """The true values of the shared parameters (per unit mass without an oscillator)."""
    per = 1.0 if spec["given"] else spec["m"]
    out = {"mu": spec["mu"], "b": spec["b"] / per, "D": spec["D"] / per}
    out = {k: v for k, v in out.items() if k in spec["free"]}
    if not spec["given"]:
        out["w0"] = spec["w0"]
    return out


def fit_set(spec, runs, model="reference"):
    """dp.fit of the runs of a set, jointly; (JointResult or None, error)."""
    import dampax as dp

    kw = dict(model=model, window=dp.Window(start="data"), free=spec["free"],
              solver=dp.LeastSquares(max_swings=64))
    if spec["given"]:
        kw["oscillator"] = dp.Oscillator(m=spec["m"], k=spec["k"])
        kw["shared"] = spec["free"]
    else:
        kw["shared"] = spec["free"] + ("w0",)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return dp.fit(runs, **kw), None
    except ValueError as err:
        return None, str(err)


def judge(res, truth: dict, spec: dict) -> dict:
    """Coverage of one joint fit against the truth."""
    ci90, ci99 = res.conf_interval(0.90), res.conf_interval(0.99)
    return dict(success=bool(res.success), reason=res.reason,
                cover90={k: bool(ci90[k][0] <= v <= ci90[k][1]) for k, v in truth.items()},
                inside99={k: bool(ci99[k][0] <= v <= ci99[k][1]) for k, v in truth.items()},
                z={k: (res.values[k] - v) / res.hac_stderr[k] if res.hac_stderr[k] > 0
                   else math.inf for k, v in truth.items()},
                rms_over_noise=[r.rms / run["noise"] for r, run in
                                zip(res.runs, spec["runs"], strict=True)])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=30, help="number of sets")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first", type=int, default=0,
                        help="fit the sets from this index on (the earlier ones are drawn and "
                             "skipped: a run cut short resumes with the same sets)")
    parser.add_argument("--model", default="reference")
    parser.add_argument("--json", default=None, help="write the records here")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    records = []
    began = time.perf_counter()
    for i in range(args.n):
        spec = draw(rng)
        if i < args.first:
            continue
        runs = simulate(spec)
        truth = truth_of(spec)
        t0 = time.perf_counter()
        res, err = fit_set(spec, runs, args.model)
        rec = dict(i=i, n_runs=len(runs), given=spec["given"], free=spec["free"],
                   ratios=spec["ratios"], seconds=time.perf_counter() - t0)
        if res is None:
            rec.update(status="refused", error=err)
        else:
            rec.update(status="fitted", **judge(res, truth, spec))
        records.append(rec)
        print(json.dumps({k: v for k, v in rec.items() if k != "ratios"}), flush=True)
    fitted = [r for r in records if r["status"] == "fitted"]
    ok = [r for r in fitted if r["success"]]
    print(f"\n{len(records)} sets of 2-3 runs, model {args.model}, seed {args.seed}: "
          f"{len(fitted)} fitted, {len(ok)} with success, "
          f"{len(records) - len(fitted)} refused; {time.perf_counter() - began:.0f} s")
    names = ("mu", "b", "D", "w0")
    print("| parameter | sets | 90 % coverage | truth inside 99 % |")
    print("|---|---|---|---|")
    for name in names:
        cov = [r["cover90"][name] for r in ok if name in r["cover90"]]
        in99 = [r["inside99"][name] for r in ok if name in r["inside99"]]
        if cov:
            print(f"| {name} | {len(cov)} | {100 * np.mean(cov):.0f} % | "
                  f"{100 * np.mean(in99):.0f} % |")
    allc = [v for r in ok for v in r["cover90"].values()]
    if allc:
        print(f"| all | {len(allc)} | {100 * np.mean(allc):.0f} % | "
              f"{100 * np.mean([v for r in ok for v in r['inside99'].values()]):.0f} % |")
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
