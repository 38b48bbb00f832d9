"""dampax.global_sensitivity: Sobol' S1, ST with bootstrap half-widths, and DGSM.

Checked against independent numbers: Ishigami's analytic indices and mean squared derivatives;
SALib's own sampler and sobol.analyze on the oscillator (within the confidence half-widths) and
on the same outputs (the same estimators: equal to rounding); central finite differences of
dampax.solve for the DGSM gradients; the matched ansatz against the reference (slow: the
reference compiles for ~20 s). Bad input raises ValueError naming the argument; the CLI prints
the table and draws the bars.
"""

import argparse
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from SALib.analyze import sobol as salib_sobol
from SALib.sample import sobol as salib_sample

import dampax as dp
from dampax._cli.sensitivity import add_arguments, run
from dampax._studies._global import sobol_indices

OSC = dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=1.0)
BOUNDS = {"mu": (0.01, 0.05), "D": (0.5, 3.0), "x0": (0.15, 0.25)}

# Ishigami, a = 7, b = 0.1 on [-pi, pi]^3 (Ishigami & Homma 1990; Saltelli et al. 2008)
A_ISH, B_ISH = 7.0, 0.1
S1_ISH = np.array([0.3139, 0.4424, 0.0])
ST_ISH = np.array([0.5576, 0.4424, 0.2437])
# mean squared derivatives, by hand: E[cos^2 x1] E[(1 + b x3^4)^2], E[(a sin 2 x2)^2],
# E[(4 b x3^3 sin x1)^2], with E[x^4] = pi^4/5, E[x^6] = pi^6/7, E[x^8] = pi^8/9 on U(-pi, pi)
NU_ISH = np.array([0.5 * (1 + 2 * B_ISH * math.pi**4 / 5 + B_ISH**2 * math.pi**8 / 9),
                   A_ISH**2 / 2, 8 * B_ISH**2 * math.pi**6 / 7])
VAR_ISH = A_ISH**2 / 8 + B_ISH * math.pi**4 / 5 + B_ISH**2 * math.pi**8 / 18 + 0.5


def ishigami(p):
    return jnp.sin(p[0]) + A_ISH * jnp.sin(p[1]) ** 2 + B_ISH * p[2] ** 4 * jnp.sin(p[0])


@pytest.fixture(scope="module")
def ish():
    return sobol_indices(ishigami, [-math.pi] * 3, [math.pi] * 3, ["x1", "x2", "x3"], n=4096,
                         seed=0)


def test_ishigami_published_indices(ish):
    S1, ST = ish.S1.values, ish.ST.values
    S1c, STc = ish.S1_conf.values, ish.ST_conf.values
    # within the 95 % half-widths, and those are a few hundredths at n = 4096
    assert np.all(np.abs(S1 - S1_ISH) <= S1c) and np.all(np.abs(ST - ST_ISH) <= STc)
    assert np.all(S1c < 0.05) and np.all(STc < 0.05)
    assert np.max(np.abs(S1 - S1_ISH)) < 0.01 and np.max(np.abs(ST - ST_ISH)) < 0.01
    np.testing.assert_allclose(ish.attrs["variance"], VAR_ISH, rtol=0.01)
    # DGSM: mean squared autodiff derivatives against the analytic ones; the bound ST <= DGSM
    np.testing.assert_allclose(ish.nu.values, NU_ISH, rtol=0.02)
    np.testing.assert_allclose(ish.DGSM.values,
                               NU_ISH * (2 * math.pi) ** 2 / (math.pi**2 * VAR_ISH), rtol=0.03)
    assert np.all(ST <= ish.DGSM.values)
    assert ish.sizes["sample"] == 4096 * 5 and list(ish.parameter.values) == ["x1", "x2", "x3"]


