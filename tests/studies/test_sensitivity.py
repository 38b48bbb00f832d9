"""dampax.sensitivity: exact first derivatives of x(t), E(t), halt time and halt position.

Checked against central finite differences of dampax.solve (matched ansatz and the diffrax
reference) for mu, b, D, x0, v0, in a case away from swing-count changes and halt kinks; the
ansatz's and the reference's d x/d D agree where the ansatz is accurate; a vmap over mu equals a
loop; mu = 0 gives finite d x (and NaN d halt time); bad input raises ValueError naming the
argument; the CLI glue writes a PNG.

Turning points (issue 13): their local derivatives against central differences of
dampax.turning_points (reference and ansatz), their trends against numpy's least-squares slope of
turning points integrated independently by scipy (tests/helpers.py) and of the exact Coulomb
half-swings, over the window points where the turning point exists.

Every reference computation uses the same times, wrt and options, so the reference's forward
Jacobian is compiled once (its compilation dominates this module's run time); likewise the
ansatz's (the CLI test shares it), and the Rizcallah and exact-Coulomb tests share theirs.
"""

import argparse
import math

import equinox as eqx  # noqa: E402
import jax
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from helpers import scipy_stick_slip  # noqa: E402

import dampax as dp  # noqa: E402
from dampax._cli.sensitivity import add_arguments, run  # noqa: E402
from dampax._studies._sensitivity import Sensitivity, sensitivity  # noqa: E402

M, K = 1.0, 30.0
W0 = math.sqrt(K / M)
T0 = 2.0 * math.pi / W0
WRT = ("mu", "b", "D", "x0", "v0")
TS = jnp.linspace(0.05, T0, 24)  # the first period; shared by every reference call
N_TURNING = 3  # turning points asked for in every call below (one compiled program per model)
REF_SOLVE = dict(method="reference", t_end=2.0, max_swings=16)
REF = dict(REF_SOLVE, turning_points=N_TURNING)
ANSATZ = dict(method="ansatz", turning_points=N_TURNING)
# Coulomb + viscous + quadratic, started moving: the reference turns at x = -0.117, 0.042 and
# stops at 0.024 m (xc = 0.0327 m; every |x_n| is 0.009 m or more from xc), t = 1.66 s; the
# ansatz halts at 1.47 s. TS ends at 1.15 s, away from both halts.
CASE = np.array([0.1, 0.2, 0.5, 0.2, -0.3])  # mu, b, D, x0, v0
SCALE = np.array([0.1, 1.0, 1.0, 0.1, 0.5])  # typical magnitudes, for the step sizes
STEP = {"ansatz": 1e-6, "reference": 1e-5}  # relative to SCALE (reference: adaptive steps)


def _osc(mu, b=0.0, D=0.0):
    return dp.Oscillator(m=M, k=K, mu=mu, b=b, D=D)


@eqx.filter_jit
def _values_batch(P, options):
    """x(TS), E(TS), halt time and position, and the first N_TURNING turning points (t_n, x_n)
    of dampax.solve at each row (mu, b, D, x0, v0)."""

    def one(p):
        sol = dp.solve(_osc(p[0], p[1], p[2]), p[3], p[4], **dict(options))
        return (sol.x(TS), sol.energy(TS), sol.halt_time, sol.halt_position,
                *dp.turning_points(sol, N_TURNING))

    return jax.vmap(one)(P)


def _central_differences(options, p0, h):
    """dampax.solve's (x(TS), E(TS), tau, x_halt, t_n, x_n) at p0 and their central
    differences.

    Returns (values, derivatives): values at p0, and each derivative of shape (len(p0), ...).
    """
    n = len(p0)
    steps = np.diag(h)
    P = jnp.asarray(np.concatenate([p0 + steps, p0 - steps, p0[None]]))
    options = {k: v for k, v in options.items() if k != "turning_points"}
    out = [np.asarray(a) for a in _values_batch(P, tuple(sorted(options.items())))]
    values = tuple(a[2 * n] for a in out)
    derivs = tuple((a[:n] - a[n:2 * n]) / (2.0 * h.reshape((n,) + (1,) * (a.ndim - 1)))
                   for a in out)
    return values, derivs


