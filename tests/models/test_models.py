"""Models under jit/vmap, exact-solution checks, scaling invariance and input validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import W0, evaluate, ratios_to_constants, scipy_stick_slip

import dampax as dp

# solve options of every analytic model, from the registry; parametrised once here
MODELS = {name: m.solve_options for name, m in dp.MODELS.items()
          if name in dp._models._registry.ANALYTIC}
MODELS["matched_tail_back1"] = dict(MODELS["matched_tail"], back=1)
COULOMB_ONLY = {"rizcallah", "coulomb_exact"}
QUADRANTS = [(1, 0), (1, 1), (-1, 1), (-1, -1), (1, -1), (0, 1), (-1, 0), (0, -1)]


def osc_for(model, d0=0.05, d1=0.02, d2=0.2):
    if model in COULOMB_ONLY:
        d1 = d2 = 0.0
    mu, b, D = ratios_to_constants(d0, d1, d2)
    return dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D)


def start(quadrant, A0=0.2):
    """Initial state with undamped amplitude A0 and phase in the given quadrant."""
    cx, cv = quadrant
    phi0 = math.atan2(-cv, cx) if (cx or cv) else 0.0
    return A0 * math.cos(phi0), -W0 * A0 * math.sin(phi0)


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("quadrant", QUADRANTS)
def test_initial_state_is_matched(model, quadrant):
    if model == "undamped":
        pytest.skip("eq. 9 drops f' from the velocity: v(0) != v0 by design")
    x0, v0 = start(quadrant)
    sol = dp.solve(osc_for(model), x0, v0, **MODELS[model])
    assert float(sol.x(0.0)) == pytest.approx(x0, abs=1e-12)
    assert float(sol.v(0.0)) == pytest.approx(v0, abs=1e-11)


@pytest.mark.parametrize("model", MODELS)
def test_vmap_equals_loop_and_no_recompilation(model):
    rng = np.random.default_rng(0)
    n = 5
    d0 = rng.uniform(0.0, 0.08, n)
    d0[0] = 0.0
    d1 = np.zeros(n) if model in COULOMB_ONLY else rng.uniform(0, 0.05, n)
    d2 = np.zeros(n) if model in COULOMB_ONLY else rng.uniform(0, 0.3, n)
    phi0 = rng.uniform(-math.pi, math.pi, n)
    x0, v0 = 0.2 * np.cos(phi0), -W0 * 0.2 * np.sin(phi0)
    consts = np.array([ratios_to_constants(*r) for r in zip(d0, d1, d2, strict=True)])
    ts = jnp.linspace(0.0, 4.0, 41)
    traces = []

    def run(mu, b, D, x0, v0):
        traces.append(1)
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D), x0, v0, **MODELS[model])
        return sol.x(ts), sol.energy(ts), sol.halt_time, dp.turning_points(sol, 4)[0]

    batched = jax.jit(jax.vmap(run))
    out = batched(*consts.T, x0, v0)
    for i in range(n):
        single = jax.jit(run)(*consts[i], x0[i], v0[i])
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(single), strict=True):
            np.testing.assert_allclose(np.asarray(a)[i], np.asarray(b), rtol=1e-12, atol=1e-14)
    n_traces = len(traces)
    batched(*(consts.T * 1.01), x0 * 0.9, v0 * 0.9)  # new values, same shapes
    assert len(traces) == n_traces, "the jitted solve recompiled for new values"


@pytest.mark.parametrize("model", MODELS)
def test_scaling_invariance(model):
    # docs/DESIGN.md 1: same ratios d0/(w0 A0), d1/w0, d2 A0/w0, phi0 -> same x/A0 against w0 t
    phi0 = 0.7
    curves = []
    for m, k, A0 in [(1.0, 30.0, 0.2), (0.3, 2.0, 0.05), (5.0, 800.0, 1.7)]:
        w0 = math.sqrt(k / m)
        mu, b, D = ratios_to_constants(0.04, 0.0 if model in COULOMB_ONLY else 0.03,
                                       0.0 if model in COULOMB_ONLY else 0.2, m=m, k=k, A0=A0)
        sol = dp.solve(dp.Oscillator(m=m, k=k, mu=mu, b=b, D=D), A0 * math.cos(phi0),
                       -w0 * A0 * math.sin(phi0), **MODELS[model])
        s = np.linspace(0.0, 40.0, 400)
        curves.append(np.asarray(sol.x(s / w0)) / A0)
        curves.append(np.asarray(sol.halt_time) * w0)
    for other in range(2, len(curves), 2):
        np.testing.assert_allclose(curves[other], curves[0], atol=1e-11)
        np.testing.assert_allclose(curves[other + 1], curves[1], rtol=1e-11)


def test_undamped_limit():
    # mu = b = D = 0: every model is x = A0 cos(w0 t + phi0) and never halts
    osc = dp.Oscillator(m=1.0, k=30.0)
    ts = np.linspace(0, 5, 50)
    for model, opts in MODELS.items():
        for q in QUADRANTS:
            x0, v0 = start(q)
            sol = dp.solve(osc, x0, v0, **opts)
            expected = x0 * np.cos(W0 * ts) + v0 / W0 * np.sin(W0 * ts)
            np.testing.assert_allclose(sol.x(ts), expected, atol=1e-12, err_msg=model)
            assert np.isinf(float(sol.halt_time)), model


@pytest.mark.parametrize("x0", [0.2, -0.13, 0.5])
@pytest.mark.parametrize("ratio", [0.01, 0.05, 0.1])
def test_rizcallah_turning_points_are_exact(x0, ratio):
    # Rizcallah, kappa = 4/pi, from rest: x_n = (-1)^n (x0 - 2 n xc) at t = n pi/w0
    mu, _, _ = ratios_to_constants(ratio)
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu)
    xc = mu * 9.81 / 30.0
    sol = dp.solve(osc, x0, 0.0, method="rizcallah")
    n_halt = math.ceil((abs(x0) - xc) / (2 * xc))
    t, x = (np.asarray(a) for a in dp.turning_points(sol, n_halt + 2))
    n = np.arange(1, n_halt + 1)
    np.testing.assert_allclose(t[:n_halt], n * math.pi / W0, rtol=1e-12)
    exact = (-1.0) ** n * np.sign(x0) * (abs(x0) - 2 * n * xc)
    np.testing.assert_allclose(x[:n_halt], exact, atol=1e-12)
    assert np.all(np.isnan(x[n_halt:]))
    assert float(sol.halt_time) == pytest.approx(n_halt * math.pi / W0, rel=1e-12)
    assert float(sol.halt_position) == pytest.approx(exact[-1], abs=1e-12)


@pytest.mark.parametrize("kappa", [math.pi / 2, math.sqrt(2)])
def test_rizcallah_other_kappas_decay_rates(kappa):
    # envelope slope d = kappa mu g/(2 w0): from rest the turning points are still at n pi/w0
    mu, _, _ = ratios_to_constants(0.02)
    sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu), 0.2, 0.0, method="rizcallah",
                   kappa=kappa)
    t, x = (np.asarray(a) for a in dp.turning_points(sol, 3))
    d = kappa * mu * 9.81 / (2 * W0)
    np.testing.assert_allclose(np.abs(x), 0.2 - d * t, rtol=1e-12)



@pytest.mark.parametrize("kappa", [math.pi / 2, math.sqrt(2)])
@pytest.mark.parametrize("ratio", [0.02, 0.025, 0.03, 0.045])
def test_rizcallah_halt_when_turning_points_jump_over_the_band(kappa, ratio):
    # kappa > 4/pi: |x_n| = x0 - n (kappa pi/2) xc drops by more than the band's width per half
    # period; the model halts in the band if a turning point lands there, else at the one
    # nearest the band before the envelope's zero, and never with NaN
    mu, _, _ = ratios_to_constants(ratio)
    xc = mu * 9.81 / 30.0
    sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu), 0.2, 0.0, method="rizcallah",
                   kappa=kappa)
    step = kappa * math.pi / 2 * xc
    n = np.arange(1, 200)
    xn = 0.2 - n * step  # signed envelope at the turning points n pi / w0
    inside = np.flatnonzero(np.abs(xn) <= xc)
    before_zero = np.flatnonzero(xn > 0)
    last = before_zero[-1]
    cands = n[: last + 2]
    pick = (inside[0] if inside.size and inside[0] <= last + 1
            else int(np.argmin(np.abs(xn[: last + 2]))))
    assert float(sol.halt_time) == pytest.approx(cands[pick] * math.pi / W0, rel=1e-12)
    assert abs(float(sol.halt_position)) == pytest.approx(abs(xn[pick]), abs=1e-12)
    assert bool(sol.valid)
    assert np.all(np.isfinite(np.asarray(sol.x(np.linspace(0.0, 10.0, 50)))))

@pytest.mark.parametrize("b_ratio", [0.0, 0.03])
def test_coulomb_exact_against_scipy(b_ratio):
    rng = np.random.default_rng(1)
    for _ in range(4):
        mu, b, _ = ratios_to_constants(rng.uniform(0.005, 0.1), b_ratio)
        phi0 = rng.uniform(-math.pi, math.pi)
        x0, v0 = 0.2 * math.cos(phi0), -W0 * 0.2 * math.sin(phi0)
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b), x0, v0,
                       method="coulomb_exact")
        segs, turning, rest = scipy_stick_slip(1.0, 30.0, mu, b, 0.0, x0, v0, 60.0)
        assert rest is not None
        ts = np.linspace(0.0, rest[0] + 1.0, 3000)
        xs, vs = evaluate(segs, rest, ts)
        np.testing.assert_allclose(sol.x(ts), xs, atol=1e-9)
        np.testing.assert_allclose(sol.v(ts), vs, atol=1e-8)
        assert float(sol.halt_time) == pytest.approx(rest[0], rel=1e-9)
        assert float(sol.halt_position) == pytest.approx(rest[1], abs=1e-10)
        t_tp, x_tp = (np.asarray(a) for a in dp.turning_points(sol, len(turning) + 1))
        np.testing.assert_allclose(t_tp[:-1], [p[0] for p in turning], rtol=1e-9)
        np.testing.assert_allclose(x_tp[:-1], [p[1] for p in turning], atol=1e-10)
        assert np.isnan(t_tp[-1])
        energy = np.asarray(sol.energy(ts))
        assert np.all(np.diff(energy) <= 1e-12)


def test_start_inside_band_stays_at_rest():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.3)  # xc = 0.098 m
    for opts in (MODELS["coulomb_exact"], MODELS["matched_tail"], MODELS["rizcallah"]):
        sol = dp.solve(osc, 0.05, 0.0, **opts)
        np.testing.assert_allclose(sol.x(np.linspace(0, 3, 7)), 0.05, rtol=1e-15)
        assert float(sol.halt_time) == 0.0 and float(sol.halt_position) == 0.05


def test_rest_state_is_valid():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05, b=0.1, D=1.0)
    for model, opts in MODELS.items():
        if model in COULOMB_ONLY:
            osc_m = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
        else:
            osc_m = osc
        sol = dp.solve(osc_m, 0.0, 0.0, **opts)
        assert bool(sol.valid), model
        np.testing.assert_array_equal(sol.x(np.linspace(0, 2, 5)), 0.0)
        np.testing.assert_array_equal(sol.v(np.linspace(0, 2, 5)), 0.0)


def test_tail_matches_exact_when_started_from_a_turning_point():
    # after the switch the tail is the exact motion from (t_s, x_s, 0): compare with scipy
    mu, b, D = ratios_to_constants(0.03, 0.02, 0.25)
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D)
    sol = dp.solve(osc, 0.2, 0.0, tail="coulomb")
    t_s = float(sol.t_switch)
    x_s = float(sol.x(t_s))
    segs, _, rest = scipy_stick_slip(1.0, 30.0, mu, b, 0.0, x_s, 0.0, 30.0)
    ts = np.linspace(t_s, t_s + rest[0] + 0.5, 500)
    np.testing.assert_allclose(sol.x(ts), evaluate(segs, rest, ts - t_s)[0], atol=1e-9)
    assert float(sol.halt_time) == pytest.approx(t_s + rest[0], rel=1e-9)


def test_matched_ansatz_under_jit_flags_missing_amplitude():
    # quadratic drag with d2 x0 >= w0: no admissible root of eq. 26 -> NaN and valid = False
    D = 3 * math.pi * 1.2 / (4 * 0.2)  # d2 x0 / w0 = 1.2
    f = jax.jit(lambda D: dp.solve(dp.Oscillator(m=1.0, k=30.0, D=D), 0.2, 0.0))
    sol = f(D)
    assert not bool(sol.valid) and np.isnan(float(sol.amplitude))
    g = jax.grad(lambda D: jnp.nan_to_num(f(D).x(0.3)))(D)
    assert np.isfinite(float(g))
    assert bool(f(1.0).valid)


@pytest.mark.parametrize("field", ["m", "k", "mu", "b", "D"])
def test_negative_parameters_rejected(field):
    kwargs = dict(m=1.0, k=30.0)
    kwargs[field] = -0.1
    with pytest.raises(ValueError, match=rf"\b{field}\b"):
        dp.Oscillator(**kwargs)


@pytest.mark.parametrize("field", ["m", "k", "mu", "b", "D", "g"])
def test_non_finite_parameters_rejected(field):
    kwargs = dict(m=1.0, k=30.0)
    kwargs[field] = float("nan")
    with pytest.raises(ValueError, match=rf"\b{field}\b.*finite"):
        dp.Oscillator(**kwargs)


def test_bad_initial_state_and_options_rejected():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
    with pytest.raises(ValueError, match="x0.*finite"):
        dp.solve(osc, float("nan"), 0.0)
    with pytest.raises(ValueError, match="v0.*finite"):
        dp.solve(osc, 0.1, float("inf"))
    with pytest.raises(ValueError, match="method"):
        dp.solve(osc, 0.1, 0.0, method="euler")
    with pytest.raises(ValueError, match="phase"):
        dp.solve(osc, 0.1, 0.0, phase="random")
    with pytest.raises(ValueError, match="b, D"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=1.0), 0.1, 0.0, method="rizcallah")
    with pytest.raises(ValueError, match="D"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=1.0), 0.1, 0.0, method="coulomb_exact")
    with pytest.raises(ValueError, match="admissible amplitude"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, D=3 * math.pi * 1.2 / (4 * 0.2)), 0.2, 0.0)


def test_batched_oscillator_fields():
    # fields may be arrays: damping_coefficients is elementwise, and solve vmaps over them
    mu = jnp.array([0.0, 0.02, 0.05])
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, D=jnp.array([0.0, 1.0, 2.0]))
    d0, d1, d2 = dp.damping_coefficients(osc)
    np.testing.assert_allclose(d0, 2 * mu * 9.81 / (math.pi * W0))
    np.testing.assert_allclose(d2, 4 * np.array([0.0, 1.0, 2.0]) * W0 / (3 * math.pi))
    with pytest.raises(ValueError, match="mu"):
        dp.Oscillator(m=1.0, k=30.0, mu=jnp.array([0.1, -0.2]))
    amps = jax.vmap(lambda mu, D: dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu, D=D), 0.2,
                                           0.0).amplitude)(osc.mu, osc.D)
    assert amps.shape == (3,) and np.all(np.isfinite(amps))


@pytest.mark.parametrize("model", MODELS)
def test_array_fields_without_vmap(model):
    # an Oscillator with array fields: the plain ansatz broadcasts (same numbers as a loop);
    # the piecewise models ask for jax.vmap with a ValueError (not a shape error deep inside)
    mu = jnp.array([0.0, 0.02, 0.05])
    D = jnp.zeros(3) if model in COULOMB_ONLY else jnp.array([0.0, 1.0, 2.0])
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, D=D)
    opts = MODELS[model]
    if model not in ("matched", "undamped"):
        with pytest.raises(ValueError, match="jax.vmap"):
            dp.solve(osc, 0.2, 0.0, **opts)
        return
    sol = dp.solve(osc, 0.2, 0.0, **opts)
    t, x = dp.turning_points(sol, 3)
    assert t.shape == (3, 3)
    for i in range(3):
        one = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=float(mu[i]), D=float(D[i])), 0.2, 0.0,
                       **opts)
        assert float(sol.x(0.7)[i]) == pytest.approx(float(one.x(0.7)), rel=1e-12)
        amplitude = jnp.broadcast_to(sol.amplitude, (3,))[i]  # A0 for the undamped phase
        assert float(amplitude) == pytest.approx(float(one.amplitude), rel=1e-12)
        t1, x1 = dp.turning_points(one, 3)
        np.testing.assert_allclose(t[i], t1, rtol=1e-12)
        np.testing.assert_allclose(x[i], x1, rtol=1e-12)


def test_turning_point_just_before_the_halt_under_vmap():
    # the matched ansatz turns at 1.4405 s, 0.027 s before its halt; Newton started at the halt
    # once stuck there under vmap (f = 0 exactly) and lost that turning point, while the
    # unbatched program (f a rounding error above 0) found it. Its residual must vanish there:
    # w0 t + phi = 3 pi + atan(f'/(w0 f)), i.e. v(t) = 0
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.1, b=0.2, D=0.5)

    def turning(mu):
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu, b=0.2, D=0.5), 0.2, -0.3)
        return dp.turning_points(sol, 3)

    one = dp.solve(osc, 0.2, -0.3)
    t, x = (np.asarray(a) for a in dp.turning_points(one, 3))
    tb, xb = (np.asarray(a) for a in jax.jit(jax.vmap(turning))(jnp.array([0.1, 0.1])))
    assert 0.0 < float(one.halt_time) - t[2] < 0.05
    assert abs(float(one.v(t[2]))) < 1e-10
    np.testing.assert_allclose(tb, np.stack([t, t]), rtol=1e-12)
    np.testing.assert_allclose(xb, np.stack([x, x]), rtol=1e-12)
