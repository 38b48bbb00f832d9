"""Fitting damping constants (dampax._fit): synthetic truth, coverage, scipy agreement, real data.

Compilation dominates the run time (10-30 s per compiled fit on 2 cores), so the tests share
shapes: the synthetic trace has 8192 samples, the same padded length as the torsion file, and
fit() pads every trace to a power of two.
"""

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

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

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
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
    res = fit(t, x, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True, start="data")
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
    np.testing.assert_allclose(np.asarray(core.params),
                               [res.params[p] for p in PARAMS], rtol=1e-7, atol=1e-12)
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
    kw = dict(oscillator=KNOWN, free=("mu", "D"), fit_omega0=True, start="data")
    linear = fit(t, bad, **kw)
    robust = fit(t, bad, loss="soft_l1", **kw)
    assert robust.success and robust.loss == "soft_l1"
    assert robust.f_scale == pytest.approx(NOISE, rel=0.5)  # MAD of the residuals
    for name in ("mu", "D"):
        err = clean.stderr[name]
        assert abs(robust.params[name] - TRUTH[name]) < 4 * err
        assert abs(robust.params[name] - TRUTH[name]) < abs(linear.params[name] - TRUTH[name])
        assert robust.stderr[name] < linear.stderr[name]


def test_constant_not_in_the_data_goes_to_zero_gracefully(synthetic):
    t, x, _ = synthetic
    res = fit(t, x, oscillator=KNOWN, free=("mu", "b", "D"), fit_omega0=True, start="data")
    assert res.success, res.message
    assert res.params["b"] < 3 * res.stderr["b"] and math.isfinite(res.stderr["b"])
    for name in ("mu", "D"):
        assert abs(res.params[name] - TRUTH[name]) < 3 * res.stderr[name]


@pytest.mark.parametrize("optimizer, tol", [("lbfgs", 1e-4), ("adam", 0.02)])
def test_optax_optimizers_reach_the_lm_optimum(synthetic, optimizer, tol):
    t, x, lm = synthetic
    res = fit(t, x, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True, start="data",
              optimizer=optimizer)
    assert res.success, res.message
    for name in ("mu", "D"):
        assert res.params[name] == pytest.approx(lm.params[name], rel=tol)
    assert res.chisqr == pytest.approx(lm.chisqr, rel=10 * tol)


def test_auto_start_skips_the_release():
    # a hand release: the block is held off centre, pushed out, then swings freely
    t, x = ansatz_trace(6000)
    hold = np.full(300, x[0] - 0.01)
    ramp = np.linspace(x[0] - 0.01, x[0], 100)
    tt = np.arange(400 + t.size) / RATE
    xx = np.concatenate([hold, ramp, x])
    res = fit(tt, xx, oscillator=KNOWN, free=("mu", "D"), fit_omega0=True)
    w0 = math.sqrt(K / M)
    # the first extreme after the largest excursion: half a period after the release
    assert res.t_start == pytest.approx(4.0 + math.pi / w0, abs=0.02)
    for name in ("mu", "D"):
        assert abs(res.params[name] - TRUTH[name]) < 3 * res.stderr[name]


def test_input_errors():
    t, x = ansatz_trace(64)
    with pytest.raises(ValueError, match="free must name"):
        fit(t, x, free=("mu", "c"))
    with pytest.raises(ValueError, match="model must be"):
        fit(t, x, model="exact")
    with pytest.raises(ValueError, match="loss must be"):
        fit(t, x, loss="huber")
    with pytest.raises(ValueError, match="at least 10"):
        fit(t[:5], x[:5])
    with pytest.raises(ValueError, match="same length"):
        fit(t, x[:-1])
    with pytest.raises(ValueError, match="p0: unknown"):
        fit(t, x, p0={"k": 1.0})
    with pytest.raises(ValueError, match="sets free itself"):
        compare_models((t, x), free=("mu",))


def test_cli(tmp_path, capsys, monkeypatch):
    import argparse

    from dampax import _cli

    t, x = ansatz_trace(N)
    path = tmp_path / "trace.csv"
    rows = "".join(f"{a:.4f};{b:.6f}\r\n" for a, b in zip(t, x, strict=True))
    path.write_text("time;position\r\n" + rows)
    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    out = tmp_path / "out"
    assert _cli.main(["fit", str(path), "--m", str(M), "--k", str(K), "--fit-omega0",
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
    args = parser.parse_args([str(path), "--rate", "fast"])
    with pytest.raises(ValueError, match="--rate"):
        run(args)


# ----------------------------------------------------------------------------------------------
# real data


@needs_data
def test_spring_runs_1_and_2_agree():
    osc = dp.Oscillator(m=0.2016, k=14.91945)
    fits = [fit(load_trace(DATA / "spring_mass_airdrag" / f"run{i}.csv"), oscillator=osc,
                free=("b", "D"), fit_omega0=True) for i in (1, 2)]
    for res in fits:
        assert res.success, res.message
        assert 8.40 < res.params["w0"] < 8.50 < math.sqrt(14.91945 / 0.2016)  # spring mass
        assert res.rms < 0.004  # m, on a 7 cm swing
    for name in ("b", "D"):
        a, b = fits[0].params[name], fits[1].params[name]
        assert abs(a - b) / (0.5 * (a + b)) < 0.10, (name, a, b)


@needs_data
def test_torsion_release_60_friction():
    trace = load_trace(DATA / "torsion_pendulum_friction" / "release_60deg.txt",
                       time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    ranking = compare_models(trace, fit_omega0=True)
    assert ranking.best.success
    assert "mu" in ranking.best.free  # a friction model first
    assert [row["free"] for row in ranking.table][0] == ranking.ranking[0]
    res = ranking.results[("mu", "b")]
    assert res.success and res.rms < 1.0  # degrees
    assert res.params["mu"] > 5 * res.stderr["mu"] and res.params["b"] > 5 * res.stderr["b"]
    assert res.t_start > trace.t[0]  # the release is skipped
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
