"""Calibration of the fit checks (issue 25, item 1): are dp.fit's verdicts true?

    python benchmarks/fit_calibration.py [--n 200] [--seed 0] [--quick] [--models reference,ansatz]
    python benchmarks/fit_calibration.py --models auto   # the exact answer, model="auto" (issue 36)
    python benchmarks/fit_calibration.py --models default   # dp.fit as called without model=
    python benchmarks/fit_calibration.py --models default --lacking k3   # the settle rule

Traces are drawn from an INDEPENDENT integrator (scipy ``solve_ivp``, DOP853, rtol 1e-11,
terminal events at v = 0 and exact stick-slip: the block sticks for good at a velocity zero where
|k x + k3 x^3| <= mu m g), not from dampax, over the dimensionless family of docs/DESIGN.md
(eq. 21: d0 = 2 mu g/(pi w0), d1 = b/(2m), d2 = 4 D w0/(3 pi m)):

- d0/(w0 A0) in [0, 0.15], d1/w0 in [0, 0.1], d2 A0/w0 in [0, 0.6] (each term absent with
  probability 1/4, at least one present), any starting phase (x0 = A0 cos phi0,
  v0 = -w0 A0 sin phi0), an offset;
- w0 in [2, 20] rad/s, m in [0.1, 5] kg, A0 in [1 cm, 50 cm] (log-uniform): the motion depends
  only on the ratios, the fits must not;
- a hardening spring k3 A0^2/k in [0.01, 0.2] for a third of the traces (k3 = 0 otherwise);
- noise 0.1-3 % of A0 (log-uniform), white or AR(1) with coefficient up to 0.95 (marginal sd);
- windows from one swing (half a period) to 50 periods, 1000-4096 samples (one padded shape:
  the compiled fits are shared).

Each trace is fitted with ``dp.fit`` as a user would: half of them with the oscillator given
(m, k and, for a hardening spring, k3 known; w0 not fitted), half without (w0 fitted, per unit
mass, a hardening k3 fitted as ``free=(..., "k3")``); ``free`` names the damping terms present
(plus, for a fifth of the traces, one that is absent: its truth is 0); the default start
("auto"). Models: "reference" (the exact model: every failure must be the optimizer's or the
data's) on every draw, and "ansatz" (a closed-form approximation) where it makes
sense: on the draws of the same family whose own error estimate (``solve(...).error_estimate``)
is below the noise (elsewhere its parameters carry the approximation's bias, which no interval
of the fit can know).

Measured, per model:

- false refusals: a ValueError on a trace (every trace here holds a real signal) whose message
  does not state a true reason. A refusal "not separately identifiable; fix one" is a true
  reason: the fit with that constant fixed (at its truth) must then work, and is counted.
- false failures: success False although the truth of every fitted parameter lies inside its
  99 % ``conf_interval`` (goal <= 2 %).
- confident wrong answers: success True with a parameter farther than 3 half-widths of its
  99 % interval from the truth (goal 0).
- coverage: the share of 90 % ``conf_interval`` that contain the truth, per parameter, over
  the successful fits (goal 85-95 %).

``--quick`` draws 12 traces and fits the reference model only. Not a test (tests/fit/test_fit.py
fits a small fixed-seed sample of this family): the table goes to benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import evaluate, scipy_stick_slip  # noqa: E402  (the tests' scipy integrator)

G = 9.81
#: the family's bounds (issue 25, item 1)
RATIO_MAX = {"d0": 0.15, "d1": 0.1, "d2": 0.6}
NOISE_RANGE = (1e-3, 3e-2)  # of A0
PHI_MAX = 0.95
HALF_SWINGS = (1.0, 100.0)  # the window: one swing to 50 periods
SAMPLES = (1000, 4096)
K3_RANGE = (0.01, 0.2)  # k3 A0^2 / k
#: ``--wide``: a family beyond the calibrated one (issue 36's check of the general case):
#: viscous damping to half the critical, Coulomb and drag twice as strong, noise from 1e-4 to
#: 10 % of A0, 300 to 20,000 samples (the same windows: MAX_SWINGS follows HALF_SWINGS)
WIDE = {"RATIO_MAX": {"d0": 0.3, "d1": 0.5, "d2": 1.2}, "NOISE_RANGE": (1e-4, 0.1),
        "SAMPLES": (300, 20000)}
#: a refusal that names a true reason (the fit with one constant fixed must then work)
TRUE_REASONS = ("not separately identifiable",)
#: what the harness can hold at its truth after such a refusal
FIXABLE = ("mu", "b", "D", "offset")


# ----------------------------------------------------------------------------------------------
# the independent integrator


def stick_slip(m, k, mu, b, D, x0, v0, t_end, *, k3=0.0, g=G, rtol=1e-11, atol=None):
    """Eq. 3 with a cubic spring, swing by swing (scipy DOP853, terminal event at v = 0): the
    tests' ``helpers.scipy_stick_slip`` with an absolute tolerance of 1e-13 of the amplitude.

    Returns (segments, rest): dense-output pieces (t0, t1, sol) and the rest state (t, x) or
    None when the block still moves at ``t_end``.
    """
    scale = max(abs(x0), abs(v0) / math.sqrt(k / m), 1e-300)
    segments, _, rest = scipy_stick_slip(m, k, mu, b, D, x0, v0, t_end, g=g, rtol=rtol,
                                         atol=1e-13 * scale if atol is None else atol, k3=k3,
                                         max_swings=1_000_000)
    return segments, rest


def positions(segments, rest, ts):
    """x(ts) of a :func:`stick_slip` result."""
    return evaluate(segments, rest, np.asarray(ts, dtype=float))[0]


def ar1_noise(rng, n, sd, phi):
    """AR(1) noise of marginal sd ``sd`` (white for phi = 0)."""
    z = rng.standard_normal(n)
    if phi == 0.0:
        return sd * z
    e = np.empty(n)
    e[0] = z[0]
    c = math.sqrt(1.0 - phi * phi)
    for i in range(1, n):
        e[i] = phi * e[i - 1] + c * z[i]
    return sd * e


# ----------------------------------------------------------------------------------------------
# the family


def _logu(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw(rng) -> dict:
    """One trace of the family: the oscillator, start, noise, window and how it is fitted."""
    w0 = _logu(rng, 2.0, 20.0)
    m = _logu(rng, 0.1, 5.0)
    k = m * w0 * w0
    A0 = _logu(rng, 0.01, 0.5)
    present = rng.random(3) >= 0.25
    if not present.any():
        present[rng.integers(3)] = True
    r = {name: (float(rng.uniform(0.0, hi)) if on else 0.0)
         for (name, hi), on in zip(RATIO_MAX.items(), present, strict=True)}
    # eq. 21 inverted by hand: d0 = 2 mu g/(pi w0), d1 = b/(2m), d2 = 4 D w0/(3 pi m)
    mu = math.pi * w0 * r["d0"] * w0 * A0 / (2.0 * G)
    b = 2.0 * m * r["d1"] * w0
    D = 3.0 * math.pi * m * (r["d2"] * w0 / A0) / (4.0 * w0)
    k3 = _logu(rng, *K3_RANGE) * k / A0 ** 2 if rng.random() < 1.0 / 3.0 else 0.0
    phi0 = float(rng.uniform(0.0, 2.0 * math.pi))
    x0, v0 = A0 * math.cos(phi0), -w0 * A0 * math.sin(phi0)
    noise = _logu(rng, *NOISE_RANGE) * A0
    phi = float(rng.uniform(0.0, PHI_MAX)) if rng.random() < 0.5 else 0.0
    half_swings = _logu(rng, *HALF_SWINGS)
    span = half_swings * math.pi / w0
    n = int(rng.integers(SAMPLES[0], SAMPLES[1] + 1))
    free = [name for name, on in zip(("mu", "b", "D"), present, strict=True) if on]
    absent = [name for name, on in zip(("mu", "b", "D"), present, strict=True) if not on]
    if absent and rng.random() < 0.2:
        free.append(absent[int(rng.integers(len(absent)))])
    given = bool(rng.random() < 0.5)
    return dict(w0=w0, m=m, k=k, A0=A0, ratios=r, mu=mu, b=b, D=D, k3=k3, phi0=phi0, x0=x0,
                v0=v0, offset=float(rng.uniform(-1.0, 1.0) * A0), noise=noise, phi=phi,
                half_swings=half_swings, span=span, n=n,
                free=tuple(f for f in ("mu", "b", "D") if f in free), given=given,
                noise_seed=int(rng.integers(2 ** 31)))


def simulate(spec: dict):
    """(t, x) of a drawn trace: the independent integrator plus noise and offset."""
    t = np.linspace(0.0, spec["span"], spec["n"])
    seg, rest = stick_slip(spec["m"], spec["k"], spec["mu"], spec["b"], spec["D"], spec["x0"],
                           spec["v0"], spec["span"] * (1 + 1e-9) + 1e-12, k3=spec["k3"])
    clean = positions(seg, rest, t)
    rng = np.random.default_rng(spec["noise_seed"])
    x = clean + spec["offset"] + ar1_noise(rng, t.size, spec["noise"], spec["phi"])
    spec["_clean"] = clean + spec["offset"]
    spec["halt"] = None if rest is None else rest[0]
    spec["swings"] = len(seg)
    return t, x


def truth_of(spec: dict, free) -> dict:
    """The true values of the fitted parameters (per unit mass without an oscillator)."""
    per = 1.0 if spec["given"] else spec["m"]
    out = {"mu": spec["mu"], "b": spec["b"] / per, "D": spec["D"] / per,
           "offset": spec["offset"]}
    out = {k: v for k, v in out.items() if k in free or k == "offset"}
    if not spec["given"]:
        out["w0"] = spec["w0"]
    if "k3" in free:
        out["k3"] = spec["k3"] / per
    return out


# ----------------------------------------------------------------------------------------------
# fitting and judging


#: the reference model's swing budget for every trace (one compiled program for all)
MAX_SWINGS = int(1.15 * HALF_SWINGS[1]) + 16


def fit_one(spec, t, x, model, *, free=None, fixed=None, max_swings=MAX_SWINGS,
            lacking=False, p0=None):
    """dp.fit of a drawn trace as a user would call it; returns (result or None, error).
    ``lacking``: the fit leaves the trace's k3 out (a model that lacks a term of the data);
    ``p0``: the start (one start, no global search)."""
    import dampax as dp

    free = tuple(spec["free"] if free is None else free)
    kw = {} if model == "default" else dict(model=model)  # "default": dp.fit's own default
    solver = dp.LeastSquares(max_swings=max_swings) if p0 is None else \
        dp.LeastSquares(max_swings=max_swings, p0=p0, starts=1)
    fixed = dict(fixed or {})
    if "offset" in fixed:  # held at its value: offset=False with p0
        kw["offset"] = False
        solver = solver._replace(p0={"offset": fixed.pop("offset")})
    kw["solver"] = solver
    if spec["given"]:
        kw["oscillator"] = dp.Oscillator(m=spec["m"], k=spec["k"], **fixed)
        if spec["k3"] and not lacking:
            kw["k3"] = spec["k3"]
    else:
        if fixed:
            kw["oscillator"] = dp.Oscillator(m=1.0, k=1.0, **fixed)
            kw["fit_omega0"] = True
        if spec["k3"] and not lacking:
            free = free + ("k3",)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return dp.fit(t, x, free=free, **kw), None
    except ValueError as err:
        return None, str(err)


def judge(res, truth: dict, clean=None, t=None) -> dict:
    """Coverage and verdict of one fit against the truth.

    With the noise-free trace ``clean`` on the times ``t``: ``excess`` is the fit's residual
    sum of squares minus the truth's, in noise variances (the model is exact: a positive
    value means the optimizer stopped short of the truth's cost, a local optimum)."""
    ci90, ci99 = res.conf_interval(0.90), res.conf_interval(0.99)
    truth = {k: v for k, v in truth.items() if k in ci99}  # (a held offset is not fitted)
    inside99, cover90, worst = {}, {}, 0.0
    for name, value in truth.items():
        lo, hi = ci99[name]
        # an interval that is not finite (a standard error that is not) holds nothing: such a
        # fit is not counted right (nor as a false failure when it fails)
        inside99[name] = bool(lo <= value <= hi) and math.isfinite(hi - lo)
        lo9, hi9 = ci90[name]
        cover90[name] = bool(lo9 <= value <= hi9)
        half = 0.5 * (ci99[name][1] - ci99[name][0])
        # distance from the estimate in 99 % half-widths (the interval is est +- half, clipped)
        dist = abs(res.params[name] - value) / half if half > 0 else math.inf
        worst = max(worst, dist)
    right = all(inside99.values())
    excess = math.nan
    if clean is not None:
        sel = t >= res.t[0] - 1e-12
        r_true = res.x - clean[sel][: res.x.size]
        s_true = float(r_true @ r_true)
        s_fit = float(res.residuals @ res.residuals)
        var = s_true / max(r_true.size, 1)
        excess = (s_fit - s_true) / var if var > 0 else math.nan
    hac = res.hac_stderr
    z_hac = {k: (res.params[k] - v) / hac[k] if hac.get(k, 0) > 0 else math.inf
             for k, v in truth.items()}
    z_delta = {k: (res.params[k] - v) / res.stderr[k] if res.stderr.get(k, 0) > 0 else math.inf
               for k, v in truth.items()}
    return dict(excess=excess, t_start=float(res.t[0]), n_window=int(res.t.size),
                answered=res.model,
                z_hac=z_hac, z_delta=z_delta,
                correlation_max=float(np.nanmax(np.abs(
                    res.correlation - np.eye(len(res.varied))))) if len(res.varied) > 1
                else 0.0,success=bool(res.success), adequate=bool(res.adequate), reason=res.reason,
                inadequacy=list(res.inadequacy), right=right, inside99=inside99,
                cover90=cover90, worst=worst,
                confident_wrong=bool(res.success and worst > 3.0),
                false_failure=bool(right and not res.success),
                params={k: res.params[k] for k in truth},
                ci99={k: ci99[k] for k in truth},
                diagnostics={k: v for k, v in res.diagnostics.items()
                             if isinstance(v, (int, float, str))})


