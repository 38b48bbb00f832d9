"""The posterior (issue 25, item 4): NUTS with blackjax's window adaptation vmapped over chains,
the ansatz and the reference model, posterior.nc as ArviZ InferenceData, R-hat and ESS as ArviZ
computes them.

One synthetic trace with known truth, from an independent scipy integration of eq. 3 with exact
stick-slip (tests/helpers.py): m = 1 kg, k = 30 N/m, x0 = 0.2 m at rest, mu = 0.01, D = 0.5
kg/m, 3 s at 250 Hz, white noise 1 mm. The ansatz posterior (2 chains, 150 warm-up steps, 200
draws) is sampled once per module; the command line samples the same shapes and settings, so
it reuses the compiled program.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers import evaluate, scipy_stick_slip

import dampax as dp
from dampax._cli.fit import add_arguments, run
from dampax._fit._mcmc import GROUPS, ess_bulk, ess_tail, rhat

az = pytest.importorskip("arviz")

M, K, MU, D, X0, NOISE = 1.0, 30.0, 0.01, 0.5, 0.2, 1e-3
OSC = dp.Oscillator(m=M, k=K)
DRAWS = dict(num_samples=200, num_chains=2, num_warmup=150)
POSTERIOR_VARS = {"mu", "D", "offset", "x0", "v0", "sigma", "phi_noise"}


@pytest.fixture(scope="module")
def trace():
    segments, _, rest = scipy_stick_slip(M, K, MU, 0.0, D, X0, 0.0, 3.0)
    t = np.arange(750) / 250.0
    x = evaluate(segments, rest, t)[0] + NOISE * np.random.default_rng(0).standard_normal(t.size)
    return t, x


@pytest.fixture(scope="module")
def post(trace):
    t, x = trace
    return dp.posterior(t, x, oscillator=OSC, free=("mu", "D"), start="data", seed=1,
                        model="ansatz", **DRAWS)


def test_posterior_covers_the_truth(post):
    """The 95 % intervals of mu, D and the noise sd hold the truth, the chains agree, no
    divergences; w0 (known) is not sampled but recorded; v0 is the ansatz's at (x0, y)."""
    s = post.summary(0.95)
    assert set(s) == POSTERIOR_VARS
    for name, value in (("mu", MU), ("D", D), ("sigma", NOISE), ("x0", X0)):
        assert s[name]["lo"] < value < s[name]["hi"], (name, s[name])
    for name, row in s.items():
        assert row["r_hat"] < 1.05 and row["ess_bulk"] > 100 and row["ess_tail"] > 50, (name, row)
    assert post.divergences == 0 and 0.6 < post.accept_rate < 0.99
    # white noise, the model right: the posterior sd is the fit's HAC sd within the scatter
    # of the two estimates, far from too narrow (issue 36: _posterior.NARROW)
    hac = post.fit.hac_stderr
    ratios = {name: s[name]["sd"] / hac[name] for name in ("mu", "D")}
    print("posterior sd / HAC sd:", ratios, "stride", post.stride)
    assert all(0.75 < r < 2.0 for r in ratios.values()), ratios
    assert post.narrow == {} and "narrower" not in post.report()
    assert post.draws.attrs["fixed_w0"] == pytest.approx(math.sqrt(K / M))
    assert post.draws.attrs["fixed_b"] == 0.0 and post.draws.attrs["fixed_m"] == M
    rep = post.report()
    assert rep.startswith("[[Posterior]] NUTS (blackjax, window adaptation), ansatz model")