def _close(got, want, rel):
    """|got - want| <= rel * (max |want| of the row + 1e-12), row by row (one per parameter)."""
    got, want = np.asarray(got), np.asarray(want)
    scale = np.max(np.abs(want.reshape(len(want), -1)), axis=1) + 1e-12
    err = np.max(np.abs(got - want).reshape(len(want), -1), axis=1)
    assert np.all(err <= rel * scale), f"error / scale per parameter: {err / scale}"


@pytest.mark.parametrize("options", [ANSATZ, REF], ids=["ansatz", "reference"])
def test_matches_central_differences(options):
    name = options["method"]
    sens = sensitivity(_osc(*CASE[:3]), CASE[3], CASE[4], TS, wrt=WRT, **options)
    assert sens.wrt == WRT and sens.dx.shape == (5, 24) and sens.dhalt_time.shape == (5,)
    assert bool(sens.valid)
    (x, _, tau, _, tn, xn), (fx, fe, ftau, fxh, ftn, fxn) = _central_differences(
        options, CASE, STEP[name] * SCALE)
    assert np.all(np.isfinite(ftau)) and np.all(np.isfinite(sens.dhalt_time))
    rel = 1e-5 if name == "ansatz" else 1e-4
    _close(sens.dx, fx, rel)
    _close(sens.denergy, fe, rel)
    np.testing.assert_allclose(sens.dhalt_time, ftau, rtol=rel, atol=rel * np.max(np.abs(ftau)))
    np.testing.assert_allclose(sens.dhalt_position, fxh, rtol=rel,
                               atol=rel * max(np.max(np.abs(fxh)), 1e-3))
    # turning points: both models have all three (the reference's third is its rest point)
    assert sens.turning_times.shape == (N_TURNING,)
    assert sens.dturning_time.shape == sens.dturning_position.shape == (5, N_TURNING)
    assert np.all(np.isfinite(tn)) and np.all(np.isfinite(ftn)) and np.all(np.isfinite(fxn))
    _close(np.moveaxis(sens.dturning_time, 1, 0), np.moveaxis(ftn, 1, 0), rel)
    _close(np.moveaxis(sens.dturning_position, 1, 0), np.moveaxis(fxn, 1, 0), rel)
    # the values are dampax.solve's
    np.testing.assert_allclose(sens.x, x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sens.halt_time, tau, rtol=1e-12)
    np.testing.assert_allclose(sens.turning_times, tn, rtol=1e-12)
    np.testing.assert_allclose(sens.turning_positions, xn, rtol=1e-12)
    # accessors
    np.testing.assert_array_equal(sens.of("D")["x"], sens.dx[2])
    assert list(sens.as_dict()) == list(WRT)
    assert float(sens.as_dict()["v0"]["halt_time"]) == float(sens.dhalt_time[4])
    np.testing.assert_array_equal(sens.of("mu")["turning_position"], sens.dturning_position[0])
    np.testing.assert_array_equal(sens.of("D")["turning_time_trend"],
                                  sens.dturning_time_trend[2])


@pytest.fixture(scope="module")
def quadratic():
    """Quadratic drag d2 A0/w0 = 0.1 from rest at A0 = 0.2 m, no friction: both models."""
    osc = dp.from_ratios(d2_ratio=0.1, m=M, k=K, A0=0.2)
    return {name: sensitivity(osc, 0.2, 0.0, TS, wrt=WRT, **options)
            for name, options in (("ansatz", ANSATZ), ("reference", REF))}


def test_ansatz_agrees_with_reference_where_accurate(quadratic):
    # D = 1.18 kg/m: over the first period the matched ansatz is close to the exact motion,
    # and so are its sensitivities
    for name in ("D", "x0", "b"):
        da = np.asarray(quadratic["ansatz"].of(name)["x"])
        dr = np.asarray(quadratic["reference"].of(name)["x"])
        assert np.max(np.abs(dr)) > 0.0
        assert np.max(np.abs(da - dr)) <= 0.1 * np.max(np.abs(dr)), name