def ansatz_error(spec) -> float:
    """The ansatz's own error estimate (max |x - x_ref|/A0 from the packaged atlas)."""
    import dampax as dp

    try:
        sol = dp.solve(dp.Oscillator(m=spec["m"], k=spec["k"], mu=spec["mu"], b=spec["b"],
                                     D=spec["D"], k3=spec["k3"]), spec["x0"], spec["v0"])
        return float(sol.error_estimate)
    except (ValueError, TypeError, AttributeError):
        return math.nan


def run_case(spec, t, x, model, *, max_swings=MAX_SWINGS) -> dict:
    """Fit, refit with all but one of the named constants fixed after a true refusal, and
    judge."""
    rec = dict(model=model, status="fit")
    began = time.perf_counter()
    res, err = fit_one(spec, t, x, model, max_swings=max_swings)
    fixed, errors = {}, []
    while res is None:
        named = re.match(r"^(.*?) are not separately identifiable", err)
        errors.append(err)
        if not (named and any(s in err for s in TRUE_REASONS)) or len(errors) > 3:
            rec.update(status="refused", error="; then: ".join(errors))
            break
        # fix all but one of the named constants at their truth, as the message says (the
        # first named one stays free); a further true refusal of that fit is followed too
        group = [g.strip() for g in re.split(r",| and ", named.group(1)) if g.strip()]
        truth = truth_of(spec, spec["free"])
        more = {g: truth[g] for g in group[1:] if g in truth and g in FIXABLE}
        if not more:
            rec.update(status="refused", error="; then: ".join(errors))
            break
        fixed.update(more)
        free = tuple(f for f in spec["free"] if f not in fixed)
        rec.update(status="refused (true reason)", error="; then: ".join(errors),
                   fixed=sorted(fixed))
        res, err = fit_one(spec, t, x, model, free=free, fixed=fixed, max_swings=max_swings)
    if res is not None:
        try:
            rec.update(judge(res, truth_of(spec, tuple(res.free)), spec.get("_clean"), t))
        except np.linalg.LinAlgError as err:  # no interval: counted as a failed, wrong fit
            rec.update(success=bool(res.success), adequate=bool(res.adequate),
                       reason=res.reason + f" (no interval: {err})", inadequacy=[],
                       right=False, inside99={}, cover90={}, worst=math.inf,
                       confident_wrong=bool(res.success), false_failure=False, params={},
                       ci99={}, diagnostics={})
    rec["seconds"] = time.perf_counter() - began
    rec["_res"] = res
    return rec