def test_same_outputs_give_salib_indices(ish):
    # the design is in SALib's row order: SALib's analyze on our outputs, same estimators
    problem = dict(num_vars=3, names=["x1", "x2", "x3"], bounds=[[-math.pi, math.pi]] * 3)
    si = salib_sobol.analyze(problem, ish.Y.values, calc_second_order=False, seed=3)
    np.testing.assert_allclose(ish.S1.values, si["S1"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ish.ST.values, si["ST"], rtol=1e-9, atol=1e-12)
    # bootstrap half-widths: other draws, same spread
    np.testing.assert_allclose(ish.S1_conf.values, si["S1_conf"], rtol=0.3)
    np.testing.assert_allclose(ish.ST_conf.values, si["ST_conf"], rtol=0.3)
    # the rows of A and B are in [lo, hi]; AB_j is A with column j of B
    X = ish.X.values.reshape(4096, 5, 3)
    np.testing.assert_array_equal(X[:, 2, [0, 2]], X[:, 0, [0, 2]])
    np.testing.assert_array_equal(X[:, 2, 1], X[:, 4, 1])


@jax.jit
def _halt_times(P):
    """The matched ansatz's halt time at rows (mu, D, x0), from dampax.solve (not the engine)."""
    def one(p):
        osc = dp.Oscillator(m=1.0, k=30.0, mu=p[0], D=p[1])
        return dp.solve(osc, p[2], 0.0).halt_time

    return jax.vmap(one)(P)


def _halt_times_np(X, rows=1024):
    """_halt_times on the rows of X in chunks of ``rows`` (the last one padded): one compiled
    shape for every call in this module."""
    X = np.asarray(X, dtype=float)
    pad = -len(X) % rows
    Xp = np.concatenate([X, np.repeat(X[-1:], pad, axis=0)])
    out = [np.asarray(_halt_times(jnp.asarray(Xp[i:i + rows]))) for i in range(0, len(Xp), rows)]
    return np.concatenate(out)[:len(X)]


@pytest.fixture(scope="module")
def oscillator_study():
    return dp.global_sensitivity(bounds=BOUNDS, oscillator=OSC, x0=0.2, v0=0.0, n=1024, seed=1)


def test_oscillator_against_salib_sampler_and_analyze(oscillator_study):
    ds = oscillator_study
    assert ds.attrs["quantity"] == "halt_time" and ds.attrs["method"] == "ansatz"
    # SALib's own design (other seed, other points) and analysis of the same model
    problem = dict(num_vars=3, names=list(BOUNDS), bounds=[list(b) for b in BOUNDS.values()])
    X = salib_sample.sample(problem, 1024, calc_second_order=False, seed=7)
    Y = _halt_times_np(X)
    si = salib_sobol.analyze(problem, Y, calc_second_order=False, seed=7)
    for key in ("S1", "ST"):
        diff = np.abs(ds[key].values - si[key])
        assert np.all(diff <= ds[f"{key}_conf"].values + si[f"{key}_conf"]), (key, diff)
    # friction dominates the halt time, then drag; the start matters little
    assert ds.ST.values[0] > 0.6 and 0.1 < ds.ST.values[1] < 0.4 and ds.ST.values[2] < 0.1
    # the outputs are dampax.solve's halt times at the design's rows
    np.testing.assert_allclose(ds.Y.values, _halt_times_np(ds.X.values), rtol=1e-12)


def test_dgsm_against_finite_differences(oscillator_study):
    # nu_i = E[(d tau/d theta_i)^2] over the rows of A, the derivatives by central differences
    ds = oscillator_study
    A = ds.X.values.reshape(1024, 5, 3)[:, 0]
    h = 1e-6 * (ds.upper.values - ds.lower.values)
    grads = []
    for i in range(3):
        step = np.zeros(3)
        step[i] = h[i]
        grads.append((_halt_times_np(A + step) - _halt_times_np(A - step)) / (2 * h[i]))
    nu = np.mean(np.square(grads), axis=1)
    np.testing.assert_allclose(ds.nu.values, nu, rtol=1e-5)
    V = ds.attrs["variance"]
    np.testing.assert_allclose(ds.DGSM.values,
                               nu * (ds.upper.values - ds.lower.values) ** 2 / (math.pi**2 * V),
                               rtol=1e-5)
    assert np.all(ds.ST.values <= ds.DGSM.values)  # the smooth ansatz: DGSM bounds ST


def test_quantities_at_a_time_and_callable():
    bounds = {"mu": (0.01, 0.05), "v0": (-0.5, 0.5)}
    common = dict(bounds=bounds, oscillator=OSC, x0=0.2, v0=0.0, n=64, seed=2, dgsm=False)
    x = dp.global_sensitivity(quantity="x", t=0.4, **common)
    by_callable = dp.global_sensitivity(quantity=lambda s: s.x(0.4), **common)
    np.testing.assert_array_equal(x.Y.values, by_callable.Y.values)
    energy = dp.global_sensitivity(quantity="energy", t=0.4, **common)
    rows = x.X.values[:8]
    for row, xv, ev in zip(rows, x.Y.values[:8], energy.Y.values[:8], strict=True):
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=row[0], D=1.0), 0.2, row[1])
        np.testing.assert_allclose(xv, float(sol.x(0.4)), rtol=1e-12)
        np.testing.assert_allclose(ev, float(sol.energy(0.4)), rtol=1e-12)
    assert np.all(np.isnan(x.DGSM.values))


