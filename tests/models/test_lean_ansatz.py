"""The lean evaluation of the ansatz (issue 12): per-point constants, a vectorized tan, state(t).

x(t), v(t) and energy(t) compute q = sqrt|Q|, c + b'/2, a + b'/2 and the regime once per point
and tan(q t) as a rational function (dampax._trig._tan_fraction) instead of XLA's float64 tan;
x and v take sin and cos from polynomials too (dampax._trig.sincos). Checked here: the rational
tan against the true tan (3 ulp) and its derivative against jax.lax.tan's; sincos against the true
sin and cos (2 ulp, every quadrant, up to the 4.2e8 switch and beyond it, compiled and op by
op) and its derivatives;
f(t) against the textbook per-sample formula (numpy, every regime, Q = 0 exactly); state(t)
against x(t), v(t) and energy(t); NaN for t < 0 and for invalid solutions; a batched solution
(array fields) and gradients under jit and vmap, including at mu = b = D = 0.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dampax as dp
from dampax._models._decay import decay, halt_time
from dampax._trig import _SINCOS_MAX, _sincos_poly, _tan_fraction, sincos

EPS = np.finfo(float).eps


def _ulps(got, u, fn, floor=0.0):
    """|got - fn(u)| in ulp of the true fn(u) (or of ``floor`` where smaller), the true value
    from long double (64 or 113 bits); where long double is double (no truth at hand), from
    numpy's libm, counted 1 ulp closer (its own error: 0.52 ulp here)."""
    extended = np.finfo(np.longdouble).nmant >= 63
    truth = fn(np.asarray(u, dtype=np.longdouble if extended else float))
    err = np.abs(np.asarray(got, dtype=truth.dtype) - truth)
    scale = np.spacing(np.maximum(np.abs(truth.astype(float)), floor))
    return np.asarray(err / scale, dtype=float) - (0.0 if extended else 1.0)


def _tan(u):
    num, den = _tan_fraction(u)
    return num / den


def test_rational_tan_within_three_ulp_of_numpy():
    rng = np.random.default_rng(0)
    u = np.concatenate([np.linspace(0.0, np.pi / 2, 200_001)[:-1],
                        rng.uniform(-50.0, 50.0, 100_000),
                        10.0 ** rng.uniform(-300, 0, 20_000), [0.0, np.pi / 4, 1.5707963267948966]])
    got = np.asarray(jax.jit(_tan)(u))
    # the true value, not numpy's libm (itself up to 0.55 ulp off, and another libm or numpy's
    # SIMD tan another way): XLA's rounding here is 2.73 ulp at most, a numpy replay of the
    # polynomial without fused multiply-adds 2.67, with them everywhere 2.43
    assert _ulps(got, u, np.tan).max() <= 3.0
    assert np.isnan(np.asarray(_tan(jnp.asarray([np.nan, np.inf])))).all()


def test_rational_tan_derivatives_as_lax_tan():
    u = jnp.asarray([0.0, 1e-8, 0.3, 0.7853981633974483, 1.2, 1.55, -0.9])
    for tr in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(jax.vmap(tr(_tan))(u), jax.vmap(tr(jnp.tan))(u),
                                   rtol=2e-15)
    np.testing.assert_allclose(jax.vmap(jax.grad(jax.grad(_tan)))(u),
                               jax.vmap(jax.grad(jax.grad(jnp.tan)))(u), rtol=1e-13, atol=1e-15)


def test_sincos_within_two_ulp_of_numpy():
    """sin and cos within 2 ulp of the true values up to the switch to libm, compiled (XLA on
    a CPU fuses multiplies and adds into exact fused multiply-adds) and op by op (eager: no
    fusion, as an H200's code computed it): the reduction must not need the fused ones. With
    the switch at 8e8 the op-by-op sin was 3.8e8 ulp off at u = -6.2e8 (n p0 inexact for
    n >= 2^28), the GPU's failure of this test, while the compiled one passed."""
    rng = np.random.default_rng(1)
    k = np.arange(-8, 9)
    top = _SINCOS_MAX * (1 - 1e-12)
    u = np.concatenate([rng.uniform(-10.0, 10.0, 200_000), rng.uniform(-1e4, 1e4, 100_000),
                        rng.uniform(-top, top, 100_000), rng.uniform(0.95 * top, top, 20_000),
                        10.0 ** rng.uniform(-300, 0, 20_000),
                        k * np.pi / 4, k * np.pi / 2 + 1e-9, [0.0, -0.0, top, -top]])
    for how, f in (("compiled", jax.jit(sincos)), ("op by op", _sincos_poly)):
        s, c = (np.asarray(v) for v in f(jnp.asarray(u)))
        for got, fn in ((s, np.sin), (c, np.cos)):
            # 2 ulp of the true value, or of 1e-16 near a zero of sin or cos (the reduction's
            # limit). Against the truth XLA's CPU code is 1.50 ulp off at most, a numpy replay
            # without fused multiply-adds 1.54 (benchmarks/README.md, issue 34)
            assert _ulps(got, u, fn, floor=1e-16).max() <= 2.0, (how, fn)


def test_sincos_beyond_the_switch_and_non_finite_is_libm():
    # one argument of the call past 4.2e8 (or not finite): the whole call takes jnp.sin, jnp.cos,
    # under vmap too (the branch is per call)
    u = jnp.asarray([0.3, 2.0, 1e9, -3e12, np.inf, np.nan])
    for f in (jax.jit(sincos), jax.vmap(sincos)):
        s, c = f(u)
        np.testing.assert_array_equal(s, jnp.sin(u))
        np.testing.assert_array_equal(c, jnp.cos(u))