def lacking_case(spec, t, x, model) -> dict:
    """The verdict of a fit that lacks the trace's k3 (issue 36, item 4: is the settle rule of
    ``_measures.settled_starts`` true?), against an independent search for a lower cost: the
    same model fitted from the truth's damping constants (and w0), one start. Where that
    finds a cost lower by more than one noise variance, the fit's optimum was local."""
    began = time.perf_counter()
    res, err = fit_one(spec, t, x, model, lacking=True)
    rec = dict(model=model, status="fit" if res is not None else "refused", error=err)
    if res is not None:
        truth = truth_of(spec, tuple(res.free))
        alt, _ = fit_one(spec, t, x, model, lacking=True, free=tuple(res.free),
                         p0={k: max(v, 1e-12) if k in ("mu", "b", "D") else v
                             for k, v in truth.items() if k != "offset"})
        s2 = float(res.chisqr) / max(res.ndata - res.nvarys, 1)
        below = (float(res.chisqr) - float(alt.chisqr)) / s2 if alt is not None else math.nan
        text = " ".join(res.inadequacy)
        rec.update(success=bool(res.success), adequate=bool(res.adequate), reason=res.reason,
                   inadequacy=list(res.inadequacy), answered=res.model,
                   stands="eq. 3 with these terms lacks" in text,
                   local="a local optimum, or the data hold" in (res.reason or ""),
                   k3_hint="cubic" in text, lower_elsewhere=bool(below > 1.0),
                   below_variances=below)
    rec["seconds"] = time.perf_counter() - began
    return rec