def test_posterior_file_opens_in_arviz(post, trace, tmp_path):
    """posterior.nc is InferenceData: posterior (the sampled parameters, (chain, draw)),
    sample_stats (ArviZ's names) and observed_data (the window: x over t)."""
    path = post.to_netcdf(tmp_path / "posterior.nc")
    idata = az.from_netcdf(path)
    assert set(idata.groups()) == set(GROUPS)
    assert set(idata.posterior.data_vars) == POSTERIOR_VARS
    assert idata.posterior["mu"].dims == ("chain", "draw")
    assert idata.posterior["mu"].shape == (2, 200)
    np.testing.assert_array_equal(idata.posterior["D"].values, post.draws["D"].values)
    assert idata.posterior.attrs["fixed_w0"] == pytest.approx(math.sqrt(K / M))
    stats = idata.sample_stats
    assert {"diverging", "energy", "step_size", "tree_depth", "acceptance_rate",
            "lp"} <= set(stats.data_vars)
    assert stats["diverging"].dtype == bool and stats["tree_depth"].dtype.kind == "i"
    assert np.all(np.isfinite(stats["lp"])) and np.all(stats["step_size"] > 0)
    # one step size per chain (each chain adapts its own)
    assert np.all(stats["step_size"].values == stats["step_size"].values[:, :1])
    t, x = trace
    np.testing.assert_array_equal(idata.observed_data["t"].values, t)
    np.testing.assert_array_equal(idata.observed_data["x"].values, x)
    # ArviZ's own summary works on it, with our numbers
    table = az.summary(idata, var_names=["mu", "D"], round_to="none")
    s = post.summary()
    for name in ("mu", "D"):
        assert table.loc[name, "r_hat"] == pytest.approx(s[name]["r_hat"], abs=1e-8)
        assert table.loc[name, "ess_bulk"] == pytest.approx(s[name]["ess_bulk"], rel=1e-8)


def test_summary_matches_arviz(post):
    """summary()'s R-hat and bulk / tail ESS are arviz.rhat and arviz.ess on the same draws."""
    s = post.summary()
    for name in POSTERIOR_VARS:
        a = post.draws[name].values
        assert s[name]["r_hat"] == pytest.approx(float(az.rhat(a)), abs=1e-8), name
        assert s[name]["ess_bulk"] == pytest.approx(float(az.ess(a)), rel=1e-8), name
        assert s[name]["ess_tail"] == pytest.approx(float(az.ess(a, method="tail")),
                                                    rel=1e-8), name