@pytest.mark.parametrize("kwargs, argument", [
    (dict(bounds={"zeta": (0.0, 1.0)}), "unknown parameter"),
    (dict(bounds={}), "bounds"),
    (dict(bounds={"mu": (0.05, 0.01)}), "lo < hi"),
    (dict(bounds={"mu": (0.01, math.inf)}), "finite"),
    (dict(bounds={"mu": (-0.01, 0.05)}), "negative"),
    (dict(bounds={"m": (0.0, 1.0)}), "must be > 0"),
    (dict(bounds={"mu": (0.01,)}), "pair"),
    (dict(n=8), "n must be"),
    (dict(quantity="speed"), "quantity"),
    (dict(quantity="x"), "t:"),
    (dict(t=3.0), "t: quantity='halt_time' does not use a time"),  # (ignored, yet in attrs)
    (dict(samples=7), "samples: quantity='halt_time' does not sample"),
    (dict(method="euler"), "method"),
    (dict(conf_level=1.5), "conf_level"),
    (dict(x0=float("nan")), "x0"),
    (dict(tail="sideways"), "tail"),
    (dict(quantity=lambda s: s.x(jnp.ones(3))), "scalar"),
    (dict(bounds={"D": (0.5, 3.0)}, n=16, oscillator=dp.Oscillator(m=1.0, k=30.0)),
     "not finite"),  # mu = 0: never halts, infinite halt time
])
def test_bad_input_names_the_argument(kwargs, argument):
    call = dict(bounds={"mu": (0.01, 0.05)}, oscillator=OSC, x0=0.2, v0=0.0, n=64,
                dgsm=False)
    call.update(kwargs)
    with pytest.raises(ValueError, match=argument):
        dp.global_sensitivity(**call)


@pytest.mark.slow
def test_ansatz_against_reference():
    # the halt time of the exact motion jumps where a swing is lost; its variance shares still
    # match the smooth ansatz's; DGSM of the reference sees only the slopes between jumps.
    # max_error: the ansatz's error against the reference, a function of both damping ratios.
    bounds = {"mu": (0.01, 0.05), "D": (0.5, 3.0)}
    common = dict(bounds=bounds, oscillator=OSC, x0=0.2, v0=0.0, n=256, seed=4, dgsm=False)
    ans = dp.global_sensitivity(**common)
    ref = dp.global_sensitivity(method="reference", max_swings=24, **common)
    for key in ("S1", "ST"):
        diff = np.abs(ans[key].values - ref[key].values)
        assert np.all(diff <= ans[f"{key}_conf"].values + ref[f"{key}_conf"].values), key
    assert ref.ST.values[0] > ref.ST.values[1] > 0.05
    err = dp.global_sensitivity(quantity="max_error", t=2.0, samples=64, max_swings=24,
                                **common)
    assert np.all(err.Y.values > 0.0) and np.all(err.Y.values < 0.5)
    assert np.all(np.isfinite(err.ST.values)) and np.all(err.ST.values > 0.05)


def test_cli_global(tmp_path, capsys, monkeypatch, oscillator_study):
    # the ranges and sample size of oscillator_study: its compiled programs serve the command
    parser = argparse.ArgumentParser(prog="dampax sensitivity")
    add_arguments(parser)
    path = tmp_path / "global.png"
    args = parser.parse_args(["--global", "mu=0.01:0.05,D=0.5:3,x0=0.15:0.25", "--n", "1024",
                              "--seed", "1", "--plot", str(path)])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "S1" in out and "ST" in out and "DGSM" in out and "mu in [0.01, 0.05]" in out
    # the command's numbers are the library's (same design, seed and model; the other
    # parameters, mu = 0.05 and D = 1 of the command's defaults, are all inside the ranges)
    row = next(line.split() for line in out.splitlines() if line.split()[:1] == ["D"])
    ds = oscillator_study.sel(parameter="D")
    assert row[-5:] == [f"{float(ds.S1):.4g}", f"{float(ds.S1_conf):.2g}", f"{float(ds.ST):.4g}",
                       f"{float(ds.ST_conf):.2g}", f"{float(ds.DGSM):.4g}"], row
    # bad specs: one line, exit status 2, before any computing
    from dampax import _cli

    monkeypatch.setitem(_cli.SUBCOMMANDS, "sensitivity", (add_arguments, run))
    for argv, word in ((["--global", "mu=0.05:0.01"], "lo < hi"),
                       (["--global", "zeta=0:1"], "unknown parameter"),
                       (["--global", "mu"], "NAME=LO:HI"),
                       (["--global", "mu=a:b"], "numbers"),
                       (["--global", "mu=0.01:0.05", "--quantity", "x"], "--time"),
                       (["--global", "mu=0.01:0.05", "--plot", str(tmp_path / "no" / "g.png")],
                        "--plot"),
                       (["--window", "0"], "window")):
        assert _cli.main(["sensitivity", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("dampax: error:") and word in err, err


@pytest.mark.parametrize("args, words", [
    (["--global", "mu=0.01:0.05", "--wrt", "k", "--swings"], "--wrt, --swings: not used by"),
    (["--quantity", "x", "--time", "1", "--n", "5"], "--quantity, --time, --n: not used by"),
])
def test_cli_flags_of_the_other_mode_are_refused(args, words, tmp_path, capsys):
    """``dampax sensitivity``: a local study's flags with --global, and --global's without it,
    end the command with status 2 and their names (they were ignored, exit 0)."""
    from dampax._cli import main

    assert main(["sensitivity", *args, "--plot", str(tmp_path / "s.png")]) == 2
    assert words in capsys.readouterr().err