def lacking_table(records) -> list[str]:
    """The settle rule's table: fits that lack k3, by verdict, against the search from the
    truth."""
    fitted = [r for r in records if "success" in r]
    stands = [r for r in fitted if r["stands"]]
    local = [r for r in fitted if r["local"]]
    plain = [r for r in fitted if r["success"] and r["adequate"]]
    return [f"**fits that lack k3** ({len(records)} traces with k3, fitted without)", "",
            "| verdict | fits | a lower cost from the truth's start (> 1 noise variance) |",
            "|---|---|---|",
            f"| refused | {len(records) - len(fitted)} | - |",
            f"| success, adequate (k3 not seen) | {len(plain)} | "
            f"{sum(r['lower_elsewhere'] for r in plain)} |",
            f"| success, inadequate: the optimum stands (the search settled) | {len(stands)} | "
            f"{sum(r['lower_elsewhere'] for r in stands)} (goal 0) |",
            f"| failed: a local optimum, or what eq. 3 lacks (not settled) | {len(local)} | "
            f"{sum(r['lower_elsewhere'] for r in local)} |",
            f"| failed, another reason | "
            f"{sum(not r['success'] and not r['local'] for r in fitted)} | "
            f"{sum(r['lower_elsewhere'] for r in fitted if not r['success'] and not r['local'])}"
            " |",
            f"| structure named with the cubic-stiffness hint | "
            f"{sum(r['k3_hint'] for r in fitted)} | - |"]