@pytest.mark.parametrize("shape", [(4, 101), (3, 7), (2, 64)])
def test_rhat_and_ess_match_arviz_on_awkward_shapes(shape):
    """Odd chain lengths (the middle draw dropped by the split), few draws, ties, a stuck
    chain: the same numbers as ArviZ."""
    rng = np.random.default_rng(sum(shape))
    a = np.cumsum(rng.standard_normal(shape), axis=1) * 0.3 + rng.standard_normal(shape)
    a[0, : shape[1] // 3] = a[0, 0]  # ties
    assert rhat(a) == pytest.approx(float(az.rhat(a)), abs=1e-8)
    assert ess_bulk(a) == pytest.approx(float(az.ess(a)), rel=1e-8)
    assert ess_tail(a) == pytest.approx(float(az.ess(a, method="tail")), rel=1e-8)
    assert math.isnan(rhat(a[:1]))  # one chain: no R-hat
    with pytest.raises(ValueError, match="draws must have shape"):
        rhat(a[0])


@pytest.mark.slow
def test_reference_posterior(trace, post):
    """model="reference": the log density through the reference integrator (forward-mode
    gradient); its intervals hold the truth and agree with the ansatz's."""
    t, x = trace
    ref = dp.posterior(t, x, oscillator=OSC, free=("mu", "D"), model="reference",
                       start="data", seed=2, num_samples=60, num_chains=2, num_warmup=60)
    s, sa = ref.summary(0.95), post.summary(0.95)
    assert ref.model == "reference" and ref.fit.model == "reference"
    for name, value in (("mu", MU), ("D", D), ("sigma", NOISE)):
        assert s[name]["lo"] < value < s[name]["hi"], (name, s[name])
        assert s[name]["r_hat"] < 1.1, (name, s[name])
        assert abs(s[name]["mean"] - sa[name]["mean"]) < 0.5 * (sa[name]["hi"] - sa[name]["lo"])
    assert ref.divergences <= 2 and "reference model" in ref.report()


def test_posterior_arguments(trace, post):
    t, x = trace
    with pytest.raises(ValueError, match="num_samples"):
        dp.posterior(t, x, num_samples=1, model="ansatz")
    with pytest.raises(ValueError, match="model"):
        dp.posterior(t, x, model="envelope")
    with pytest.raises(ValueError, match="start_fit must be a 'reference' fit"):
        dp.posterior(t, x, oscillator=OSC, model="reference", start_fit=post.fit)


def test_cli_posterior_writes_inference_data(trace, tmp_path, capsys, monkeypatch):
    """dampax fit --posterior writes posterior.nc that ArviZ opens, and the summary with
    R-hat and ESS in fit.json."""
    from dampax import _cli

    t, x = trace
    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    csv = tmp_path / "trace.csv"
    csv.write_text("time;position\n" + "".join(f"{a:.4f};{b:.8f}\n"
                                               for a, b in zip(t, x, strict=True)))
    out = tmp_path / "out"
    assert _cli.main(["fit", "--model", "ansatz",
                      str(csv), "--m", "1", "--k", "30", "--free", "mu,D",
                      "--start", "data", "--no-compare", "--posterior", "--draws", "200",
                      "--chains", "2", "--warmup", "150", "--seed", "3",
                      "--out", str(out)]) == 0
    assert "[[Posterior]]" in capsys.readouterr().out
    idata = az.from_netcdf(out / "posterior.nc")
    assert set(idata.groups()) == set(GROUPS) and idata.posterior["D"].shape == (2, 200)
    summary = json.loads((out / "fit.json").read_text())["posterior"]
    assert summary["D"]["lo"] < D < summary["D"]["hi"]
    assert summary["D"]["r_hat"] == pytest.approx(float(az.rhat(idata.posterior["D"].values)),
                                                  abs=1e-8)
    assert (out / "corner.png").read_bytes()[:4] == b"\x89PNG"


def test_a_posterior_narrower_than_the_fit_intervals_is_named(post):
    """Where the AR(1) noise model is too simple for the residuals (structure at the
    oscillation frequency, as spring run 1's), the posterior of a constant comes out narrower
    than the fit's HAC interval: named per parameter (damping constants, w0, k3), in the
    report, under a threshold (_posterior.NARROW) below the ratio of a right model (above)."""
    from types import SimpleNamespace

    from dampax._fit._posterior import NARROW, narrow_parameters
    from dampax._fit._posterior_result import narrow_text

    sd = {name: float(post.draws[name].std(ddof=1)) for name in ("mu", "D", "x0")}
    wide = SimpleNamespace(hac_stderr={"mu": 20.0 * sd["mu"], "D": sd["D"], "x0": 50 * sd["x0"]})
    found = narrow_parameters(post.draws, wide)
    assert set(found) == {"mu"} and found["mu"] == pytest.approx(0.05)  # x0: not a constant
    assert narrow_parameters(post.draws, SimpleNamespace(
        hac_stderr={"mu": sd["mu"] / (1.01 * NARROW), "D": math.nan})) == {}
    assert "mu 20x" in narrow_text(found) and "conf_interval" in narrow_text(found)


def test_laplace_hessian_by_differences_of_the_gradient():
    """The chains' Laplace preconditioner: the Hessian by central differences of the compiled
    gradient equals the exact Hessian of a non-quadratic density (independent: its analytic
    second derivatives), at scales from 1e-3 to 1e3 in the coordinates."""
    import jax
    import jax.numpy as jnp

    from dampax._fit._sampler import _neg_hessian

    scale = jnp.array([1e-3, 1.0, 1e3])

    def neg_log(th):
        u = th / scale
        return jnp.sum(u**2) + 0.1 * u[0] ** 4 + u[0] * u[1] + jnp.cosh(u[2] - 0.3)

    theta = np.array([2e-4, -0.7, 800.0])
    got = _neg_hessian(lambda th: np.asarray(jax.grad(neg_log)(jnp.asarray(th))), theta)
    u = theta / np.asarray(scale)
    exact = np.diag([2 + 1.2 * u[0] ** 2, 2.0, 2 + np.cosh(u[2] - 0.3)])
    exact[0, 1] = exact[1, 0] = 1.0
    exact = exact / np.outer(scale, scale)
    np.testing.assert_allclose(got, exact, rtol=1e-6, atol=1e-9 * np.abs(exact).max())
