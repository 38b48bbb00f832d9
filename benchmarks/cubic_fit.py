"""Issue 14: fits of the real traces with the cubic stiffness k3 free (profiled).

Spring runs 1 and 2 (m = 0.2016 kg, w0 fitted; b, D free; positions in m), the pendulum on
video (per unit mass, angle in rad; b, D free) and the torsion releases (per unit mass, deg;
mu, b free), each without and with "k3" in ``free``. Prints rms, k3, its 95 % interval and the
damping constants. Reads ../shared/data (never copied into the repository).

    python benchmarks/cubic_fit.py [--only spring|pendulum|torsion]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import dampax as dp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def row(name, res, keys):
    ci = res.conf_interval(0.95)
    vals = ", ".join(f"{k}={res.params[k]:.5g} [{ci[k][0]:.4g}, {ci[k][1]:.4g}]"
                     for k in keys if k in ci)
    print(f"{name}: rms={res.rms:.4g} success={res.success} adequate={res.adequate} "
          f"{vals}", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="")
    args = ap.parse_args()
    cases = []
    spring = dp.Oscillator(m=0.2016, k=14.91945)
    for run in ("run1", "run2"):
        cases.append(("spring", f"spring {run}", DATA / "spring_mass_airdrag" / f"{run}.csv",
                      dict(oscillator=spring, fit_omega0=True), ("b", "D")))
    cases.append(("pendulum", "pendulum", DATA / "pendulum_airdrag" / "AAAtAmp3revised.txt",
                  dict(window=dp.Window(units="rad")), ("b", "D")))
    for deg in (60, 70, 80, 90, 100):
        cases.append(("torsion", f"torsion {deg} deg",
                      DATA / "torsion_pendulum_friction" / f"release_{deg}deg.txt", {},
                      ("mu", "b")))
    for kind, name, path, kw, free in cases:
        if args.only and kind != args.only:
            continue
        trace = (dp.load_trace(path, time="Time_Elapsed(s)", position="Angle(deg)",
                               rate="auto") if kind == "torsion" else dp.load_trace(path))
        t0 = time.perf_counter()
        lin = dp.fit(trace, free=free, **kw)
        row(f"{name} linear", lin, free)
        res = dp.fit(trace, free=free + ("k3",), **kw)
        row(f"{name} k3 free ({time.perf_counter() - t0:.0f} s, "
            f"{res.profiled['k3']['evaluations']} fits, k3 A^2/k = "
            f"{res.profiled['k3']['ratio']:.4g}, rho = {res.profiled['k3']['rho']:.3f})",
            res, free + ("k3", "w0"))


if __name__ == "__main__":
    main()
