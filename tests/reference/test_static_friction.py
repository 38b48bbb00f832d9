"""Static friction mu_s >= mu (issue 25 item 3): the reference, the exact half-swings and the
Coulomb tail against scipy's DOP853 with events and exact stick-slip; mu_s = None and
mu_s = mu alike; derivatives; the models that assume mu_s = mu; fits with free mu_s; the CLI.

One oscillator family (m = 1 kg, k = 30 N/m, mu = 0.03, b = 0.1 kg/s, x0 = 0.2 m at rest),
one reference program (a batch of mu_s, t_end = 6 s) shared by the tests.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import count_reads
from scipy.integrate import solve_ivp

import dampax as dp
from dampax._cli import main
from dampax._models._solution import RESULTS

M, K, MU, B, G, X0, T_END = 1.0, 30.0, 0.03, 0.1, 9.81, 0.2, 6.0
MU_S = (0.05, 0.1, 0.15, 0.4)
TQ = np.linspace(0.0, 5.5, 23)


def _stick_slip(mu_s, D=0.0):
    """scipy DOP853 swing by swing; the block sticks at the first turning point with
    k |x| <= mu_s m g. Returns (halt time, halt position, x at TQ)."""
    t, x, v, s = 0.0, X0, 0.0, -1.0
    segments = []
    while True:
        def rhs(_, y, s=s):
            return [y[1], (-K * y[0] - MU * M * G * s - B * y[1] - D * y[1] * abs(y[1])) / M]

        def turn(_, y):
            return y[1]

        turn.terminal, turn.direction = True, -s
        sol = solve_ivp(rhs, (t, 50.0), [x, v], method="DOP853", rtol=1e-13, atol=1e-15,
                        events=turn, dense_output=True)
        t1, x1 = sol.t_events[0][0], sol.y_events[0][0][0]
        segments.append((t, t1, sol.sol))
        t, x, v, s = t1, x1, 0.0, -np.sign(x1)
        if K * abs(x) <= mu_s * M * G:
            break
    xs = np.array([x if tq >= t else next(f(tq)[0] for a, b, f in segments if a <= tq <= b)
                   for tq in TQ])
    return t, x, xs


@pytest.fixture(scope="module")
def exact():
    return {mu_s: _stick_slip(mu_s) for mu_s in MU_S}


@pytest.fixture(scope="module")
def batch():
    """One reference solve of every mu_s (vmapped: one program)."""
    osc = dp.Oscillator(m=M, k=K, mu=MU, b=B, mu_s=jnp.asarray(MU_S))
    return dp.solve(osc, X0, 0.0, method="reference", t_end=T_END, max_swings=16)


def test_reference_matches_scipy_stick_slip(batch, exact):
    halts = []
    for i, mu_s in enumerate(MU_S):
        t_h, x_h, xs = exact[mu_s]
        halts.append(t_h)
        assert float(batch.halt_time[i]) == pytest.approx(t_h, abs=1e-9)
        assert float(batch.halt_position[i]) == pytest.approx(x_h, abs=1e-9)
        x = np.asarray(batch.x(TQ))[i]
        np.testing.assert_allclose(x, xs, atol=1e-9)
    assert halts == sorted(halts, reverse=True) and halts[0] > halts[-1]  # halts earlier


def test_exact_half_swings_and_tail_halt_with_mu_s(exact):
    for mu_s in MU_S:
        t_h, x_h, xs = exact[mu_s]
        osc = dp.Oscillator(m=M, k=K, mu=MU, b=B, mu_s=mu_s)
        sol = dp.solve(osc, X0, 0.0, method="coulomb_exact")
        assert float(sol.halt_time) == pytest.approx(t_h, abs=1e-9)
        assert float(sol.halt_position) == pytest.approx(x_h, abs=1e-9)
        np.testing.assert_allclose(np.asarray(sol.x(TQ)), xs, atol=1e-9)
        # the ansatz with the exact tail switches at the last turning point outside the
        # static band: the same halting turning point
        tail = dp.solve(osc, X0, 0.0, method="ansatz", tail="coulomb")
        assert float(tail.halt_time) == pytest.approx(t_h, abs=0.1)
        assert np.sign(float(tail.halt_position)) == np.sign(x_h)


def test_none_and_mu_s_equal_to_mu_agree_exactly(batch):
    plain = dp.Oscillator(m=M, k=K, mu=MU, b=B)
    assert plain.mu_s is None and len(jax.tree_util.tree_leaves(plain)) == 7  # no new leaf
    assert "mu_s" not in repr(plain)
    same = dp.Oscillator(m=M, k=K, mu=MU, b=B, mu_s=MU)
    for method in ("coulomb_exact", "reference"):
        kw = dict(t_end=T_END, max_swings=16) if method == "reference" else {}
        a = dp.solve(plain, X0, 0.0, method=method, **kw)
        b = dp.solve(same, X0, 0.0, method=method, **kw)
        np.testing.assert_array_equal(np.asarray(a.x(TQ)), np.asarray(b.x(TQ)))
        assert float(a.halt_time) == float(b.halt_time)
        assert float(a.halt_position) == float(b.halt_position)
    # mu_s = mu given explicitly is not "different": every model still answers
    assert dp.solve(same, X0, 0.0, method="ansatz").valid


def test_validation_names_mu_s():
    with pytest.raises(ValueError, match="mu_s must be >= mu"):
        dp.Oscillator(m=M, k=K, mu=0.1, mu_s=0.05)
    with pytest.raises(ValueError, match="mu_s must be >= 0"):
        dp.Oscillator(m=M, k=K, mu_s=-0.1)
    with pytest.raises(ValueError, match="mu_s must be finite"):
        dp.Oscillator(m=M, k=K, mu_s=float("nan"))


def test_models_that_assume_mu_s_equal_mu_say_so():
    osc = dp.Oscillator(m=M, k=K, mu=MU, mu_s=0.1)
    for kw in (dict(method="ansatz"), dict(method="ansatz", phase="undamped"),
               dict(method="rizcallah")):
        with pytest.raises(ValueError, match="mu_s: static friction differs"):
            dp.solve(osc, X0, 0.0, **kw)
        sol = jax.jit(lambda o, kw=kw: dp.solve(o, X0, 0.0, **kw))(osc)
        assert sol.result == RESULTS.static_friction and not bool(sol.valid)
    # a start at rest inside the static band is exact for every model: it stays there
    x_in = 0.9 * 0.1 * G / K
    sol = dp.solve(osc, x_in, 0.0, method="ansatz")
    assert sol.valid and float(sol.x(1.0)) == pytest.approx(x_in)


def test_gradients_wrt_mu_s_and_mu():
    """x(t) after the halt: d/d mu_s is exactly 0 (only the halt decision depends on it, a
    step), finite; d/d mu with mu_s > mu matches central differences."""
    t_q = jnp.asarray(5.0)

    def x_at(mu, mu_s):
        osc = dp.Oscillator(m=M, k=K, mu=mu, b=B, mu_s=mu_s)
        return dp.solve(osc, X0, 0.0, method="reference", t_end=T_END, max_swings=16).x(t_q)

    g_mu, g_mus = jax.jit(jax.grad(x_at, argnums=(0, 1)))(MU, 0.15)  # one program
    assert np.isfinite(float(g_mu)) and float(g_mus) == 0.0
    h = 1e-6
    fd_mu = (float(x_at(MU + h, 0.15)) - float(x_at(MU - h, 0.15))) / (2 * h)
    fd_mus = (float(x_at(MU, 0.15 + 1e-3)) - float(x_at(MU, 0.15 - 1e-3))) / 2e-3
    assert float(g_mu) == pytest.approx(fd_mu, rel=1e-5)
    assert fd_mus == 0.0


FIT_MU, FIT_D, FIT_MU_S = 0.04, 0.5, 0.2


@pytest.fixture(scope="module")
def fit_traces():
    """The trace of issue 25's table with mu = 0.04, D = 0.5 (m = 1 kg, k = 30 N/m, x0 = 0.2 m
    at rest, 3 s at 500 Hz, 1 mm white noise: the shapes and programs of tests/fit/test_fit.py)
    from scipy's exact stick-slip, without static friction and with mu_s = 0.2 (the block
    halts at 2.30 s instead of swinging on). {mu_s: (t, x, rest)}."""
    from helpers import evaluate, scipy_stick_slip

    t = np.arange(0.0, 3.0, 1.0 / 500.0)
    out = {}
    for mu_s in (None, FIT_MU_S):
        segments, _, rest = scipy_stick_slip(M, K, FIT_MU, 0.0, FIT_D, X0, 0.0, 3.0,
                                             rtol=1e-11, atol=1e-13, mu_s=mu_s)
        noise = 1e-3 * np.random.default_rng(0).standard_normal(t.size)
        out[mu_s] = (t, evaluate(segments, rest, t)[0] + noise, rest)
    return out


@pytest.mark.parametrize("mu_s", [None, FIT_MU_S])
def test_fit_with_free_mu_s(fit_traces, mu_s, monkeypatch):
    """With static friction the search finds the halt: the interval of mu_s holds the truth,
    mu and D are inside their 99 % intervals, the halt time is the data's, and the rms falls
    to the noise from the sliding-friction fit's. Without it the fit stays the sliding one
    (no invented halt), mu_s from mu up. Seconds once the sliding fit is compiled."""
    t, x, rest = fit_traces[mu_s]
    reads, analyses = count_reads(monkeypatch, x)
    res = dp.fit(t, x, oscillator=dp.Oscillator(m=M, k=K), free=("mu", "D", "mu_s"),
                 model="reference")
    assert res.success, res.reason
    assert len(reads) == len(analyses) == 1  # prepared and analysed once for the whole search
    assert res.free[-1] == "mu_s" and "mu_s" in res.report()
    ci = res.conf_interval(0.99)
    for name, value in (("mu", FIT_MU), ("D", FIT_D)):
        assert ci[name][0] < value < ci[name][1], (name, value, ci[name])
    prof = res.profiled["mu_s"]
    lo, hi = ci["mu_s"]
    assert (lo, hi) == prof["interval"] and lo <= res.params["mu_s"] < hi
    assert prof["evaluations"] <= 6  # the sliding fit and a few at fixed mu_s
    if mu_s is None:  # truth: mu_s = mu, the block moves to the window's end
        assert rest is None and prof["halt_turn"] is None and lo == res.params["mu"]
        assert res.rms == pytest.approx(prof["rms_sliding"], rel=1e-3)
        return
    assert lo <= mu_s < hi and prof["halt_turn"] is not None
    assert res.derived["halt_time"] == pytest.approx(rest[0], abs=5e-3)
    assert res.rms < 1.2e-3 < 5e-3 < prof["rms_sliding"]
    # a fixed mu_s (through compare_models, which passes it to fit): the same optimum
    cmp = dp.compare_models(t, x, oscillator=dp.Oscillator(m=M, k=K), model="reference",
                            mu_s=res.params["mu_s"], candidates=(("mu", "D"),))
    assert cmp.best.rms == pytest.approx(res.rms, rel=1e-4)
    assert cmp.best.derived["halt_time"] == pytest.approx(res.derived["halt_time"], abs=1e-6)


def test_cli_fit_with_free_mu_s(fit_traces, tmp_path, capsys):
    """``dampax fit --free mu,D,mu_s --model reference`` on the trace with static friction
    (the programs of the test above); mu_s needs the reference model and says so."""
    t, x, _ = fit_traces[FIT_MU_S]
    path = tmp_path / "stick.txt"
    path.write_text("".join(f"{a:.4f} {b:.7f}\n" for a, b in zip(t, x, strict=True)))
    argv = ["fit", str(path), "--m", "1", "--k", "30", "--model", "reference", "--no-compare",
            "--free", "mu,D,mu_s", "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert re.search(r"mu_s:\s+[0-9.]+ \+/- ", out), out
    assert "every value gives the fitted halt" in out
    assert main([*argv[:-5], "--model", "ansatz", *argv[-5:]]) == 2
    assert "need the exact model (--model auto or reference)" in capsys.readouterr().err


def test_cli_solve_accepts_mu_s(capsys):
    code = main(["solve", "--mu", "0.03", "--b", "0.1", "--mu-s", "0.15", "--no-reference",
                 "--turning", "0"])
    out = capsys.readouterr()
    assert code == 0
    assert "mu_s = 0.15" in out.out and "static friction differs" in out.out
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    assert "--mu-s" in capsys.readouterr().out


def test_posterior_likelihood_carries_mu_s(fit_traces):
    """The posterior of a fit with static friction holds mu_s (fixed, or the free fit's value;
    it is a step function of the halt, so it is not sampled): its residuals at the fit's
    parameters are the data minus scipy's exact stick-slip motion with that mu_s, and the
    halted tail is in them (without mu_s the motion swings on and misses by centimetres)."""
    import jax.numpy as jnp
    from helpers import evaluate, scipy_stick_slip

    from dampax._fit._posterior import _trace_setup, static_friction

    t, x, _ = fit_traces[FIT_MU_S]
    res = dp.fit(t, x, oscillator=dp.Oscillator(m=M, k=K), free=("mu", "D"),
                 model="reference", mu_s=FIT_MU_S)
    assert res.fixed["mu_s"] == FIT_MU_S == static_friction(res)
    residual, args, layout, _, _, theta0 = _trace_setup(res, 1, vary_k3=False)
    assert "mu_s" not in layout.names and float(args.consts.mu_s) == FIT_MU_S
    p = res.params
    point = jnp.asarray([p[n] if n != "y" else p["v0"] for n in residual.names])
    got = np.asarray(residual(point, args))
    segments, _, rest = scipy_stick_slip(M, p["w0"] ** 2 * M, p["mu"], p["b"], p["D"], p["x0"],
                                         p["v0"], float(res.t[-1] - res.t[0]), rtol=1e-11,
                                         atol=1e-13, mu_s=FIT_MU_S)
    want = np.asarray(res.x) - p["offset"] - evaluate(segments, rest, res.t - res.t[0])[0]
    assert rest is not None and np.max(np.abs(got - want)) < 1e-7
    sliding = args._replace(consts=args.consts._replace(mu_s=None))
    assert np.max(np.abs(np.asarray(residual(point, sliding)))) > 1e-2
