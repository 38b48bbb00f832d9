"""Issue 25 item 3: the torsion releases fitted with and without static friction mu_s.

Per unit mass, angle in deg, w0 fitted, reference model, mu and b free; then mu_s free too
(``fit(free=("mu", "b", "mu_s"))``, whose first fit is the sliding-friction one, mu_s = mu).
Prints per release: rms of both fits, mu and the mu_s interval, the fitted centre (offset),
the data's rest (median of the last second) and the model's position at the window's end for
both fits, and the time. Reads ../shared/data (never copied into the repository).

    python benchmarks/torsion_static.py [60 70 80 90 100]
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

import dampax as dp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "torsion_pendulum_friction"


def main():
    angles = sys.argv[1:] or ["60", "70", "80", "90", "100"]
    print("| release | rms sliding -> with mu_s [deg] | mu | mu_s interval | offset [deg] | "
          "data rest | model end sliding -> with mu_s [deg] | s |")
    print("|---|---|---|---|---|---|---|---|")
    for angle in angles:
        trace = dp.load_trace(DATA / f"release_{angle}deg.txt", time="Time_Elapsed(s)",
                              position="Angle(deg)", rate="auto")
        began = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = dp.fit(trace, fit_omega0=True, free=("mu", "b", "mu_s"), model="reference",
                         window=dp.Window(units="deg"))
        took = time.perf_counter() - began
        pr = res.profiled["mu_s"]
        lo, hi = pr["interval"]
        t, x = np.asarray(trace.t), np.asarray(trace.x)
        rest = float(np.median(x[t >= t[-1] - 1.0]))
        end = float(np.asarray(res.model_x)[-1])
        print(f"| {angle} deg | {pr['rms_sliding']:.4g} -> {res.rms:.4g} | "
              f"{res.params['mu']:.4g} | [{lo:.4g}, {hi:.4g}] (halt at turn "
              f"{pr['halt_turn']}) | {res.params['offset']:.4g} | {rest:.4g} | "
              f"{pr['end_sliding']:.4g} -> {end:.4g} | {took:.0f} |", flush=True)
        print(f"  {angle}: success {res.success} ({res.reason}), fits {pr['evaluations']}, "
              f"halt_time {res.derived.get('halt_time')}", flush=True)


if __name__ == "__main__":
    main()