def test_no_friction_gives_finite_dx_and_nan_dhalt(quadratic):
    # mu = 0: the motion never halts; d x/d mu (at mu = 0) is finite, d tau is undefined; the
    # turning points exist (b = 0 too), with finite derivatives, also d/d mu and d/d b at 0
    for sens in quadratic.values():
        assert np.all(np.isfinite(sens.dx)) and np.all(np.isfinite(sens.denergy))
        assert np.all(np.abs(sens.of("mu")["x"]) > 0.0)
        assert float(sens.halt_time) == math.inf
        assert np.all(np.isnan(sens.dhalt_time)) and np.all(np.isnan(sens.dhalt_position))
        assert np.all(np.isfinite(sens.turning_times))
        assert np.all(np.isfinite(sens.dturning_time))
        assert np.all(np.isfinite(sens.dturning_position))
        # smooth where it never halts: trends where the window is not empty (mu = b = v0 = 0)
        for name in ("D", "x0"):
            g = sens.of(name)
            np.testing.assert_allclose(g["turning_time_trend"], g["turning_time"], rtol=0.02,
                                       atol=1e-3 * np.max(np.abs(g["turning_time"])))
            np.testing.assert_allclose(g["turning_position_trend"], g["turning_position"],
                                       rtol=0.02)
        for name in ("mu", "b", "v0"):
            assert np.all(np.isnan(sens.of(name)["turning_time_trend"])), name
    # where the ansatz is accurate, so are its turning points and their derivatives
    ans, ref = quadratic["ansatz"], quadratic["reference"]
    np.testing.assert_allclose(ans.turning_positions, ref.turning_positions, rtol=0.05)
    np.testing.assert_allclose(ans.of("D")["turning_position"], ref.of("D")["turning_position"],
                               rtol=0.1)


# exact half-swings (pure Coulomb), the cheapest model to compile, in a narrow window with few
# points: one program for the forward calls of the reverse-mode, window, swing and CLI tests
EXACT = dict(wrt=("mu", "x0"), method="coulomb_exact", swings=True, turning_points=N_TURNING,
             window=0.01, window_points=5)


def test_reverse_mode_equals_forward_mode():
    # the plumbing of mode="reverse" (jax.jacrev), from a moving start; the sweep is the same
    # for both modes, left out of the reverse call
    args = (_osc(0.1), 0.2, -0.3, TS[:3])
    fwd = sensitivity(*args, **EXACT)
    rev = sensitivity(*args, **EXACT, mode="reverse", trend=False)
    assert np.all(np.abs(fwd.dx) > 0.0) and np.all(np.isfinite(fwd.dturning_position))
    for a, b in ((fwd.dx, rev.dx), (fwd.denergy, rev.denergy),
                 (fwd.dhalt_time, rev.dhalt_time), (fwd.dhalt_position, rev.dhalt_position),
                 (fwd.turning_times, rev.turning_times),
                 (fwd.dturning_time, rev.dturning_time),
                 (fwd.dturning_position, rev.dturning_position)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-14)
    assert np.all(np.isnan(rev.dhalt_time_trend)) and np.all(np.isnan(rev.dturning_time_trend))


