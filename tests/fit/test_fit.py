"""Fitting damping constants (dampax._fit): synthetic truth, coverage, scipy agreement, real data.

Compilation dominates the run time (10-30 s per compiled fit on 2 cores), so the tests share
shapes: the synthetic trace has 8192 samples, the same padded length as the torsion file, and
fit() pads every trace to a power of two.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import count_reads, evaluate, scipy_stick_slip

import dampax as dp
from dampax._cli.fit import add_arguments, run
from dampax._fit import (
    PARAMS,
    compare_envelope_models,
    compare_models,
    example_trace,
    fit,
    fit_arrays,
    fit_envelope,
    initial_guess,
    residual_function,
)
from dampax._trace import Trace, load_trace

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
needs_data = pytest.mark.skipif(
    not DATA.is_dir(), reason=f"measured data not found at {DATA} (the shared data folder "
                              "beside the checkout); skipping the real-data fits")

# the synthetic oscillator: m = 0.2 kg, k = 15 N/m, Coulomb + quadratic drag, 5 cm start
M, K = 0.2, 15.0
TRUTH = dict(mu=0.0005, b=0.0, D=0.02)
X0, V0, OFFSET, NOISE = 0.05, 0.0, 0.4, 2e-4
RATE, N = 100.0, 8192
KNOWN = dp.Oscillator(m=M, k=K)


def ansatz_trace(n=N, *, noise=NOISE, seed=0, offset=OFFSET, rate=RATE, truth=TRUTH):
    """x(t) of the matched ansatz (the fitted model itself) plus Gaussian noise."""
    sol = dp.solve(dp.Oscillator(m=M, k=K, **truth), X0, V0)
    t = np.arange(n) / rate
    x = np.asarray(sol.x(t)) + offset
    return t, x + noise * np.random.default_rng(seed).standard_normal(n)


@pytest.fixture(scope="module")
def synthetic():
    t, x = ansatz_trace()
    res = fit(t, x, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True,
              window=dp.Window(start="data"), model="ansatz")
    return t, x, res


def test_synthetic_truth_within_3_stderr_and_5_percent(synthetic):
    t, x, res = synthetic
    assert res.success, res.message
    assert res.varied == ["mu", "D", "w0", "offset", "x0", "v0"]
    truth = {**TRUTH, "w0": math.sqrt(K / M), "offset": OFFSET, "x0": X0, "v0": V0}
    for name in res.varied:
        est, err = res.params[name], res.stderr[name]
        assert abs(est - truth[name]) < 3 * err, (name, est, err, truth[name])
    for name in ("mu", "D"):
        assert abs(res.params[name] / truth[name] - 1) < 0.05
        assert res.stderr[name] / res.params[name] < 0.05
    assert res.params["b"] == 0.0 and math.isnan(res.stderr["b"])  # not free
    assert res.rms == pytest.approx(NOISE, rel=0.05)
    assert res.ndata == N and res.nvarys == 6
    assert res.redchi == pytest.approx(NOISE ** 2, rel=0.1)
    assert res.bic > res.aic  # ln(n) > 2
    np.testing.assert_allclose(res.correlation, res.correlation.T)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0)
    # the pure core on the same (padded, weight 0) arrays: the same optimum, and the same
    # compiled function as fit()
    p0 = initial_guess(t, x, free=("mu", "D"), oscillator=KNOWN, fit_omega0=True)
    pad = 2 * N
    tp, xp = np.full(pad, t[-1]), np.full(pad, x[-1])
    tp[:N], xp[:N] = t, x
    core = fit_arrays(tp, xp, p0, free=("mu", "D"), fit_omega0=True, m=M,
                      weights=(np.arange(pad) < N).astype(float))
    assert bool(core.success)
    # (v0 is near 0: compared on the scale of the swing's velocity, X0 w0)
    ours = np.array([res.params[p] for p in PARAMS])
    np.testing.assert_allclose(np.asarray(core.params)[:6], ours[:6], rtol=1e-7, atol=1e-12)
    assert abs(float(core.params[6]) - ours[6]) <= 1e-9 * X0 * math.sqrt(K / M), \
        (float(core.params[6]), ours[6])
    np.testing.assert_allclose(np.asarray(core.stderr)[[0, 2]],
                               [res.stderr["mu"], res.stderr["D"]], rtol=1e-6)


def test_report_and_plot(synthetic, tmp_path):
    _, _, res = synthetic
    text = res.report()
    for needle in ("[[Fit Statistics]]", "# data points      = 8192", "# variables        = 6",
                   "chi-square", "reduced chi-square", "Akaike info crit",
                   "Bayesian info crit", "[[Variables]]", "mu:", "+/-", "b:", "(fixed)",
                   "[[Correlations]]", "C(mu, D)"):
        assert needle in text, needle
    path = res.plot(tmp_path / "fit.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = res.to_dict()
    json.dumps(summary)
    assert summary["params"]["mu"] == res.params["mu"]


def test_same_optimum_as_scipy_least_squares(synthetic):
    from scipy.optimize import least_squares

    t, x, res = synthetic
    fun, jac, names = residual_function(t, x, free=("mu", "D"), oscillator=KNOWN,
                                        fit_omega0=True)
    assert names == res.varied
    start = np.array([res.init[n] for n in names])
    ref = least_squares(fun, start, jac=jac, x_scale="jac", xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=200)
    ours = np.array([res.params[n] for n in names])
    assert 0.5 * np.sum(fun(ours) ** 2) <= ref.cost * (1 + 1e-9)
    for name, a, b in zip(names, ours, ref.x, strict=True):
        scale = abs(b) if name != "v0" else X0 * math.sqrt(K / M)  # v0 is ~0
        assert abs(a - b) <= 1e-6 * scale, (name, a, b)


def test_coverage_of_vmapped_fits():
    """50 noisy repeats fitted at once by jax.vmap of the pure core: the 1-sigma intervals
    cover the truth in about 68 % of the cases (the model is exact for the data)."""
    n, reps = 1024, 50
    t = np.arange(n) / RATE
    xs = np.stack([ansatz_trace(n, seed=500 + i)[1] for i in range(reps)])
    p0 = np.stack([initial_guess(t, xi, free=("mu", "D"), oscillator=KNOWN) for xi in xs])

    batched = jax.vmap(lambda xi, pi: fit_arrays(t, xi, pi, free=("mu", "D"), m=M))
    out = batched(jnp.asarray(xs), jnp.asarray(p0))
    assert out.params.shape == (reps, 7) and out.stderr.shape == (reps, 7)
    assert bool(jnp.all(out.success))
    params, stderr = np.asarray(out.params), np.asarray(out.stderr)
    for i, name in ((0, "mu"), (2, "D")):
        z = (params[:, i] - TRUTH[name]) / stderr[:, i]
        covered = float(np.mean(np.abs(z) < 1.0))
        assert 0.55 <= covered <= 0.80, (name, covered)
        assert abs(np.mean(z)) < 0.5 and 0.7 < np.std(z) < 1.35, (name, np.mean(z), np.std(z))


def test_soft_l1_resists_outliers(synthetic):
    t, x, clean = synthetic
    rng = np.random.default_rng(7)
    bad = x.copy()
    idx = rng.choice(N, size=N // 50, replace=False)  # 2 % glitches of 1-3 cm
    bad[idx] += rng.choice([-1, 1], idx.size) * rng.uniform(0.01, 0.03, idx.size)
    kw = dict(oscillator=KNOWN, free=("mu", "D"), fit_omega0=True,
              window=dp.Window(start="data"))
    linear = fit(t, bad, **kw, model="ansatz")
    robust = fit(t, bad, **kw, solver=dp.LeastSquares(loss="soft_l1"), model="ansatz")
    assert robust.success and robust.loss == "soft_l1"
    assert robust.f_scale == pytest.approx(NOISE, rel=0.5)  # MAD of the residuals
    for name in ("mu", "D"):
        err = clean.stderr[name]
        assert abs(robust.params[name] - TRUTH[name]) < 4 * err
        assert abs(robust.params[name] - TRUTH[name]) < abs(linear.params[name] - TRUTH[name])
        assert robust.stderr[name] < linear.stderr[name]


def test_constant_not_in_the_data_goes_to_zero_gracefully(synthetic):
    """b (absent from the data) goes to its bound; the cost is scipy's least_squares optimum
    with the constants bounded at 0 (an independent optimizer on the same residuals)."""
    from scipy.optimize import least_squares

    t, x, _ = synthetic
    res = fit(t, x, oscillator=KNOWN, free=("mu", "b", "D"), fit_omega0=True,
              window=dp.Window(start="data"), model="ansatz")
    assert res.success, res.message
    assert res.params["b"] < 3 * res.stderr["b"] and math.isfinite(res.stderr["b"])
    for name in ("mu", "D"):
        assert abs(res.params[name] - TRUTH[name]) < 3 * res.stderr[name]
    fun, jac, names = residual_function(t, x, free=("mu", "b", "D"), oscillator=KNOWN,
                                        fit_omega0=True)
    lower = [0.0 if n in ("mu", "b", "D") else -np.inf for n in names]
    start = np.array([max(res.init[n], 1e-6) if n in ("mu", "b", "D") else res.init[n]
                      for n in names])
    ref = least_squares(fun, start, jac=jac, bounds=(lower, np.inf), x_scale="jac",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=500)
    assert 0.5 * res.chisqr <= ref.cost * (1 + 1e-9)


@pytest.mark.parametrize("optimizer, tol", [("lbfgs", 1e-4), ("adam", 0.02)])
def test_optax_optimizers_reach_the_lm_optimum(synthetic, optimizer, tol):
    t, x, lm = synthetic
    res = fit(t, x, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True,
              window=dp.Window(start="data"), solver=dp.LeastSquares(optimizer=optimizer, starts=1),
              model="ansatz")
    assert res.success, res.message
    for name in ("mu", "D"):
        assert res.params[name] == pytest.approx(lm.params[name], rel=tol)
    assert res.chisqr == pytest.approx(lm.chisqr, rel=10 * tol)


def test_auto_start_skips_the_release(monkeypatch):
    # a hand release: the block is held off centre, pushed out, then swings freely
    t, x = ansatz_trace(6000)
    hold = np.full(300, x[0] - 0.01)
    ramp = np.linspace(x[0] - 0.01, x[0], 100)
    tt = np.arange(400 + t.size) / RATE
    xx = np.concatenate([hold, ramp, x])
    reads, analyses = count_reads(monkeypatch, xx)
    res = fit(tt, xx, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True, model="ansatz")
    assert len(reads) == len(analyses) == 1  # one analysis places the window and reads it
    w0 = math.sqrt(K / M)
    # the first extreme after the largest excursion: half a period after the release
    assert res.t_start == pytest.approx(4.0 + math.pi / w0, abs=0.02)
    for name in ("mu", "D"):
        assert abs(res.params[name] - TRUTH[name]) < 3 * res.stderr[name]


@pytest.mark.parametrize("half_swings", [1.6, 3.0, 12.0])
def test_auto_start_keeps_a_record_that_moves_from_its_first_sample(half_swings):
    """A record of the free decay itself (scipy's integrator with exact stick-slip, from t = 0,
    the phase in every quadrant, strong friction and drag, 1 % noise) has no release to skip:
    the window starts at its first sample. Skipping to the first turning point after the
    largest excursion cost such records up to 85 % of their samples, and with them the decay
    (fit_calibration.py seed 2: two confident wrong answers). A hold before the release is
    still skipped (test_auto_start_skips_the_release)."""
    from helpers import evaluate, scipy_stick_slip

    from dampax._fit._analysis import analyse, start_index

    m, w0, A = 1.0, 15.0, 0.2
    rng = np.random.default_rng(int(10 * half_swings))
    for phi0 in (0.1, 0.7, 2.0, 3.3, 4.6, 5.9):
        seg, _, rest = scipy_stick_slip(m, m * w0 * w0, 0.2, 0.0, 8.0, A * math.cos(phi0),
                                        -w0 * A * math.sin(phi0), half_swings * math.pi / w0)
        t = np.linspace(0.0, half_swings * math.pi / w0, 2000)
        x = evaluate(seg, rest, t)[0] + 0.1 + 0.01 * A * rng.standard_normal(t.size)
        assert start_index(t, x, analyse(t, x), "auto") == 0, phi0


def test_input_errors():
    t, x = ansatz_trace(1024)  # 10 s, 6 periods (a fit needs two)
    with pytest.raises(ValueError, match="free must name"):
        fit(t, x, free=("mu", "c"), model="ansatz")
    with pytest.raises(ValueError, match="model must be"):
        fit(t, x, model="exact")
    with pytest.raises(ValueError, match="loss must be"):
        fit(t, x, solver=dp.LeastSquares(loss="huber"), model="ansatz")
    with pytest.raises(ValueError, match="at least 10"):
        fit(t[:5], x[:5], model="ansatz")
    with pytest.raises(ValueError, match="same length"):
        fit(t, x[:-1], model="ansatz")
    with pytest.raises(ValueError, match="p0: unknown"):
        fit(t, x, solver=dp.LeastSquares(p0={"k": 1.0}), model="ansatz")
    # p0 of a constant the fit holds (it was held at p0's value, overriding the oscillator's)
    with pytest.raises(ValueError, match="p0: b not fitted here"):
        fit(t, x, solver=dp.LeastSquares(p0={"b": 0.01}), model="ansatz")
    with pytest.raises(ValueError, match="p0: w0 not fitted here"):
        fit(t, x, oscillator=dp.Oscillator(m=1.0, k=4.0), solver=dp.LeastSquares(p0={"w0": 2.1}),
            model="ansatz")
    with pytest.raises(ValueError, match="a dampax.Trace is passed alone"):
        fit(t, dp.Trace(t=t, x=x))  # (a TypeError from float() before)
    # elapsed times as timedelta64 (pandas) are seconds (they were read as ns: w0 1e9 small)
    from dampax._fit._inputs import as_times

    np.testing.assert_allclose(as_times((t * 1e9).astype("timedelta64[ns]")), t, atol=1e-9)
    with pytest.raises(ValueError, match="t: datetimes"):
        fit(np.datetime64("2026-01-01") + (t * 1e3).astype("timedelta64[ms]"), x)
    # a fit of other data handed to a ranking or a posterior (it was used as it was)
    other = fit(t, 1.5 * x, free=("mu", "D"), model="ansatz")
    with pytest.raises(ValueError, match="fitted: a fit of other data"):
        compare_models(t, x, candidates=(("mu", "D"),), fitted={("mu", "D"): other},
                       model="ansatz")
    with pytest.raises(ValueError, match="start_fit: a fit of other data"):
        dp.posterior(t, x, model="ansatz", start_fit=other)
    with pytest.raises(ValueError, match="sets free itself"):
        compare_models((t, x), free=("mu",), model="ansatz")
    with pytest.raises(ValueError, match="fit_omega0=False needs an oscillator"):
        fit(t, x, fit_omega0=False, model="ansatz")
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        fit(t, x, solver=dp.LeastSquares(max_steps=0), model="ansatz")
    with pytest.raises(ValueError, match="starts must be a positive integer"):
        fit(t, x, solver=dp.LeastSquares(starts=0), model="ansatz")
    with pytest.raises(ValueError, match="units must be"):
        fit(t, x, window=dp.Window(units=""), model="ansatz")


def test_cli(tmp_path, capsys, monkeypatch):
    import argparse

    from dampax import _cli

    t, x = ansatz_trace(N)
    path = tmp_path / "trace.csv"
    rows = "".join(f"{a:.4f};{b:.6f}\r\n" for a, b in zip(t, x, strict=True))
    path.write_text("time;position\r\n" + rows)
    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    out = tmp_path / "out"
    assert _cli.main(["fit", "--model", "ansatz",
                      str(path), "--m", str(M), "--k", str(K), "--fit-omega0",
                      "--free", "mu,D", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "[[Variables]]" in text and "Model ranking by BIC" in text
    assert "the data support: mu + D" in text
    summary = json.loads((out / "fit.json").read_text())
    assert summary["fit"]["free"] == ["mu", "D"]
    assert abs(summary["fit"]["params"]["D"] / TRUTH["D"] - 1) < 0.05
    assert summary["ranking"]["ranking"][0]["free"] == ["mu", "D"]
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"
    # errors: one line, status 2
    assert _cli.main(["fit", str(tmp_path / "missing.csv"), "--out", str(out)]) == 2
    assert "dampax: error:" in capsys.readouterr().err
    assert _cli.main(["fit", str(path), "--free", "mu,q"]) == 2
    assert "free must name" in capsys.readouterr().err
    assert _cli.main(["fit"]) == 2
    assert "PATH or --example" in capsys.readouterr().err
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([str(path), "--rate", "fast", "--out", str(tmp_path / "bad")])
    with pytest.raises(ValueError, match="--rate"):
        run(args)


# ----------------------------------------------------------------------------------------------
# real data


@needs_data
def test_spring_runs_1_and_2_agree():
    osc = dp.Oscillator(m=0.2016, k=14.91945)
    fits = [fit(load_trace(DATA / "spring_mass_airdrag" / f"run{i}.csv"), oscillator=osc,
                free=("b", "D"), fit_omega0=True, model="ansatz") for i in (1, 2)]
    for res in fits:
        assert res.success, res.message
        assert 8.40 < res.params["w0"] < 8.50 < math.sqrt(14.91945 / 0.2016)  # spring mass
        assert res.rms < 0.004  # m, on a 7 cm swing
    for name in ("b", "D"):
        a, b = fits[0].params[name], fits[1].params[name]
        assert abs(a - b) / (0.5 * (a + b)) < 0.10, (name, a, b)
    # issue 11: the intervals that allow for correlated residuals overlap. Run 3 (glitches,
    # robust loss) starts at 8.2 cm instead of 7.0-7.2 cm, and the split between b and D
    # (correlation -0.9) follows the amplitude range: from t = 5.5 s, where its swing is 7.1
    # cm like the others', its b lies inside both intervals and its D inside their union
    # (0.1 % below run 1's lower end); from the automatic start it does not (benchmarks/README)
    ci = [res.conf_interval(0.95) for res in fits]
    run3 = fit(load_trace(DATA / "spring_mass_airdrag" / "run3.csv"), oscillator=osc,
               free=("b", "D"), fit_omega0=True, window=dp.Window(start=5.5),
               solver=dp.LeastSquares(loss="soft_l1"), model="ansatz")
    assert run3.success, run3.reason
    assert run3.derived["A"] == pytest.approx(0.0708, abs=0.001)
    for name in ("b", "D"):
        (lo1, hi1), (lo2, hi2) = ci[0][name], ci[1][name]
        assert max(lo1, lo2) < min(hi1, hi2), (name, ci[0][name], ci[1][name])
        assert min(lo1, lo2) < run3.params[name] < max(hi1, hi2), (name, run3.params[name])
    assert max(ci[0]["b"][0], ci[1]["b"][0]) < run3.params["b"] < min(ci[0]["b"][1],
                                                                      ci[1]["b"][1])


@needs_data
def test_real_traces_succeed_with_what_eq3_lacks_named():
    """Issue 36, item 4: on real traces the exact model's structured residuals are the model's
    (the search of its starts finds no lower cost and settles there), so spring run 1 (by
    default: the ansatz answers for eq. 3, b and D only) and the 100 deg torsion release (by
    default: the exact model answers; its frequency follows its amplitude so strongly that
    the model halts 13 s before the data) succeed, adequate False with the structure and the
    early halt named (runs 1-2 jointly: tests/fit/test_joint.py); run 2 agrees with the exact
    model's fit that issue 36 quotes. Both windows pad to 12,288
    samples: they share their compiled programs. Run 1's values agree with an independent fit
    (scipy least_squares on solve_ivp DOP853, tuned: b 0.0053608 kg/s, D 0.025342 kg/m, w0
    8.44685 rad/s; benchmarks/README.md) within a quarter of their interval sd."""
    osc = dp.Oscillator(m=0.2016, k=14.91945)
    single = fit(load_trace(DATA / "spring_mass_airdrag" / "run1.csv"), oscillator=osc,
                 free=("b", "D"), fit_omega0=True)
    torsion = fit(load_trace(DATA / "torsion_pendulum_friction" / "release_100deg.txt",
                             rate="auto"), free=("mu", "b"))
    assert single.model == "ansatz" and torsion.model == "reference"
    for res in (single, torsion):
        assert res.success and not res.adequate, res.reason
        assert any("structure that eq. 3 with these terms lacks" in s and "settled" in s
                   for s in res.inadequacy), res.inadequacy
        assert "cubic stiffness" in " ".join(res.inadequacy)  # its frequency follows A
    assert any("stops moving" in s and "the optimum stands" in s for s in torsion.inadequacy)
    sd = single.hac_stderr
    for name, scipy_value in (("b", 0.0053608), ("D", 0.025342), ("w0", 8.44685)):
        assert abs(single.params[name] - scipy_value) < 0.25 * sd[name], (name, sd[name])
    # item 6: run 2 by default holds the exact model's values of issue 36 (model="reference",
    # b 0.00548 kg/s, D 0.0247 kg/m) inside its 95 % intervals (its programs are run 1's)
    run2 = fit(load_trace(DATA / "spring_mass_airdrag" / "run2.csv"), oscillator=osc,
               free=("b", "D"), fit_omega0=True)
    ci = run2.conf_interval(0.95)
    assert run2.success and ci["b"][0] < 0.00548 < ci["b"][1] and ci["D"][0] < 0.0247 < ci["D"][1]


@needs_data
def test_torsion_release_60_friction():
    trace = load_trace(DATA / "torsion_pendulum_friction" / "release_60deg.txt",
                       time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    ranking = compare_models(trace, fit_omega0=True, model="ansatz")
    assert ranking.best.success
    assert "mu" in ranking.best.free  # a friction model first
    assert [row["free"] for row in ranking.table][0] == ranking.ranking[0]
    res = ranking.results[("mu", "b")]
    assert res.success and res.rms < 1.0  # degrees
    assert res.params["mu"] > 5 * res.stderr["mu"] and res.params["b"] > 5 * res.stderr["b"]
    # this record begins in free motion (at 52 deg, swinging to -35, 50, -33, ...: its first
    # half swing fits as well as the next ones), so nothing is skipped; the 70 deg record
    # begins with the hold and the lead-in of the hand release, which are
    assert res.t_start == trace.t[0]
    held = load_trace(DATA / "torsion_pendulum_friction" / "release_70deg.txt",
                      time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    from dampax._fit._analysis import analyse, start_index

    i = start_index(held.t, held.x, analyse(held.t, held.x), "auto")
    assert held.x[i] < held.x[0] - 30.0  # past the release (the hold sits at 54 deg)
    text = ranking.report()
    assert "Model ranking by BIC" in text and "the data support" in text


@needs_data
def test_pendulum_maxima_envelope_ranks_drag_first():
    peaks = load_trace(DATA / "pendulum_airdrag" / "AAAtopPts.txt")
    ranking = compare_envelope_models(peaks.t, peaks.x)
    assert ranking.best.success and "D" in ranking.best.free
    assert ranking.table[0]["delta"] == 0.0
    best = ranking.best
    assert best.kind == "envelope" and best.rms < 0.003  # rad
    assert best.params["D"] > 10 * best.stderr["D"]
    single = fit_envelope(peaks.t, peaks.x, free=("D",))
    assert single.success and single.params["D"] > 0


# ----------------------------------------------------------------------------------------------
# the reference model (compiles the diffrax integrator inside the optimizer: the heavy test)


@pytest.mark.slow
def test_reference_model_on_the_example_trace():
    trace, truth = example_trace()
    assert isinstance(trace, Trace) and len(trace) == 5000
    osc = dp.Oscillator(m=truth["m"], k=truth["k"])
    res = fit(trace, oscillator=osc, free=("mu", "D"), model="reference")
    assert res.success, res.message
    assert "started from the ansatz fit" in res.message
    for name in ("mu", "D"):
        assert abs(res.params[name] - truth[name]) < 3 * res.stderr[name]
        assert abs(res.params[name] / truth[name] - 1) < 0.05
    assert res.rms == pytest.approx(truth["noise"], rel=0.1)


# ----------------------------------------------------------------------------------------------
# issue 11: identifiable defaults, global starts, named failures, intervals


def test_per_unit_mass_default_and_units(synthetic):
    """Without an oscillator w0 is fitted and the fit is per unit mass: D/m = 0.1 1/m for the
    synthetic truth D = 0.02 kg/m, m = 0.2 kg; mu (a deceleration over g) is unchanged."""
    t, x, known = synthetic
    res = fit(t, x, free=("mu", "D"), window=dp.Window(start="data"), model="ansatz")
    assert res.success and res.adequate and res.per_mass, res.reason
    assert res.varied == ["mu", "D", "w0", "offset", "x0", "v0"]
    truth = {"mu": TRUTH["mu"], "D": TRUTH["D"] / M, "w0": math.sqrt(K / M)}
    for name, value in truth.items():
        assert abs(res.params[name] - value) < 3 * res.stderr[name], (name, res.params[name])
    # the same optimum as with the known mass, rescaled by m
    assert res.params["D"] == pytest.approx(known.params["D"] / M, rel=1e-5)
    assert res.params["mu"] == pytest.approx(known.params["mu"], rel=1e-5)
    assert res.derived["D/m"] == res.params["D"] and res.derived["mu_g"] > 0
    text = res.report()
    assert "per unit mass" in text and "1/m (D/m, per unit mass)" in text
    assert "kg/m" not in text and "kg/s" not in text
    known_text = known.report()
    assert "kg/m" in known_text and "per unit mass" not in known_text
    deg = fit(t, x * 100.0, free=("mu", "D"), window=dp.Window(start="data", units="deg"),
              model="ansatz")
    text = deg.report()
    assert "1/deg (D/m, per unit mass)" in text and "deg/s^2" in text and "kg/" not in text
    assert deg.to_dict()["units"] == "deg" and deg.to_dict()["per_mass"] is True


def test_global_starts_reach_the_optimum_of_an_independent_multistart(synthetic):
    from scipy.optimize import least_squares

    t, x, res = synthetic
    assert res.starts is not None and res.starts.n == 32
    assert 1 <= res.starts.reached <= 32 and np.isfinite(res.starts.costs).sum() >= 16
    assert "jittered starts reached the best optimum" in res.report()
    # numpy / scipy multi-start on the same residuals: 6 log-uniform starts of mu, D over
    # two decades each side of the truth, from the data's offset, phase and frequency
    fun, jac, names = residual_function(t, x, free=("mu", "D"), oscillator=KNOWN,
                                        fit_omega0=True)
    rng = np.random.default_rng(3)
    best = math.inf
    for _ in range(6):
        start = np.array([TRUTH["mu"] * 10 ** rng.uniform(-2, 2),
                          TRUTH["D"] * 10 ** rng.uniform(-2, 2), res.init["w0"],
                          res.init["offset"], res.init["x0"], res.init["v0"]])
        sol = least_squares(fun, start, jac=jac, x_scale="jac", max_nfev=100,
                            bounds=([0, 0, 0, -np.inf, -np.inf, -np.inf], np.inf))
        best = min(best, sol.cost)
    ours = 0.5 * np.sum(fun(np.array([res.params[n] for n in names])) ** 2)
    assert ours <= best * (1 + 1e-7)


def _undamped(n=N):
    t = np.arange(n) / RATE
    noise = NOISE * np.random.default_rng(2).standard_normal(n)
    return t, OFFSET + X0 * np.cos(math.sqrt(K / M) * t) + noise


@pytest.mark.parametrize("case, reason", [
    ("constant", "the trace is constant"),
    ("noise", "no free oscillation"),
    ("growing", "the amplitude grows"),
    ("reversed", "the amplitude grows"),
    ("constant time", "constant time"),
    # 1.6 periods: fitted, and refused with the true reason (issue 25: no longer for being
    # short, which a trace that halts after one swing is too)
    ("short", "mu and D are not separately identifiable"),
])
def test_degenerate_input_raises_a_named_value_error(case, reason):
    t, x = ansatz_trace(2048)
    rng = np.random.default_rng(1)
    data = {"constant": (t, np.full_like(t, 0.4)),
            "noise": (t, rng.standard_normal(t.size)),
            "growing": (t, OFFSET + (x - OFFSET) * np.exp(0.1 * t)),
            "reversed": (t, x[::-1]),
            "constant time": (np.full_like(t, 3.0), x),
            "short": (t[:120], x[:120])}[case]
    with pytest.raises(ValueError, match=reason):
        fit(*data, free=("mu", "D"), model="ansatz")


def test_a_short_motion_in_a_long_noisy_record_is_not_refused_as_noise():
    """A block that halts after one swing in the first 6 % of 10,486 samples, at a noise of
    7 % of its start (fit_calibration.py --wide, seed 9, draw 6; scipy's integrator): within
    its samples' noise excursions, far above those of their means over 16 or 64 samples. Pure
    white noise of the same length and sd stays refused at every scale (20 seeds)."""
    from dampax._fit._analysis import analyse
    from dampax._fit._checks import check_trace

    m, k, mu, b, D = 0.46415, 8.92949, 0.06507, 1.52448, 9.09016
    t = np.linspace(0.0, 6.63504, 10486)
    seg, _, rest = scipy_stick_slip(m, k, mu, b, D, 0.05005, -0.21979, t[-1] + 1e-9)
    assert rest is not None and rest[0] < 0.06 * t[-1] and len(seg) == 1
    clean = evaluate(seg, rest, t)[0] + 0.01541
    rng = np.random.default_rng(986696436)
    x = clean + 0.00511 * rng.standard_normal(t.size)
    check_trace(t, x, analyse(t, x))  # no ValueError
    for seed in range(20):
        z = 0.00511 * np.random.default_rng(seed).standard_normal(t.size)
        with pytest.raises(ValueError, match="no free oscillation above the noise"):
            check_trace(t, z, analyse(t, z))


def test_a_decay_sampled_a_few_times_per_period_is_not_refused_as_noise():
    """50 samples over 10 s of a 0.7255 s period (3.6 per period, above Nyquist's 2), with
    noise of 1 % of the start and without (scipy's integrator): the k-th differences grow as
    (2 sin(w dt / 2))^k > 1 there, so they measured the signal as noise of 0.8 of its
    amplitude and the trace was refused as "no free oscillation above the noise". The noise
    now comes within a factor 2 of the truth (the prediction error of an AR(2)), the trace
    passes, and pure white noise of 50 samples stays refused (20 seeds)."""
    from dampax._fit._analysis import analyse
    from dampax._fit._checks import check_trace

    t = np.linspace(0.0, 10.0, 50)
    seg, _, rest = scipy_stick_slip(0.2, 15.0, 0.002, 0.0, 0.02, 0.1, 0.0, t[-1] + 1e-9)
    clean = evaluate(seg, rest, t)[0]
    for sd in (0.0, 0.001):
        x = clean + sd * np.random.default_rng(1).standard_normal(t.size)
        an = analyse(t, x, omega0=math.sqrt(15.0 / 0.2))
        assert an.noise < max(2.0 * sd, 0.005), an.noise  # 0.043 before
        check_trace(t, x, an)  # no ValueError
    for seed in range(20):
        z = 0.01 * np.random.default_rng(seed).standard_normal(t.size)
        with pytest.raises(ValueError, match="no free oscillation above the noise"):
            check_trace(t, z, analyse(t, z))


def test_the_auto_window_does_not_start_at_a_noise_extreme_after_an_early_halt():
    """A block that halts at its first turning point (0.31 s of a 1.02 s record, cubic spring)
    under AR(1) noise of 7 % of its amplitude (fit_calibration.py --wide, seed 13, draw 49;
    scipy's integrator): the scan's only turning point is a noise extreme at 0.87 s, and the
    auto window started there, at pure noise, which the fit then refused as "no free
    oscillation above the noise". The window starts at the first sample now, and the trace
    passes the check; the samples after that extreme alone are still refused."""
    from dampax._fit._analysis import analyse
    from dampax._fit._checks import check_trace

    m, k, k3, mu, b = 0.137553, 13.173966, 8.607054, 0.550942, 0.753224
    t = np.linspace(0.0, 1.0241599, 18326)
    seg, _, rest = scipy_stick_slip(m, k, mu, b, 0.0, 0.219384, -0.352069, t[-1] + 1e-9,
                                    k3=k3)
    assert rest is not None and rest[0] < 0.31 * t[-1] and len(seg) == 1
    z = np.random.default_rng(1322487171).standard_normal(t.size)
    e, phi = np.empty(t.size), 0.428481
    e[0] = z[0]
    for i in range(1, t.size):
        e[i] = phi * e[i - 1] + math.sqrt(1.0 - phi * phi) * z[i]
    x = evaluate(seg, rest, t)[0] + 0.002919 + 0.015566 * e
    whole = analyse(t, x)
    assert whole.n_turns == 1 and whole.ext_t[0] > 0.8  # the noise extreme
    an = analyse(t, x, window=("auto", None))
    assert an.window[0] == 0, t[an.window[0]]
    check_trace(t, x, an)  # no ValueError
    tail = t >= whole.ext_t[0]
    with pytest.raises(ValueError, match="no free oscillation above the noise"):
        check_trace(t[tail], x[tail], analyse(t[tail], x[tail]))


def test_the_sinusoid_scan_finds_the_frequency_it_was_made_with():
    """The analysis's least-squares sinusoid scan (for traces with fewer than three turning
    points), batched by the normal equations, against the frequency of a trace made in its
    own model family (a linearly shrinking sinusoid on an offset, 2.5 half periods, 2 % noise,
    random sample times): within 3 % (its coarse grid steps 2.2 %, the fine one 0.1 %).
    Coincident times (a singular block) give a frequency, not an error."""
    from dampax._fit._analysis import _search_band, _sinusoid_frequency

    rng = np.random.default_rng(7)
    for w in (1.3, 4.0, 11.0, 30.0):
        T = 2.5 * np.pi / w
        t = np.sort(rng.uniform(0.0, T, 3000))
        y = (1 - 0.3 * t / T) * np.cos(w * t + 0.4) + 0.2 + 0.02 * rng.standard_normal(t.size)
        got = _sinusoid_frequency(t, y, *_search_band(T, float(np.median(np.diff(t)))))
        assert abs(got / w - 1) < 0.03, (w, got)
    # (the fine grid reaches 3 % beyond the band)
    assert 0.1 / 1.03 <= _sinusoid_frequency(np.zeros(16), rng.standard_normal(16), 0.1, 1.0) \
        <= 1.03


def test_named_failures_undamped_and_max_steps(synthetic):
    t, x = _undamped()
    res = fit(t, x, free=("mu", "D"), window=dp.Window(start="data"), model="ansatz")
    # no decay to measure: a right answer (intervals from 0), named in a note, not a failure
    assert res.success, res.reason
    assert "[[Note]] no measurable decay" in res.report()
    assert res.diagnostics["decay_wald"] >= 0.0  # a quadratic form (rounding gave -7e-21)
    ci = res.conf_interval(0.99)
    assert ci["mu"][0] == 0.0 and ci["D"][0] == 0.0
    t, x, _ = synthetic
    res = fit(t, x, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True,
              window=dp.Window(start="data"), solver=dp.LeastSquares(max_steps=1, starts=1),
              model="ansatz")
    assert not res.success and not res.converged and res.n_iterations <= 1
    assert "did not converge" in res.reason and "maximum number of steps" in res.reason


def test_covariance_of_nearly_collinear_columns_does_not_depend_on_the_last_bits():
    """Damping constants at 0 have Jacobian columns that agree to ~1e-8 (the undamped trace
    above): cond(J^T J) ~ 1e16, and inverting J^T J gave a variance of either sign by the last
    bits of the data (issue 34, a GPU's verdict). The delta-method covariance comes from the
    singular values of J: positive, and equal to a QR solution's whatever the last bits."""
    from dampax._fit._core import _covariance

    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((2, 4000))
    J = np.stack([a, a + 1e-8 * b, rng.standard_normal(4000)], axis=1)
    r = np.linalg.qr(J / np.linalg.norm(J, axis=0), mode="r")
    inv_r = np.linalg.inv(r)
    truth = np.sqrt(np.sum(inv_r * inv_r, axis=1)) / np.linalg.norm(J, axis=0)
    cov = jax.jit(lambda J: _covariance(J, lambda th: th, jnp.zeros(3), jnp.ones(3, bool), 1.0))
    for k in range(4):  # the columns moved by up to k ulp
        Jk = J + np.spacing(J) * rng.integers(-k, k + 1, J.shape)
        stderr = np.asarray(cov(Jk)[1])
        np.testing.assert_allclose(stderr, truth, rtol=1e-6)


def test_ranking_by_statistics_leaves_out_fits_without_an_optimum(synthetic):
    """issue 36: a fit whose verdict fails (a check of its residuals or intervals) is still its
    model's optimum and is ranked by its criterion; a fit that reached no optimum is left out."""
    import dataclasses

    from dampax._fit._result import rank

    _, _, res = synthetic
    broken = dataclasses.replace(res, success=False, converged=False,
                                 reason="the optimizer did not converge", bic=res.bic - 100.0,
                                 free=("D",))
    ranking = rank({("mu", "D"): res, ("D",): broken}, "bic")
    assert ranking.ranking == [("mu", "D")] and list(ranking.failed) == [("D",)]
    assert ranking.best is res
    assert "left out (no optimum): D: the optimizer did not converge" in ranking.report()
    judged = dataclasses.replace(res, success=False, reason="the residuals are not noise",
                                 bic=res.bic - 100.0, free=("D",))
    both = rank({("mu", "D"): res, ("D",): judged}, "bic")
    assert both.ranking == [("D",), ("mu", "D")] and not both.failed
    assert "ranked, but its verdict failed: D: the residuals are not noise" in both.report()
    none = rank({("D",): broken}, "bic")
    assert none.best is None and "no candidate fit reached an optimum" in none.report()


def test_conf_interval_covers_and_widens_for_correlated_noise(synthetic):
    t, x, res = synthetic
    ci = res.conf_interval(0.95)
    assert set(ci) == set(res.varied)
    truth = {"mu": TRUTH["mu"], "D": TRUTH["D"], "w0": math.sqrt(K / M), "offset": OFFSET}
    for name, value in truth.items():
        lo, hi = ci[name]
        assert lo < value < hi, (name, lo, value, hi)
        # white noise: the HAC sd is the delta-method stderr, within its sampling error
        assert res.hac_stderr[name] == pytest.approx(res.stderr[name], rel=0.35), name
    assert "[[Intervals]] 95 %" in res.report()
    for level in (1.5, "0.9", None, True):  # (a text or None raised numpy's TypeError)
        with pytest.raises(ValueError, match="level must be a number in"):
            res.conf_interval(level)
    # AR(1) noise (coefficient 0.9): the HAC sd exceed the delta-method stderr ~3-4 times
    e = np.zeros(N)
    z = np.random.default_rng(4).standard_normal(N) * NOISE * math.sqrt(1 - 0.81)
    for i in range(1, N):
        e[i] = 0.9 * e[i - 1] + z[i]
    red = fit(t, x - (x - ansatz_trace(N, noise=0.0)[1]) + e, oscillator=KNOWN, free=("mu", "D"),
              fit_omega0=True, window=dp.Window(start="data"), model="ansatz")
    for name in ("mu", "D"):
        assert 2.0 < red.hac_stderr[name] / red.stderr[name] < 6.0, name


def test_cli_help_documents_every_option():
    import argparse

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for action in parser._actions:
        assert action.help and action.help != argparse.SUPPRESS, action.option_strings
    text = parser.format_help()
    for needle in ("exit status", "per unit mass", "--units", "--intervals", "--posterior",
                   "--starts", "--g", "--model", "--optimizer"):
        assert needle in text, needle


def test_cli_per_mass_and_exit_status(tmp_path, capsys, monkeypatch):
    from dampax import _cli

    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    t, x = ansatz_trace(N)
    path = tmp_path / "trace.csv"
    path.write_text("time;position\n" + "".join(f"{a:.4f};{b:.6f}\n"
                                                for a, b in zip(t, x, strict=True)))
    out = tmp_path / "out"
    assert _cli.main(["fit", "--model", "ansatz",
                      str(path), "--free", "mu,D", "--no-compare", "--intervals",
                      "--start", "data", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "per unit mass" in text and "confidence intervals at 0.95" in text
    summary = json.loads((out / "fit.json").read_text())
    assert summary["fit"]["per_mass"] and summary["fit"]["success"]
    assert abs(summary["fit"]["params"]["D"] / (TRUTH["D"] / M) - 1) < 0.05
    assert set(summary["fit"]["conf_interval"]["intervals"]) >= {"mu", "D"}
    # a failed fit: exit status 3, the reason on stderr and first in the report
    assert _cli.main(["fit", "--model", "ansatz",
                      str(path), "--m", str(M), "--k", str(K), "--fit-omega0",
                      "--start", "data", "--no-compare", "--max-steps", "1", "--starts", "1",
                      "--out", str(out)]) == 3
    captured = capsys.readouterr()
    assert "FIT FAILED: the optimizer did not converge" in captured.out
    assert "fit failed" in captured.err
    # degenerate input: one line, status 2, no traceback
    flat = tmp_path / "flat.csv"
    flat.write_text("time;position\n" + "".join(f"{a:.4f};0.4\n" for a in t[:500]))
    assert _cli.main(["fit", str(flat), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "the trace is constant" in err and "Traceback" not in err
    assert _cli.main(["fit", str(path), "--k", "15", "--out", str(out)]) == 2
    assert "--k needs --m" in capsys.readouterr().err


@needs_data
def test_torsion_releases_reach_their_best_optimum():
    """Every release, per unit mass with Coulomb + viscous damping: the global starts agree
    and the rms is the best the constant-frequency model allows (benchmarks/README.md, issue
    11); 100 deg is named a failure: the model halts ~13 s before the data stop swinging."""
    # (60 and 80 deg move from their first sample: their first half swing is fitted too)
    rms = {60: 0.683, 70: 1.007, 80: 0.502, 90: 1.186, 100: 4.349}  # deg
    for deg, expected in rms.items():
        trace = load_trace(DATA / "torsion_pendulum_friction" / f"release_{deg}deg.txt",
                           time=1, position=2, rate="auto")
        res = fit(trace, free=("mu", "b"), model="ansatz")
        assert res.units == "deg" and res.per_mass
        assert res.rms == pytest.approx(expected, rel=0.01), (deg, res.rms)
        assert res.starts.reached >= res.starts.n // 2, (deg, res.starts.summary())
        if deg < 100:
            assert res.success and res.adequate, (deg, res.reason, res.inadequacy)
        else:
            assert not res.success and not res.adequate
            assert "stops moving" in res.reason and "before the data" in res.reason
            assert res.report().startswith("FIT FAILED: the model stops moving")


def test_inadequate_model_is_named_and_exits_with_status_4(tmp_path, capsys, monkeypatch):
    """A decay whose frequency rises 1.5 % over the window (as the torsion releases'): the fit
    converges, but its residuals are 40 times the noise and 18 % of the amplitude (a phase
    drift of 1.3 rad): adequate is False, the report says so, ``dampax fit`` exits with
    status 4."""
    from dampax import _cli

    t = np.arange(N) / RATE
    w = math.sqrt(K / M) * (1.0 + 0.015 * t / t[-1])
    x = OFFSET + X0 * np.exp(-0.01 * t) * np.cos(np.cumsum(w) / RATE)
    x = x + NOISE * np.random.default_rng(6).standard_normal(N)
    res = fit(t, x, free=("b",), window=dp.Window(start="data"), model="ansatz")
    assert res.success, res.reason
    assert not res.adequate and any("times the noise level" in s for s in res.inadequacy)
    assert res.diagnostics["phase_drift"] > 1.0 and res.diagnostics["rms/A"] > 0.1
    assert "MODEL DOES NOT DESCRIBE THE DATA: " in res.report().splitlines()[0]
    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    path = tmp_path / "chirp.csv"
    path.write_text("".join(f"{a:.4f} {b:.6f}\n" for a, b in zip(t, x, strict=True)))
    assert _cli.main(["fit", "--model", "ansatz",
                      str(path), "--free", "b", "--start", "data", "--no-compare",
                      "--starts", "8", "--out", str(tmp_path / "out")]) == 4
    assert "does not describe the data" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# issue 25, item 1: checks that hold in general (traces of an independent scipy integrator)

ISSUE25 = [(0.04, 3.0), (0.03, 2.0), (0.035, 2.8), (0.04, 0.5), (0.01, 3.0)]


@pytest.mark.parametrize("mu, D", ISSUE25)
def test_issue25_strongly_damped_traces_fit_with_the_truth_inside(mu, D):
    """The table of issue 25: m = 1 kg, k = 30 N/m, x0 = 0.2 m at rest, 3 s at 500 Hz, white
    noise of 1 mm, oscillator given, free mu and D, the reference model. The block halts after
    two to four swings (the first three were refused as "pure noise", the fourth failed on the
    zero-crossing frequency that friction moves): each fits, with the truth inside its 99 %
    intervals."""
    t, x = _issue25_trace(mu, 0.0, D)
    res = fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=("mu", "D"), model="reference")
    assert res.success, res.reason
    ci = res.conf_interval(0.99)
    for name, value in (("mu", mu), ("D", D)):
        assert ci[name][0] < value < ci[name][1], (name, value, ci[name])
    assert "zero-crossing" not in res.report()


def test_an_overdamped_trace_fits_with_the_truth_inside():
    """Viscous damping twice the critical (b = 4 sqrt(k m)): eq. 3 holds, but the ansatz's
    oscillation (and the amplitude and phase matched to the start, eqs. 22-23) does not exist.
    The exact model fits it, with the truth inside its 99 % intervals, and the derived
    amplitude and phase are the start's undamped ones (x0 = A cos(phi), v0 = -w0 A sin(phi));
    the fit failed before on "the fitted amplitude or frequency is not a positive finite
    number" with the truth inside."""
    b = 4.0 * math.sqrt(30.0)
    t, x = _issue25_trace(0.0, b, 0.0)
    res = fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=("b", "D"))
    assert res.success and res.model == "reference", res.reason
    lo, hi = res.conf_interval(0.99)["b"]
    assert lo < b < hi and res.conf_interval(0.99)["D"][0] <= 0.0
    p, w0 = res.params, math.sqrt(30.0)
    assert res.derived["A"] == pytest.approx(math.hypot(p["x0"], p["v0"] / w0), rel=1e-12)
    assert res.derived["A"] * math.cos(res.derived["phi"]) == pytest.approx(p["x0"], rel=1e-12)


def test_the_absurd_check_of_the_exact_model_reads_the_start_amplitude():
    """The check that fails a parameter run to absurd values (a damping ratio above 10)
    reads, for the exact model, the amplitude of its fitted start, hypot(x0, v0/w0): the
    ansatz matched to a start under strong drag (eqs. 22-23) can have an amplitude many
    times the motion's. The fitted constants and matched amplitude (1.38) of draw 23 of
    ``fit_calibration.py --wide --seed 7`` (per unit mass, d2 A0/w0 = 1.1), which failed on
    "d2 A/w0 = 15.5" with its residuals at the noise and the truth inside, with a start of
    amplitude 0.14 (its own was not recorded; A0 = 0.095): eq. 21 by hand gives d2 A/w0 =
    1.6 at the start's amplitude."""
    from dampax._fit._assess import Inputs, Verdict, absurd

    w0, mu, b, D, x0, v0 = 2.4611, 0.0208, 1.683, 26.38, -0.0818, -0.28
    d0, d1, d2 = 2 * mu * 9.81 / (math.pi * w0), b / 2, 4 * D * w0 / (3 * math.pi)  # eq. 21
    start = math.hypot(x0, v0 / w0)
    assert d2 * start / w0 < 10 < d2 * 1.38 / w0
    t = np.linspace(0.0, 6.0, 50)
    kw = dict(t=t, x=0.1 * np.cos(w0 * t), curve=None, stderr={}, varied=("mu", "b", "D"),
              params=dict(mu=mu, b=b, D=D, w0=w0, x0=x0, v0=v0, offset=0.0), an=None,
              derived=dict(d0=d0, d1=d1, d2=d2, A=1.38), converged=True, message="")
    none = Verdict((), (), {})
    found = absurd(Inputs(model="reference", **kw), none)
    assert found.fails == () and found.diag["d2 A/w0"] == pytest.approx(d2 * start / w0)
    (reason,) = absurd(Inputs(model="ansatz", **kw), none).fails  # the ansatz's own amplitude
    assert "d2 A/w0 = 15" in reason, reason


def _issue25_trace(mu, b, D):
    """The issue 25 set-up (m = 1 kg, k = 30 N/m, x0 = 0.2 m at rest, 3 s at 500 Hz, 1 mm
    white noise) from the independent scipy integrator with exact stick-slip."""
    from helpers import evaluate, scipy_stick_slip

    t = np.arange(0.0, 3.0, 1.0 / 500.0)
    segments, _, rest = scipy_stick_slip(1.0, 30.0, mu, b, D, 0.2, 0.0, 3.0, rtol=1e-11,
                                         atol=1e-13)
    return t, evaluate(segments, rest, t)[0] + 1e-3 * np.random.default_rng(0).standard_normal(
        t.size)


@pytest.mark.parametrize("mu, b, D, answers", [(0.02, 0.0, 0.5, "reference"),
                                               (0.0, 0.05, 0.0, "ansatz")])
def test_the_default_fit_answers_with_the_exact_model(mu, b, D, answers):
    """Issue 36: dp.fit's default ("auto") gives the exact model's values and intervals:
    with Coulomb friction and drag the ansatz's optimum is biased by several interval sd, so
    eq. 3 integrated answers; with viscous damping alone the ansatz is eq. 3's own solution
    and answers (one Gauss-Newton step of the exact model would move nothing). Either way
    the truth lies inside the 99 % intervals and the result says which model answered."""
    t, x = _issue25_trace(mu, b, D)
    truth = {n: v for n, v in (("mu", mu), ("b", b), ("D", D)) if v > 0}
    res = fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=tuple(truth))
    assert res.success and res.model == answers, (res.model, res.reason)
    assert f"the {'exact model (eq. 3)' if answers == 'reference' else 'ansatz'} answers" in \
        res.message
    assert res.adequate, res.inadequacy  # eq. 3 is the truth here: noise is all it leaves
    ci = res.conf_interval(0.99)
    for name, value in truth.items():
        assert ci[name][0] < value < ci[name][1], (name, value, ci[name])


def test_a_trace_without_decay_is_not_searched_as_a_local_optimum():
    """An undamped motion (scipy's integrator, mu = b = D = 0) fitted for mu and D by the
    default call: the exact model's optimizer creeps along eq. 3's kink at mu = D = 0 until
    its step budget runs out on a flat valley, which the assessment accepts as converged; it
    is no sign of a local optimum, so no batch of the exact model's starts is run (it found
    no lower cost and cost 2-5 s). The answer: no measurable decay, intervals from 0."""
    t, x = _issue25_trace(0.0, 0.0, 0.0)
    res = fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=("mu", "D"))
    assert res.success and res.model == "reference", res.reason
    assert "jittered starts of the reference model" not in res.message, res.message
    assert "[[Note]] no measurable decay" in res.report()
    ci = res.conf_interval(0.99)
    assert ci["mu"][0] == 0.0 and ci["D"][0] == 0.0
    # the motion keeps its amplitude to the noise: upper bounds far below the damping of the
    # test above (mu 0.02, D 0.5), which the same window measures
    assert ci["mu"][1] < 0.005 and ci["D"][1] < 0.1, ci


def test_a_constant_the_data_lack_settles_at_its_bound(monkeypatch):
    """mu and D (scipy's integrator), fitted with b free too: b's optimum is its bound, 0.
    The exact model's fit and the profile's held refits crept toward it until their step
    budget ran out (256 steps each: 15,000 samples over 200 periods took 60 s, 9.6 s now),
    and the capped fit ran a batch of 30 starts that found nothing. They now stop where they
    creep and restart at the bound (``Problem.solve(settle=...)``): no fit of the exact
    model runs out of steps, no batch runs, and the truth lies inside the 99 % intervals."""
    from dampax._fit import _problem

    steps, solve = [], _problem.Problem.solve

    def counted(self, *args, **kwargs):
        out = solve(self, *args, **kwargs)
        if args[1] == "reference":
            steps.append(int(out.out.steps))
        return out

    monkeypatch.setattr(_problem.Problem, "solve", counted)
    t, x = _issue25_trace(0.02, 0.0, 0.5)
    res = fit(t, x, oscillator=dp.Oscillator(m=1, k=30), free=("mu", "b", "D"))
    assert res.success and res.model == "reference", res.reason
    assert "jittered starts" not in res.message and "continued" not in res.message
    budget = _problem.MAX_STEPS["lm"]
    assert steps and max(steps) < budget, (steps, budget, res.message)
    ci = res.conf_interval(0.99)
    for name, value in (("mu", 0.02), ("b", 0.0), ("D", 0.5)):
        assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


def test_a_constant_settled_at_its_bound_keeps_a_standard_error(benchmark_module):
    """Draw 38 of fit_calibration.py seed 44 (per unit mass, mu, b and D free, mu's truth 0;
    scipy's integrator): settled at mu's bound, where the clamp leaves its Jacobian column 0,
    the fit failed "the standard error of mu is not finite". Its statistics are taken one
    unit above the bound: a success, mu's 99 % interval from 0 holding the truth, and b, D
    inside theirs."""
    cal = benchmark_module("fit_calibration")
    spec = cal.traces("reference", 39, 44)[0][38]
    assert spec["mu"] == 0.0 and spec["free"] == ("mu", "b", "D") and not spec["given"]
    t, x = cal.simulate(spec)
    res = fit(t, x, free=spec["free"])
    assert res.success, res.reason
    assert math.isfinite(res.stderr["mu"]) and res.stderr["mu"] > 0
    ci = res.conf_interval(0.99)
    assert ci["mu"][0] == 0.0 < ci["mu"][1]
    for name in ("b", "D"):
        assert ci[name][0] <= spec[name] / spec["m"] <= ci[name][1], (name, ci[name])


def test_a_failed_search_goes_on_at_the_bound():
    """Quadratic drag with a little friction, four swings to a halt in a 15.6 s record, fitted
    per unit mass with mu, b and D free (fit_calibration.py --wide, seed 13, draw 33, at 8,192
    samples; scipy's integrator): the search settled on b 0.35 with D 2.4 times the truth, at
    2.7 times the truth's cost, and failed ("the residuals are not noise: a local optimum").
    Its tests at the bound need noise-like residuals, so the search now goes on there: with b
    held at 0 the cost is lower, the fit continues from there (b at its bound), then searches
    its neighbouring halts again, and reaches the truth's cost: a success, the truth inside
    its 99 % intervals."""
    m, k, mu, D = 0.29468585, 1.58093699, 0.00223224, 3.79648233
    t = np.linspace(0.0, 15.624786, 8192)
    seg, _, rest = scipy_stick_slip(m, k, mu, 0.0, D, 0.00187784, -0.45354324, t[-1] + 1e-9,
                                    rtol=1e-11, atol=1e-13)
    clean = evaluate(seg, rest, t)[0] + 0.08425612
    x = clean + 3.519e-4 * np.random.default_rng(1).standard_normal(t.size)
    res = fit(t, x, free=("mu", "b", "D"))
    assert res.success, res.reason
    assert "with b held at 0 the cost was lower" in res.message, res.message
    assert np.sum(res.residuals ** 2) <= np.sum((x - clean) ** 2)  # the truth's cost, or less
    ci = res.conf_interval(0.99)
    for name, value in (("mu", mu), ("b", 0.0), ("D", D / m), ("w0", math.sqrt(k / m))):
        assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


@pytest.mark.parametrize("seed", [3, 11])
def test_a_failed_search_goes_on_around_its_optimum(seed):
    """Coulomb, viscous and quadratic damping, three swings to a halt in a 13.5 s record, m
    and k given (fit_calibration.py --wide, seed 15, draw 23, at 8,192 samples; scipy's
    integrator): with these two noise draws the search stopped 4-8 % above the truth's cost
    with structured residuals and failed as a local optimum. Where no constant held at 0
    costs less, a batch of the exact model's starts around that optimum now finds the lower
    one: a success at the truth's cost, the truth inside the 99 % intervals. (The outcome is
    checked, not the path: where rounding leads the first search to that optimum, so much
    the better. The programs are those of the test above: the same length and budget.)"""
    m, k, mu, b, D = (0.688796033867291, 5.056415462940492, 0.002873406060234811,
                      0.3930501811954637, 12.296345709215224)
    t = np.linspace(0.0, 13.544916158423005, 8192)
    seg, _, rest = scipy_stick_slip(m, k, mu, b, D, 0.1014656209054682, 0.16858019473758476,
                                    t[-1] + 1e-9, rtol=1e-11, atol=1e-13)
    clean = evaluate(seg, rest, t)[0] - 0.0049239600123297325
    x = clean + 0.0007343012444295956 * np.random.default_rng(seed).standard_normal(t.size)
    res = fit(t, x, oscillator=dp.Oscillator(m=m, k=k), free=("mu", "b", "D"))
    assert res.success, res.reason
    assert np.sum(res.residuals ** 2) <= np.sum((x - clean) ** 2)
    ci = res.conf_interval(0.99)
    for name, value in (("mu", mu), ("b", b), ("D", D)):
        assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


def test_a_search_around_its_optimum_moves_a_constant_off_its_bound():
    """Coulomb, viscous and quadratic damping, four swings to a halt at 1.7 s of a 13.8 s
    record, fitted per unit mass with mu, b and D free (fit_calibration.py seed 22, draw 84's
    constants; scipy's integrator, this noise draw): the search stopped with b at its bound
    (4e-9) and D 1.3x the truth, 53 noise variances above the truth's cost, and failed as a
    local optimum. Holding b at 0 then cost "less" by rounding (1e-14), which ended the search;
    and a batch jittered around b = 4e-9 (factors of exp(1.5 z)) never left the bound. Now a
    hold must lower the cost by more than a step that decides nothing, and the batch's b starts
    from its share of the decay (``_profile.shared_start``): a success at the truth's cost."""
    m, k, mu, b, D = 0.41146989, 23.734123, 0.0014429114, 0.62239227, 44.460886
    t = np.linspace(0.0, 13.842677, 1473)
    seg, _, rest = scipy_stick_slip(m, k, mu, b, D, -0.010383672, 0.026266177, t[-1] + 1e-9,
                                    rtol=1e-11, atol=1e-13)
    clean = evaluate(seg, rest, t)[0] + 0.0038283888
    x = clean + 1.5470638e-4 * np.random.default_rng(4).standard_normal(t.size)
    res = fit(t, x, free=("mu", "b", "D"))
    assert res.success, res.reason
    assert np.sum(res.residuals ** 2) <= np.sum((x - clean) ** 2)
    ci = res.conf_interval(0.99)
    for name, value in (("mu", mu), ("b", b / m), ("D", D / m), ("w0", math.sqrt(k / m))):
        assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


def test_a_motion_halting_nearby_that_fits_nearly_as_well_widens_mu(benchmark_module):
    """Coulomb, viscous and quadratic damping over 32 half swings to a halt, fitted with m and
    k given and mu, b, D free (fit_calibration.py seed 22, draw 114: scipy's integrator with
    exact stick-slip): the optimum, mu 0.01688 with interval sd 0.0007, has a neighbour that
    halts one turning point later at mu 0.01499, 2.7 sd away at likelihood-ratio chi2 6.46 <
    6.63; the fit failed "two motions fit nearly as well" though the truth (0.01723) lay
    inside its intervals. mu's profile rises smoothly through that halt (the public fit with
    mu held: chi2 2.8, 5.1, 8.0 at 1.7, 2.4, 3.0 sd below): it is now followed out to a held
    fit above the 1 % point and the intervals widened to reach the other motion (profile
    likelihood): a success with the truth inside the 99 % intervals."""
    cal = benchmark_module("fit_calibration")
    spec = dict(m=0.14543223460207944, k=6.068320198345227, mu=0.01723489538731935,
                b=0.13719582474050698, D=5.447820895950984, k3=0.0, x0=-0.015783203787687952,
                v0=-0.1956313476414964, offset=0.025135858163960932,
                noise=0.00013942350620892914, phi=0.0, span=15.418215236032308, n=1256,
                noise_seed=2086549052)
    t, x = cal.simulate(spec)
    res = fit(t, x, oscillator=dp.Oscillator(m=spec["m"], k=spec["k"]), free=("mu", "b", "D"))
    assert res.success, res.reason
    assert "note_other_halt" in res.diagnostics
    ci = res.conf_interval(0.99)
    assert ci["mu"][0] <= 0.01499  # the other motion inside mu's interval
    for name in ("mu", "b", "D"):
        assert ci[name][0] <= spec[name] <= ci[name][1], (name, spec[name], ci[name])


def test_issue25_generated_family_sample(benchmark_module):
    """A fixed-seed sample of the generated family (benchmarks/fit_calibration.py: scipy DOP853
    with exact stick-slip, random damping ratios, phase, AR(1) or white noise, windows of a few
    swings, w0 given or fitted), fitted as a user would: no refusal without a true reason, no
    failure of a right fit, no confident wrong answer."""
    cal = benchmark_module("fit_calibration")
    rng = np.random.default_rng(25)
    picked = []
    while len(picked) < 3:  # short windows, linear spring: the programs of the test above
        spec = cal.draw(rng)
        if spec["half_swings"] <= 5.0 and spec["k3"] == 0.0:
            picked.append(spec)
    for spec in picked:
        t, x = cal.simulate(spec)
        rec = cal.run_case(spec, t, x, "reference", max_swings=None)
        rec.pop("_res", None)
        assert rec["status"] != "refused", rec.get("error")
        assert not rec["confident_wrong"], rec
        assert not rec["false_failure"], rec


def test_distribution_functions_equal_scipy_stats():
    """dampax._fit._dist (scipy.special, no scipy.stats import on the fit's path) against
    scipy.stats over the arguments the checks use."""
    from scipy import stats

    from dampax._fit import _dist

    for p in (1e-6, 0.005, 0.05, 0.5, 0.95, 0.999):
        assert _dist.norm_ppf(p) == pytest.approx(stats.norm.ppf(p), rel=1e-12, abs=1e-12)
    for k in (1, 2, 3, 7, 150, 600):
        for x in (0.0, 0.3, 2.0, k, 3.0 * k + 10.0):
            assert _dist.chi2_sf(x, k) == pytest.approx(stats.chi2.sf(x, k), rel=1e-10,
                                                        abs=1e-300)
        for p in (0.01, 0.05, 0.5):
            assert _dist.chi2_isf(p, k) == pytest.approx(stats.chi2.isf(p, k), rel=1e-10)
    for d1, d2 in ((3.7, 120.5), (40.0, 2000.0), (1.0, 8.0)):
        for x in (0.0, 0.5, 1.0, 2.5, 10.0):
            assert _dist.f_sf(x, d1, d2) == pytest.approx(stats.f.sf(x, d1, d2), rel=1e-10,
                                                          abs=1e-300)
    # the closed forms of integer k (every check's) over a denser set, the tails included,
    # and scipy.special behind a k that is not an integer
    for k in (*range(1, 31), 75, 301, 1999):
        for x in (1e-9, 0.5 * k, k + 3.0 * math.sqrt(2.0 * k), 5.0 * k + 50.0, 1400.0):
            assert _dist.chi2_sf(x, k) == pytest.approx(stats.chi2.sf(x, k), rel=1e-11,
                                                        abs=1e-300)
        for p in (1e-12, 1e-6, 0.001, 0.01, 0.05, 0.5, 0.9):
            assert _dist.chi2_isf(p, k) == pytest.approx(stats.chi2.isf(p, k), rel=1e-11)
    for k in (0.5, 2.5, 7.25):
        assert _dist.chi2_sf(3.2, k) == pytest.approx(stats.chi2.sf(3.2, k), rel=1e-12)
        assert _dist.chi2_isf(0.05, k) == pytest.approx(stats.chi2.isf(0.05, k), rel=1e-10)


def test_the_checks_chi_square_needs_no_scipy_import():
    """The chi-square of integer degrees of freedom (every check's) imports no scipy module:
    scipy.special took a tenth of a second of the first fit's critical path (issue 36)."""
    code = ("import sys; from dampax._fit import _dist; _dist.chi2_sf(12.5, 9); "
            "_dist.chi2_isf(0.05, 3); print(sorted(m for m in sys.modules if "
            "m.startswith('scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == "[]", out.stdout


def test_collinear_damping_constants_no_crash_truth_inside_or_named(benchmark_module):
    """Draw 71 of the generated family's ansatz part (7 swings fading into 80 s, per unit mass):
    at the optimum the batch of starts used to pick the Jacobian's columns of mu and b cancel
    exactly and nothing else takes part: the fit crashed with StopIteration, then named the
    pair. The batch now takes the start of less than half the cost (a converged start had
    stopped at a stationary point above it): a fit with the truth (per unit mass) inside its
    99 % intervals; a refusal must still name the pair."""
    cal = benchmark_module("fit_calibration")
    spec = dict(m=0.12761251161962178, k=1.6130472964426226, mu=0.0014224739747641655,
                b=0.053917411224241256, D=0.9700329642297716, k3=0.0,
                x0=-0.07921651611736243, v0=0.1506794349947874, offset=-0.05122024099373079,
                noise=0.0024437569832596725, phi=0.0, span=81.40487382929874, n=2998,
                noise_seed=1504832035)
    t, x = cal.simulate(spec)
    try:
        res = fit(t, x, free=("mu", "b", "D"), model="ansatz")
    except ValueError as err:
        assert "mu and b are not separately identifiable" in str(err)
        return
    assert res.success, res.reason
    ci = res.conf_interval(0.99)
    truth = {"mu": spec["mu"], "b": spec["b"] / spec["m"], "D": spec["D"] / spec["m"]}
    for name, value in truth.items():
        assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


def test_two_swings_with_two_optima_fail_with_the_reason(benchmark_module):
    """Draw 125 of the generated family (2 swings, AR(1) noise phi = 0.53, free mu and b, w0
    fitted), from its first turning point on (where the window started before a record that
    moves from its first sample kept its first half swing): the least-squares optimum halts
    one turning point later than the truth, with mu 22 interval sd off; the truth's motion
    costs more (the noise prefers the other). The fit finds the motion that halts at the
    truth's turning point, which fits nearly as well, and fails with that reason instead of a
    confident wrong answer. The whole record (the default window now) settles it: success,
    the truth inside the 99 % intervals."""
    cal = benchmark_module("fit_calibration")
    spec = dict(m=3.9487683026199956, k=18.404073353633393, mu=0.006694468208940884,
                b=1.3420153648176687, D=0.0, k3=0.0, x0=-0.007420987492392991,
                v0=-0.12879634536655088, offset=0.012813652961777442,
                noise=0.0001153023673501254, phi=0.5297550982206217, span=3.8470327015659804,
                n=2992, noise_seed=994447306)
    t, x = cal.simulate(spec)
    whole = fit(t, x, free=("mu", "b"), model="reference")
    assert whole.success and whole.t_start == t[0], whole.reason
    for name, truth in (("mu", spec["mu"]), ("b", spec["b"] / spec["m"])):  # per unit mass
        lo, hi = whole.conf_interval(0.99)[name]
        assert lo <= truth <= hi
    res = fit(t, x, free=("mu", "b"), model="reference", window=dp.Window(start=0.5209))
    lo, hi = res.conf_interval(0.99)["mu"]
    assert not lo <= spec["mu"] <= hi  # the optimum is the wrong one ...
    assert not res.success and "two motions fit nearly as well" in res.reason, res.reason
    other = res.diagnostics["other_halt_mu"]  # ... and the other one is named
    assert abs(other - spec["mu"]) < abs(res.params["mu"] - spec["mu"])


@pytest.mark.parametrize("power, scale", [(2, 3.0), (4, 2.5), (1, 5.0), (3, 7.0)])
def test_profile_side_finds_where_the_cost_reaches_the_interval(power, scale):
    """_profile.profile_side on exact profiles rise(d) = (d / (scale d0))^power: the side ends
    where the rise reaches 1, at d = scale d0 (effective c = 1/scale^2); a flat profile is
    unbounded (0: the fit fails), one that reaches the parameter's bound ends there."""
    from dampax._fit._profile import PROFILE_FAIL, profile_side

    d0 = 0.7

    def rise(d):
        return (d / (scale * d0)) ** power

    c = profile_side(rise, d0, rise(d0))
    # a power law is found exactly (the steps follow the power law through the last points)
    assert c == pytest.approx(1.0 / scale ** 2, rel=1e-9)
    assert c >= PROFILE_FAIL
    assert profile_side(lambda d: 1e-4 * d, d0, 1e-4 * d0) == 0.0
    beyond = 9.0  # beyond PROFILE_REACH = 8: not measured, the fit fails
    assert profile_side(lambda d: (d / (beyond * d0)) ** 2, d0, beyond ** -2) == 0.0
    limit = 2.0 * d0  # a damping constant 2 d0 above 0: the side reaches 0
    assert profile_side(rise, d0, rise(d0), limit=limit) == pytest.approx(0.25)
    assert profile_side(rise, d0, 0.5) == 0.5  # measured by one point: unchanged


@pytest.mark.parametrize("width", [3.0, 1.5, 4.0])
def test_a_neighbouring_halt_is_followed_to_the_profiles_bound(width):
    """_profile.followed_out on an exact profile of mu, rise(d) = (d / width)^2 (d in interval
    sd from the fit: a profile width times as wide as the linearised intervals assume), from
    a held fit 3 sd up below the 1 % point (a motion that halts at a neighbouring turning
    point): followed out until a held fit rises above chi2(1) = 6.63, and the intervals
    widened to reach those below it reach the profile-likelihood 99 % bound, width * 2.576
    sd, exactly (a quadratic profile; 4 times as wide takes FOLLOW_EVALS held fits). A profile
    that stays flat, one with a lower cost, and one with a first halt above mu are not
    bounded (the fit fails: two answers), nor one bounded only by a held fit of the search
    (an upper bound of the profile: seed 0 draw 134); a lower side that reaches mu = 0 below
    the 1 % point is bounded there."""
    from dampax._fit._profile import (
        FOLLOW_EVALS,
        LR_CHI2,
        LR_Z,
        Optimum,
        followed_out,
        widen,
    )

    mu, sd = 40.0, 1.0
    calls = []

    def profile(rise, first=False):
        def held(m, near=None):
            calls.append(m)
            return rise(abs(m - mu) / sd), first and m > mu, {"mu": m}
        return held

    quad = profile(lambda d: (d / width) ** 2)
    rises = {mu + 3.0 * sd: quad(mu + 3.0 * sd)}
    assert followed_out(rises, mu, sd, quad)
    above = [m for m, r in rises.items() if r[0] >= LR_CHI2]
    assert len(above) == 1 and all(m > mu for m in rises)
    scale = {}
    fitted = Optimum({"mu": mu}, {"mu": sd}, {"mu": sd}, 0.0, 1.0)
    widen(scale, fitted, [(r[0], r[2]) for r in rises.values() if r[0] < LR_CHI2])
    side = LR_Z * sd * scale.get("mu", (1.0, 1.0))[1]
    assert side == pytest.approx(max(width, 1.0) * LR_Z * sd, rel=1e-12)
    calls.clear()  # flat: FOLLOW_EVALS held fits, still below
    flat = profile(lambda d: 0.2)
    assert not followed_out({mu + 3.0: flat(mu + 3.0)}, mu, sd, flat)
    assert len(calls) == FOLLOW_EVALS + 1
    calls.clear()  # a held fit of the search far out and high bounds nothing (from above)
    far = {mu + 3.0: flat(mu + 3.0), mu + 14.0: (216.0, False, {"mu": mu + 14.0})}
    assert not followed_out(far, mu, sd, flat)
    assert len(calls) == FOLLOW_EVALS + 1
    lower = profile(lambda d: -0.5 if d > 4.0 else 0.1)
    assert not followed_out({mu + 3.0: lower(mu + 3.0)}, mu, sd, lower)
    first = profile(lambda d: 1.0, first=True)
    assert not followed_out({mu + 3.0: first(mu + 3.0)}, mu, sd, first)
    mu = 5.0  # 5 sd above 0: the lower side reaches 0 at chi2 25 / 9 < 6.63
    near0 = profile(lambda d: (d / 3.0) ** 2)
    rises = {mu - 3.0: near0(mu - 3.0)}
    assert followed_out(rises, mu, sd, near0) and 0.0 in rises


def test_transferred_start_keeps_the_decay_rate():
    """_profile.transferred_start: the held constant's decay rate at A/2 (eq. 21's envelope
    dA/dt = -(d0 + d1 A + d2 A^2)) is split equally among the others."""
    from dampax._fit._profile import transferred_start

    scale, A = {"mu": 2.4, "b": 0.5, "D": 1.1}, 0.46
    params = {"mu": 0.01, "b": 3.0, "D": 0.2}
    start = transferred_start("b", params, ("mu", "b", "D"), scale, A)
    a = 0.5 * A
    moved = 0.5 * params["b"] * scale["b"] * a
    assert (start["mu"] - params["mu"]) * scale["mu"] == pytest.approx(moved, rel=1e-14)
    assert (start["D"] - params["D"]) * scale["D"] * a * a == pytest.approx(moved, rel=1e-14)
    assert transferred_start("b", params, ("b",), scale, A) is None


def test_fit_options_are_objects_checked_when_made():
    """dp.fit takes at most 10 keyword options (issue 27): the problem's keywords, and the
    window and optimiser settings as dp.Window / dp.LeastSquares, which check their fields
    when made (a ValueError naming the field) and are immutable."""
    import inspect

    keywords = [p.name for p in inspect.signature(dp.fit).parameters.values()
                if p.kind is inspect.Parameter.KEYWORD_ONLY]
    assert len(keywords) <= 10 and {"window", "solver"} <= set(keywords), keywords
    for bad, field in [(lambda: dp.Window(start="later"), "Window.start"),
                       (lambda: dp.Window(start=2.0, end=1.0), "Window.end"),
                       (lambda: dp.Window(units=" "), "Window.units"),
                       (lambda: dp.LeastSquares(rtol=0.0), "LeastSquares.rtol"),
                       (lambda: dp.LeastSquares(starts=2.5), "LeastSquares.starts"),
                       (lambda: dp.LeastSquares(max_swings=0), "LeastSquares.max_swings"),
                       (lambda: dp.LeastSquares(p0=[1.0]), "LeastSquares.p0"),
                       (lambda: dp.LeastSquares(optimizer="newton"),
                        "LeastSquares.optimizer")]:
        with pytest.raises(ValueError, match=field.replace(".", r"\.")):
            bad()  # refused when made (issue 37), not later
    with pytest.raises(ValueError, match="window must be a dp.Window"):
        dp.fit(np.arange(20.0), np.zeros(20), window={"start": "data"}, model="ansatz")
    with pytest.raises(AttributeError):
        dp.Window().start = 1.0  # immutable
    ok = dp.LeastSquares(starts=np.int64(8), p0={"mu": 0.1}).checked()
    assert ok.starts == 8 and isinstance(ok.starts, int) and ok.p0 == {"mu": 0.1}


def test_an_envelope_fit_of_turning_points_takes_w0_from_the_oscillator_or_their_signs():
    """fit_envelope's omega0: the oscillator's sqrt(k/m) (k was not used), else from the
    spacing of the extremes, half a period apart where their signs alternate (mu and D came
    out twice and half the truth from turning points of both signs). Against the truth of the
    reference's own turning points."""
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.005, D=0.5)
    sol = dp.solve(osc, 0.2, 0.0, method="reference")
    tp, xp = (np.asarray(a) for a in dp.turning_points(sol, 30))
    ok = np.isfinite(tp)
    for kw, (t, x) in ((dict(oscillator=dp.Oscillator(m=1.0, k=30.0)), (tp[ok], xp[ok])),
                       ({}, (tp[ok], xp[ok])), ({}, (tp[ok][::2], xp[ok][::2]))):
        res = dp.fit_envelope(t, x, **kw)
        assert res.params["mu"] == pytest.approx(0.005, rel=1e-3), kw
        assert res.params["D"] == pytest.approx(0.5, rel=1e-3), kw