# ----------------------------------------------------------------------------------------------
# the table


def _share(k, n):
    return f"{k}/{n} ({100.0 * k / n:.1f} %)" if n else "-"


def table(records, model, *, label=None) -> list[str]:
    recs = [r for r in records if r["model"] == model]
    fitted = [r for r in recs if "success" in r]
    refused = [r for r in recs if r["status"] == "refused"]
    ok = [r for r in fitted if r["success"]]
    lines = [f"**{label or model}** ({len(recs)} traces)", "",
             "| measure | value | goal |", "|---|---|---|",
             f"| false refusals | {_share(len(refused), len(recs))} | 0 |",
             f"| refusals with a true reason (refitted with one constant fixed) | "
             f"{sum(r['status'] == 'refused (true reason)' for r in recs)} | - |",
             f"| success | {_share(len(ok), len(fitted))} | - |",
             f"| false failures (truth inside the 99 % intervals, success False) | "
             f"{_share(sum(r['false_failure'] for r in fitted), len(fitted))} | <= 2 % |",
             f"| wrong fits (truth outside a 99 % interval) called failed | "
             f"{sum((not r['right']) and (not r['success']) for r in fitted)} | - |",
             f"| confident wrong answers (success, > 3 half-widths of the 99 % interval) | "
             f"{sum(r['confident_wrong'] for r in fitted)} | 0 |"]
    if model in ("auto", "default"):
        lines.append(f"| answered by the ansatz (its bias provably negligible) | "
                     f"{_share(sum(r.get('answered') == 'ansatz' for r in fitted), len(fitted))}"
                     " | - |")
        secs = sorted(r["seconds"] for r in recs)
        lines.append(f"| seconds per draw: median, max (compilation included) | "
                     f"{secs[len(secs) // 2]:.1f}, {secs[-1]:.1f} | - |")
    names = sorted({k for r in ok for k in r["cover90"]},
                   key=lambda s: ("mu", "b", "D", "w0", "k3", "offset").index(s))
    for name in names:
        hits = [r["cover90"][name] for r in ok if name in r["cover90"]]
        lines.append(f"| 90 % coverage of {name} | {_share(sum(hits), len(hits))} | 85-95 % |")
    return lines