def test_sincos_derivatives_exact():
    u = jnp.asarray([0.0, 1e-8, 0.3, 0.7853981633974483, 2.5, -4.0, 1e5])
    s, c = sincos(u)
    np.testing.assert_array_equal(jax.vmap(jax.grad(lambda v: sincos(v)[0]))(u), c)
    np.testing.assert_array_equal(jax.vmap(jax.grad(lambda v: sincos(v)[1]))(u), -s)
    np.testing.assert_array_equal(jax.vmap(jax.jacfwd(jax.grad(lambda v: sincos(v)[0])))(u), -s)
    np.testing.assert_allclose(c, np.cos(np.asarray(u)), rtol=0, atol=3e-16)


def _decay_textbook(t, a, bp, c):
    """f(t) per sample in numpy (np.tan, np.tanh; T = t at Q = 0), for 0 <= t <= tau."""
    Q = 0.25 * bp * bp - a * c
    q = np.sqrt(np.abs(Q))
    with np.errstate(divide="ignore", invalid="ignore"):
        T = np.where(Q > 0, np.tanh(q * t) / q, np.where(Q < 0, np.tan(q * t) / q, t))
    return (1.0 - (c + 0.5 * bp) * T) / (1.0 + (a + 0.5 * bp) * T)


@pytest.mark.parametrize("a, bp, c", [
    (0.0, 0.0, 0.0), (0.8, 0.0, 0.0), (0.0, 0.6, 0.0), (0.0, 0.0, 0.3), (0.8, 0.6, 0.0),
    (0.8, 0.0, 0.3), (0.0, 0.6, 0.3), (0.8, 0.6, 0.3), (0.8, 3.0, 0.3), (0.5, 1.0, 0.5),
    (2.0, 4.0, 2.0)])
def test_decay_matches_textbook_formula(a, bp, c):
    tau = float(halt_time(a, bp, c))
    t_max = 0.999 * tau if np.isfinite(tau) else 20.0
    t = np.linspace(0.0, t_max, 4001)
    f = np.asarray(jax.jit(decay)(t, a, bp, c))
    ref = _decay_textbook(t, a, bp, c)
    big = np.abs(0.25 * bp * bp - a * c) * t * t >= 1e-4  # outside the series region
    np.testing.assert_allclose(f[big], ref[big], rtol=0, atol=16 * EPS)
    np.testing.assert_allclose(f, ref, rtol=0, atol=1e-13)
    after = np.asarray(decay(np.asarray([tau, 2 * tau, -1.0]) if np.isfinite(tau)
                             else np.asarray([-1.0]), a, bp, c))
    assert np.isnan(after[-1]) and np.all(after[:-1] >= 0.0) and np.all(after[:-1] < 1e-12)


def _solutions():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=jnp.asarray([0.0, 0.02, 0.0, 0.02, 0.01]),
                        b=jnp.asarray([0.0, 0.0, 0.2, 0.2, 0.0]),
                        D=jnp.asarray([0.0, 0.4, 0.3, 0.0, 0.0]))
    return osc, dp.solve(osc, 0.2, -0.3)


def test_state_shares_x_and_v_for_a_batched_solution():
    osc, sol = _solutions()
    t = jnp.linspace(-0.5, 8.0, 301)[:, None]  # broadcasts against the batch of 5
    x, v = sol.state(t)
    assert x.shape == v.shape == (301, 5)
    np.testing.assert_array_equal(x, sol.x(t))
    np.testing.assert_array_equal(v, sol.v(t))
    np.testing.assert_allclose(sol.energy(t), osc.energy(x, v), rtol=4 * EPS, atol=0)
    before = np.asarray(t[:, 0] < 0.0)
    assert np.isnan(np.asarray(x)[before]).all() and np.isfinite(np.asarray(x)[~before]).all()
    assert np.isnan(np.asarray(sol.energy(t))[before]).all()


def test_invalid_solution_gives_nan_under_jit():
    osc = dp.Oscillator(m=1.0, k=30.0, D=3.0)  # d2 x0 >= w0: no admissible amplitude

    @jax.jit
    def run(x0):
        sol = dp.solve(osc, x0, 0.0)
        return sol.valid, sol.x(1.0), sol.v(1.0), sol.energy(1.0), sol.state(1.0)

    valid, *values = run(10.0)
    assert not bool(valid)
    assert all(np.isnan(np.asarray(v)).all() for v in jax.tree_util.tree_leaves(values))


CASES = jnp.asarray([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.4],
                     [0.02, 0.0, 0.4], [0.02, 0.2, 0.4]])  # mu, b, D: each boundary exactly


def _evaluate(p, t, which, via_state):
    osc = dp.Oscillator(m=1.0, k=30.0, mu=p[0], b=p[1], D=p[2])
    sol = dp.solve(osc, p[3], p[4])
    if via_state:
        x, v = sol.state(t)
        return {"x": x, "v": v, "E": osc.energy(x, v)}[which]
    return {"x": sol.x, "v": sol.v, "E": sol.energy}[which](t)


@pytest.mark.parametrize("which", ["x", "v", "E"])
def test_gradients_finite_at_boundaries_and_state_consistent(which):
    P = jnp.concatenate([CASES, jnp.broadcast_to(jnp.asarray([0.2, -0.3]), (6, 2))], axis=1)
    ts = jnp.asarray([0.0, 1e-7, 0.4, 1.3])

    def grid(transform, via_state):
        one = transform(lambda p, t: _evaluate(p, t, which, via_state), argnums=(0, 1))
        return jax.jit(jax.vmap(jax.vmap(one, in_axes=(None, 0)), in_axes=(0, None)))(P, ts)

    for g, h in zip(grid(jax.grad, False), grid(jax.jacfwd, True), strict=True):
        assert np.isfinite(np.asarray(g)).all()
        np.testing.assert_allclose(g, h, rtol=1e-9, atol=1e-12)