def test_vmap_over_mu_equals_loop():
    # the batch without the trend sweep (it would double the batched program's compilation;
    # the sweep is a vmap itself), the loop with it (the program of the tests above)
    mus = jnp.asarray([0.0, 0.03, 0.1])

    def dx_of(mu, trend=True):
        return sensitivity(_osc(mu, D=1.0), 0.2, 0.0, TS, wrt=WRT, trend=trend, **ANSATZ)

    batched = jax.vmap(lambda mu: dx_of(mu, trend=False))(mus)
    assert isinstance(batched, Sensitivity)
    assert batched.dx.shape == (3, 5, 24) and batched.dhalt_time.shape == (3, 5)
    assert batched.dturning_time.shape == batched.dturning_time_trend.shape == (3, 5, N_TURNING)
    assert batched.window_turning_times.shape == (3, 5, 41, N_TURNING)
    assert np.all(np.isnan(batched.dturning_time_trend))
    for i, mu in enumerate(mus):
        single = dx_of(mu)
        np.testing.assert_allclose(batched.dx[i], single.dx, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(batched.dhalt_time[i], single.dhalt_time, rtol=1e-12)
        for field in ("turning_times", "turning_positions", "dturning_time",
                      "dturning_position"):
            np.testing.assert_allclose(getattr(batched, field)[i], getattr(single, field),
                                       rtol=1e-10, atol=1e-14, err_msg=field)
    # the accessor picks the parameter behind the batch axis
    np.testing.assert_array_equal(batched.of("D")["x"], batched.dx[:, 2])
    np.testing.assert_array_equal(batched.of("D")["turning_time"], batched.dturning_time[:, 2])
    assert np.all(np.isnan(batched.of("mu")["halt_time"][0]))  # mu = 0 never halts
    assert np.all(np.isfinite(batched.of("mu")["halt_time"][1:]))
    # ... but it turns: finite turning points and derivatives (d/d mu at mu = 0 included);
    # derivatives wherever the turning point exists (at mu = 0.1 the ansatz halts before the
    # third), NaN where it does not
    exists = np.isfinite(np.asarray(batched.turning_times))
    assert np.all(exists[0]) and not np.all(exists)
    for field in ("dturning_time", "dturning_position"):
        np.testing.assert_array_equal(np.isfinite(np.asarray(getattr(batched, field))),
                                      np.broadcast_to(exists[:, None, :], (3, 5, N_TURNING)))


@pytest.mark.parametrize("kwargs, argument", [
    (dict(wrt=("mu", "zeta")), "wrt"),
    (dict(wrt=()), "wrt"),
    (dict(wrt=("mu", "mu")), "wrt"),
    (dict(ts=[0.1, float("nan")]), "ts"),
    (dict(ts=[0.1, math.inf]), "ts"),
    (dict(ts=[-0.1, 0.5]), "ts"),
    (dict(mode="sideways"), "mode"),
    (dict(method="euler"), "method"),
    (dict(method="reference", adjoint="recursive"), "adjoint"),
    (dict(method="reference", t_end=-1.0), "t_end"),
    (dict(x0=float("nan")), "x0"),
    (dict(x0=jnp.ones(2)), "x0"),
    (dict(turning_points=-1), "turning_points"),
    (dict(turning_points=2.0), "turning_points"),
])
def test_bad_input_names_the_argument(kwargs, argument):
    call = dict(osc=_osc(0.05), x0=0.2, v0=0.0, ts=TS)
    call.update(kwargs)
    with pytest.raises(ValueError, match=argument):
        sensitivity(call.pop("osc"), call.pop("x0"), call.pop("v0"), call.pop("ts"), **call)


def test_invalid_model_raises_eagerly():
    # d2 |x0| > w0: the matched ansatz has no admissible amplitude (dampax.solve's reason)
    osc = dp.from_ratios(d2_ratio=1.5, m=M, k=K, A0=0.2)
    with pytest.raises(ValueError, match="admissible amplitude"):
        sensitivity(osc, 0.2, 0.0, TS, wrt=WRT, **ANSATZ)


def test_cli_glue_writes_png(tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="dampax sensitivity")
    add_arguments(parser)
    path = tmp_path / "sens.png"
    # the shapes and options of the other ansatz tests (5 names, 24 times, 3 turning points):
    # the matched model is compiled already; the undamped phase compiles fast (the Coulomb tail
    # takes ~15 s, the reference ~25 s: left to a manual run)
    args = parser.parse_args(["--wrt", "mu,b,D,x0,v0", "--models", "matched,undamped",
                              "--samples", "24", "--turning-points", str(N_TURNING),
                              "--plot", str(path)])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "matched ansatz" in out and "undamped-phase ansatz" in out and "plot written" in out
    for name in ("mu [1]", "b [kg/s]", "D [kg/m]", "x0 [m]", "v0 [m/s]"):
        assert name in out
    # the turning points and their derivatives are those of dampax.sensitivity
    assert "turning points (v = 0, t > 0)" in out and "d t_n [s]" in out
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=1.0)  # the command's defaults
    sens = sensitivity(osc, 0.2, 0.0, TS, wrt=WRT, **ANSATZ)
    assert f"1: ({float(sens.turning_times[0]):.4g}, {float(sens.turning_positions[0]):.4g})" \
        in out
    assert f"{float(sens.of('D')['turning_time'][1]):.4g}" in out
    bad = parser.parse_args(["--wrt", "mu,zeta", "--plot", str(path)])
    with pytest.raises(ValueError, match="wrt"):
        run(bad)
    bad = parser.parse_args(["--models", "matched,guess", "--plot", str(path)])
    with pytest.raises(ValueError, match="models"):
        run(bad)