def traces(model, n, seed):
    """The drawn traces of one model: every draw for the reference; for the ansatz, where it
    makes sense: the draws whose own error estimate (``solve(...).error_estimate``, the
    packaged atlas's expected max |x - x_ref| / A0 of the closed form) is below the noise
    (linear spring only: the atlas has no cubic stiffness)."""
    rng = np.random.default_rng(seed)
    out, tried = [], 0
    while len(out) < n and tried < 400 * n:
        spec = draw(rng)
        tried += 1
        if model == "ansatz":
            err = ansatz_error(spec) if spec["k3"] == 0.0 else math.nan
            if not err < spec["noise"] / spec["A0"]:
                continue
            spec["ansatz_error"] = err
        out.append(spec)
    return out, tried


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="traces drawn per model")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="12 traces, the reference model only")
    ap.add_argument("--models", default="reference,ansatz",
                    help="comma-separated fit models (default: reference,ansatz)")
    ap.add_argument("--first", type=int, default=0,
                    help="fit only the draws from this index on (the draws before are drawn, "
                         "not fitted: to continue a run)")
    ap.add_argument("--only", default=None,
                    help="comma-separated indices: fit only these draws")
    ap.add_argument("--out", type=Path, default=None, help="write every record (JSON lines)")
    ap.add_argument("--verbose", action="store_true", help="one line per fit")
    ap.add_argument("--save", type=Path, default=None,
                    help="folder for the arrays of every fit (npz; for analysis)")
    ap.add_argument("--lacking", choices=("k3",), default=None,
                    help="fit the draws with k3 without it (the model lacks a term of the "
                         "data): the settle rule's table")
    ap.add_argument("--wide", action="store_true",
                    help="draw from the wider family WIDE (not the calibrated one)")
    args = ap.parse_args(argv)
    if args.wide:
        globals().update(WIDE)
    n = 12 if args.quick else args.n
    models = ["reference"] if args.quick else args.models.split(",")
    records = []
    began = time.perf_counter()
    out = args.out.open("w") if args.out else None
    drawn = {}
    for model in models:
        specs, drawn[model] = traces(model, n, args.seed)
        only = None if args.only is None else {int(k) for k in args.only.split(",")}
        for i, spec in enumerate(specs):
            if i < args.first or (only is not None and i not in only):
                continue
            if args.lacking and not spec["k3"]:
                continue
            t, x = simulate(spec)
            if args.lacking:
                rec = lacking_case(spec, t, x, model)
                rec.update(index=i, spec={k: v for k, v in spec.items()
                                          if not k.startswith("_")})
                records.append(rec)
                if out:
                    out.write(json.dumps(rec, default=str) + "\n")
                    out.flush()
                if args.verbose:
                    print(f"{i:4d} success={rec.get('success')} stands={rec.get('stands')} "
                          f"local={rec.get('local')} lower={rec.get('below_variances')} "
                          f"{rec['seconds']:.1f}s {rec.get('reason') or rec.get('error') or ''}",
                          flush=True)
                continue
            rec = run_case(spec, t, x, model)
            res = rec.pop("_res")
            if args.save and res is not None:
                args.save.mkdir(parents=True, exist_ok=True)
                np.savez(args.save / f"{i:04d}_{model}.npz", t=res.t, x=res.x,
                         model_x=res.model_x, jac=res.jac, resid_rows=res.resid_rows,
                         varied=np.array(res.varied))
            rec.update(index=i, ansatz_error=spec.get("ansatz_error", math.nan),
                       spec={k: v for k, v in spec.items() if not k.startswith("_")})
            records.append(rec)
            if out:
                out.write(json.dumps(rec, default=str) + "\n")
                out.flush()
            if args.verbose:
                verdict = rec.get("success", rec["status"])
                print(f"{i:4d} {model:9s} {verdict!s:5s} right={rec.get('right')!s:5s} "
                      f"worst={rec.get('worst', math.nan):6.2f} free={spec['free']} "
                      f"given={spec['given']} hs={spec['half_swings']:.1f} "
                      f"phi={spec['phi']:.2f} k3={spec['k3'] > 0} {rec['seconds']:.1f}s "
                      f"{rec.get('reason') or rec.get('error') or ''}", flush=True)
    print(f"\n{n} traces per model, seed {args.seed}, {time.perf_counter() - began:.0f} s\n")
    if args.lacking:
        print("\n".join(lacking_table(records)) + "\n")
        models = []
    for model in models:
        label = model if model != "ansatz" else (
            f"ansatz, where its error estimate is below the noise ({n} of {drawn[model]} "
            "draws)")
        print("\n".join(table(records, model, label=label)) + "\n")
    if out:
        out.close()
    return records


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