def test_cli_errors_through_main(monkeypatch, tmp_path, capsys):
    # as registered in dampax._cli.SUBCOMMANDS: bad input is one line and exit status 2
    from dampax import _cli

    monkeypatch.setitem(_cli.SUBCOMMANDS, "sensitivity", (add_arguments, run))
    for argv, word in ((["--wrt", "mu,zeta"], "wrt"), (["--samples", "1"], "samples"),
                       (["--turning-points", "-1"], "--turning-points"),
                       (["--m", "-1"], "m must be > 0"),
                       (["--plot", str(tmp_path / "no" / "s.png")], "--plot")):
        assert _cli.main(["sensitivity", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("dampax: error:") and word in err, err


# ---- trend derivatives (issue 13): least-squares slope over +-5 % windows -----------------------


def _coulomb_halt(mu, x0=0.2):
    """Exact halt (time, position) of pure Coulomb friction from rest (Rizcallah eq. 2), numpy:
    x_n = (-1)^n (x0 - 2 n xc) at t_n = n pi/w0, rest at the first |x_n| <= xc."""
    xc = mu * 9.81 * M / K
    n = np.maximum(np.ceil((x0 / xc - 1.0) / 2.0), 0.0)
    return n * math.pi / W0, (-1.0) ** n * (x0 - 2.0 * n * xc)


def _coulomb_turning(mu, x0=0.2, n_max=N_TURNING):
    """Exact turning points of pure Coulomb friction from rest, numpy, shape mu.shape + (n,):
    t_n = n pi/w0, x_n = (-1)^n (x0 - 2 n xc) for n up to the swing count (the rest point
    included), NaN after."""
    mu = np.asarray(mu, dtype=float)[..., None]
    xc = mu * 9.81 * M / K
    count = np.maximum(np.ceil((x0 / xc - 1.0) / 2.0), 0.0)
    n = np.arange(1, n_max + 1)
    exists = n <= count
    return (np.where(exists, n * math.pi / W0, np.nan),
            np.where(exists, (-1.0) ** n * (x0 - 2.0 * n * xc), np.nan))


def _slope_where_finite(u, y):
    """numpy's least-squares slope of y against u over the finite y (NaN for fewer than 3)."""
    ok = np.isfinite(y)
    return np.polyfit(u[ok], y[ok], 1)[0] if np.sum(ok) >= 3 else math.nan


def _check_turning_trends(sens, i, u, t_n, x_n, rtol, atol=0.0):
    """Sensitivity's turning-point trends for wrt[i] against numpy on the values t_n, x_n
    (shape (len(u), N)), and the sweep's NaN where (only where) the turning point is absent."""
    got_t = np.asarray(sens.window_turning_times)[i]
    np.testing.assert_array_equal(np.isnan(got_t), np.isnan(t_n))
    np.testing.assert_array_equal(np.isnan(np.asarray(sens.window_turning_positions)[i]),
                                  np.isnan(x_n))
    for n in range(t_n.shape[1]):
        for got, values in ((sens.dturning_time_trend, t_n), (sens.dturning_position_trend,
                                                               x_n)):
            want = _slope_where_finite(u, values[:, n])
            if math.isnan(want):
                assert math.isnan(float(got[i, n])), (i, n)
            else:
                np.testing.assert_allclose(float(got[i, n]), want, rtol=rtol, atol=atol,
                                           err_msg=f"wrt {i}, turning point {n + 1}")


def test_trend_sees_the_jump_the_local_derivative_misses():
    # pure Coulomb from rest at 0.2 m: x0 = 5 xc at mu = 0.1223, so the +-5 % window of
    # mu = 0.122 holds the point where the block loses its third half-swing (1.72 s -> 1.15 s).
    # Same program as the reference above (wrt, TS and options): no new compilation.
    mu = 0.122
    sens = sensitivity(_osc(mu), 0.2, 0.0, TS, wrt=WRT, **REF)
    g = sens.of("mu")
    # locally the halt time does not depend on mu (t_n = n pi/w0)
    assert abs(float(g["halt_time"])) < 1e-6
    # the trend is the least-squares slope of the exact halts on the same window, in numpy
    u = mu * (1.0 + 0.05 * np.linspace(-1.0, 1.0, 41))
    tau, xh = _coulomb_halt(u)
    assert np.ptp(tau) > 0.5  # the window holds the jump
    np.testing.assert_allclose(np.asarray(sens.window_values)[0], u, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(sens.window_halt_time)[0], tau, rtol=1e-7)
    np.testing.assert_allclose(float(g["halt_time_trend"]), np.polyfit(u, tau, 1)[0], rtol=1e-6)
    np.testing.assert_allclose(float(g["halt_position_trend"]), np.polyfit(u, xh, 1)[0],
                               rtol=1e-6)
    assert float(g["halt_time_trend"]) < -10.0
    # flagged, with the reason, in the report; b = D = v0 = 0 have empty windows: NaN trends
    assert sens.disagreements()["mu"]["halt_time"]
    report = sens.report()
    assert "*" in report and "jumps inside the window" in report
    for name in ("b", "D", "v0"):
        assert math.isnan(float(sens.of(name)["halt_time_trend"])), name
        assert not sens.disagreements()[name]["halt_time"]
    # the turning points do not jump: the third exists on part of the window only (it is the
    # rest point where the block stops there), and its trend is fitted over that part;
    # d t_n/d mu = 0 and d x_n/d mu = (-1)^(n+1) 2 n g m/k, locally and as the trend
    t_n, x_n = _coulomb_turning(u)
    assert np.isfinite(t_n[0, 2]) and np.isnan(t_n[-1, 2])
    np.testing.assert_allclose(sens.turning_times, _coulomb_turning(mu)[0], rtol=1e-8)
    _check_turning_trends(sens, 0, u, t_n, x_n, rtol=1e-6, atol=1e-6)
    dx_n = (-1.0) ** (np.arange(1, 4) + 1) * 2 * np.arange(1, 4) * 9.81 * M / K
    np.testing.assert_allclose(g["turning_position"], dx_n, rtol=1e-6)
    np.testing.assert_allclose(g["turning_position_trend"], dx_n, rtol=1e-6)
    assert np.max(np.abs(g["turning_time"])) < 1e-6
    assert not any(v for k, v in sens.disagreements()["mu"].items() if k.startswith("turning"))
    # b = D = 0: the derivatives of the turning points are finite there too
    assert np.all(np.isfinite(sens.dturning_time)) and np.all(
        np.isfinite(sens.dturning_position))


def test_trend_equals_local_derivative_without_jumps():
    # CASE has no swing-count change within +-5 % of any parameter: the reference's trend is
    # its local derivative up to the window's curvature
    sens = sensitivity(_osc(*CASE[:3]), CASE[3], CASE[4], TS, wrt=WRT, **REF)
    np.testing.assert_allclose(sens.dhalt_time_trend, sens.dhalt_time, rtol=0.05,
                               atol=1e-3 * np.max(np.abs(sens.dhalt_time)))
    for local, trend in ((sens.dturning_time, sens.dturning_time_trend),
                         (sens.dturning_position, sens.dturning_position_trend)):
        np.testing.assert_allclose(trend, local, rtol=0.05, atol=1e-3 * np.max(np.abs(local)))
    assert not any(any(f.values()) for f in sens.disagreements().values())
    assert "*" not in sens.report() and "turning points" in sens.report()


def test_turning_point_trends_against_scipy():
    # the reference's turning-point trends over the mu and D windows of CASE against numpy's
    # least-squares slope of turning points integrated by scipy (DOP853, v = 0 events)
    sens = sensitivity(_osc(*CASE[:3]), CASE[3], CASE[4], TS, wrt=WRT, **REF)
    for i, name in ((0, "mu"), (2, "D")):
        u = CASE[i] * (1.0 + 0.05 * np.linspace(-1.0, 1.0, 41))
        t_n, x_n = np.full((41, N_TURNING), np.nan), np.full((41, N_TURNING), np.nan)
        for j, value in enumerate(u):
            p = CASE.copy()
            p[i] = value
            _, turning, _ = scipy_stick_slip(M, K, *p, t_end=2.0)
            for n, (t, x) in enumerate(turning[:N_TURNING]):
                t_n[j, n], x_n[j, n] = t, x
        assert np.all(np.isfinite(t_n)), name  # no swing lost: three turning points throughout
        _check_turning_trends(sens, i, u, t_n, x_n, rtol=1e-5)


def test_ansatz_trend_against_numpy_sweep():
    # the ansatz's halt is smooth: its trend is the numpy least-squares slope of halt times
    # computed here by dampax.solve on the same grid, and close to the local derivative
    # (wrt, TS and the default window as above: the compiled program is re-used)
    p0 = dict(mu=0.0288, D=2.95, x0=0.2, v0=-0.3, b=0.2)
    sens = sensitivity(_osc(p0["mu"], p0["b"], p0["D"]), p0["x0"], p0["v0"], TS, wrt=WRT,
                       **ANSATZ)
    assert sens.window == 0.05 and np.asarray(sens.window_values).shape == (5, 41)
    for i, name in enumerate(WRT):
        u = p0[name] * (1.0 + 0.05 * np.linspace(-1.0, 1.0, 41))
        tau, turning = [], []
        for value in u:
            p = dict(p0, **{name: value})
            sol = dp.solve(_osc(p["mu"], p["b"], p["D"]), p["x0"], p["v0"])
            tau.append(float(sol.halt_time))
            turning.append(np.asarray(dp.turning_points(sol, N_TURNING)))
        np.testing.assert_allclose(float(sens.dhalt_time_trend[i]), np.polyfit(u, tau, 1)[0],
                                   rtol=1e-9, err_msg=name)
        np.testing.assert_allclose(float(sens.dhalt_time_trend[i]),
                                   float(sens.dhalt_time[i]), rtol=0.02, err_msg=name)
        t_n, x_n = np.moveaxis(np.array(turning), 1, 0)
        _check_turning_trends(sens, i, u, t_n, x_n, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(sens.dhalt_position_trend, 0.0)  # always stops at x = 0
    assert not any(any(f.values()) for f in sens.disagreements().values())


def test_window_option_sets_the_sweep():
    # a narrower window and fewer points (EXACT: window=0.01, window_points=5)
    sens = sensitivity(_osc(0.1), 0.2, -0.3, TS[:3], **EXACT)
    np.testing.assert_allclose(np.asarray(sens.window_values),
                               np.array([[0.1], [0.2]]) * (1.0 + 0.01 * np.linspace(-1, 1, 5)),
                               rtol=1e-14)
    assert sens.window == 0.01 and np.all(np.isfinite(sens.window_halt_time))
    assert np.asarray(sens.window_turning_times).shape == (2, 5, N_TURNING)


@pytest.mark.parametrize("kwargs, argument", [
    (dict(window=0.0), "window"),
    (dict(window=1.5), "window"),
    (dict(window=float("nan")), "window"),
    (dict(window_points=2), "window_points"),
])
def test_bad_window_names_the_argument(kwargs, argument):
    with pytest.raises(ValueError, match=argument):
        sensitivity(_osc(0.05), 0.2, 0.0, TS, **kwargs)


def test_swing_count_and_its_trend():
    # pure Coulomb from rest at 0.2 m, exact half-swings: n = ceil((x0/xc - 1)/2) turning
    # points, the rest point included; x0 = 5 xc at mu = 0.1223, inside the +-1 % window of
    # mu = 0.122 (EXACT), and at x0 = 0.1996 m, inside that of x0 = 0.2 m. The count's trend
    # against numpy's least-squares slope, the turning points against the closed form
    mu = 0.122
    sens = sensitivity(_osc(mu), 0.2, 0.0, TS[:3], **EXACT)
    u_mu = mu * (1.0 + 0.01 * np.linspace(-1.0, 1.0, 5))
    u_x0 = 0.2 * (1.0 + 0.01 * np.linspace(-1.0, 1.0, 5))
    xc = mu * 9.81 * M / K
    assert float(sens.swings) == 3.0
    for i, count in ((0, np.ceil((0.2 / (u_mu * 9.81 * M / K) - 1.0) / 2.0)),
                     (1, np.ceil((u_x0 / xc - 1.0) / 2.0))):
        u = (u_mu, u_x0)[i]
        assert np.ptp(count) == 1.0  # a swing is lost inside the window
        np.testing.assert_array_equal(np.asarray(sens.window_swings)[i], count)
        np.testing.assert_allclose(float(sens.dswings_trend[i]), np.polyfit(u, count, 1)[0],
                                   rtol=1e-9)
    assert "swings" in sens.report()
    # a count's local derivative is 0: a non-zero trend is flagged (a swing lost in the window)
    assert sens.disagreements()["mu"]["swings"]
    # turning points, the third on part of the mu window only (3 of 5 points), against the
    # closed form t_n = n pi/w0, x_n = (-1)^n (x0 - 2 n xc)
    t_n, x_n = _coulomb_turning(u_mu)
    assert np.sum(np.isfinite(t_n[:, 2])) == 3
    np.testing.assert_allclose(sens.turning_times, _coulomb_turning(mu)[0], rtol=1e-12)
    np.testing.assert_allclose(sens.turning_positions, _coulomb_turning(mu)[1], rtol=1e-12)
    _check_turning_trends(sens, 0, u_mu, t_n, x_n, rtol=1e-9, atol=1e-12)
    dx_n = (-1.0) ** (np.arange(1, 4) + 1) * 2 * np.arange(1, 4) * 9.81 * M / K
    np.testing.assert_allclose(sens.dturning_position[0], dx_n, rtol=1e-12)
    np.testing.assert_allclose(sens.dturning_position[1], (-1.0) ** np.arange(1, 4),
                               rtol=1e-12)
    np.testing.assert_array_equal(sens.dturning_time, 0.0)
    # t_n does not depend on mu: a trend at rounding level is not flagged
    flags = sens.disagreements()["mu"]
    assert not any(flags[f"turning_{q}_{j}"] for q in ("time", "position") for j in (1, 2, 3))


def test_cli_swings_and_turning_points(tmp_path, capsys):
    # the same program as above (EXACT): the printed table has the count, the turning points
    # and their trends, flagged where they differ from the local derivative, with the note
    parser = argparse.ArgumentParser(prog="dampax sensitivity")
    add_arguments(parser)
    path = tmp_path / "swings.png"
    args = parser.parse_args(["--mu", "0.122", "--D", "0", "--wrt", "mu,x0", "--models",
                              "coulomb_exact", "--samples", "3", "--swings",
                              "--turning-points", str(N_TURNING), "--window", "0.01",
                              "--window-points", "5", "--plot", str(path)])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    sens = sensitivity(_osc(0.122), 0.2, 0.0, TS[:3], **EXACT)
    assert "number of swings" in out and "exact half-swings (D = 0) 3" in out
    lines = out.splitlines()
    # the count's row: local 0, the trend flagged
    trend = f"{float(sens.dswings_trend[0]):.4g}*"
    assert any(line.split()[:2] == ["mu", "[1]"] and line.split()[-2:] == ["0", trend]
               for line in lines), out
    assert "1: (0.5736, -0.1202)" in out and "3: (1.721, 0.03936)" in out
    # d x_3/d mu = 6 g m/k = 1.962, locally and as the trend: not flagged
    row = next(line for line in lines if line.split()[:1] == ["3"] and "1.962" in line)
    assert row.split()[-2:] == ["1.962", "1.962"], row
    assert "jumps inside the window" in out


@pytest.mark.parametrize("wrt, method, options, lacking", [
    (("mu", "b", "D"), "rizcallah", {}, "b, D"),
    (("mu", "D"), "coulomb_exact", {}, "D"),
    (("mu", "k3"), "ansatz", {"phase": "undamped"}, "k3"),
    (("k3",), "ansatz", {"tail": "coulomb"}, "k3"),
])
def test_a_constant_the_model_leaves_out_is_refused(wrt, method, options, lacking):
    """A derivative in a constant the method's model leaves out (Model.lacks) is a ValueError
    naming it: it came out 0 (Rizcallah's dx/db and dx/dD, coulomb_exact's dx/dD), where the
    reference's is not."""
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
    with pytest.raises(ValueError, match=f"wrt: {lacking} not in the"):
        dp.sensitivity(osc, 0.2, 0.0, np.array([0.5, 1.0]), wrt=wrt, method=method,
                       trend=False, **options)
