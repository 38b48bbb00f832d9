"""The reference by diffrax (``engine="diffrax"``, issue 35 item 3) against dampax's own
engine and against scipy: two integrators that share only the equation, so each is the other's
independent number on every platform (a GPU included, where scipy cannot run).

One batched solve per engine (every damping term, a cubic spring, static friction, starts in
all four quadrants, a start at rest in the band, an invalid oscillator), one gradient, one
small error map.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ENGINE_CASES, evaluate, scipy_stick_slip, solve_cases

import dampax as dp
from dampax._oscillator import Oscillator
from dampax._reference import solve_reference

pytest.importorskip("diffrax")

T_END = 6.0
TS = np.linspace(0.0, T_END, 301)
OPTIONS = dict(rtol=1e-11, atol=1e-13, max_swings=32, max_steps_per_swing=48)
CASES = ENGINE_CASES


def _solve(engine):
    return solve_cases(engine, T_END, TS, **OPTIONS)


@pytest.fixture(scope="module")
def both():
    return _solve("dampax"), _solve("diffrax")


def test_the_engines_agree_on_every_case(both):
    """x at the samples within 1e-8 A0 (v within 1e-7 A0 w0), the same halts (time within
    1e-9 s), turning points and swing counts; the invalid oscillator is invalid for both (NaN,
    the same reason)."""
    ours, theirs = both
    assert list(np.asarray(ours.result._value)) == list(np.asarray(theirs.result._value))
    valid = np.asarray(ours.valid)
    assert list(valid) == [True] * 7 + [False]
    for name in ("halted", "n_swings"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), err_msg=name)
    np.testing.assert_allclose(theirs.halt_time[valid], ours.halt_time[valid], rtol=0,
                               atol=1e-9)
    np.testing.assert_allclose(theirs.swing_times[valid], ours.swing_times[valid], rtol=0,
                               atol=1e-9)
    for a, b, tol in zip(ours.state(TS), theirs.state(TS), (1e-8, 1e-7), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        np.testing.assert_allclose(b[valid], a[valid], rtol=0, atol=tol)
        assert np.all(np.isnan(b[~valid]))


def test_the_diffrax_engine_against_scipy(both):
    """The diffrax engine's samples within 1e-8 A0 of scipy's DOP853 with events (a cubic
    spring and static friction included)."""
    theirs = both[1]
    xs = np.asarray(theirs.x(TS))
    for i, (m, k, mu, b, D, k3, mu_s, x0, v0) in enumerate(CASES[:-1]):
        segs, _, rest = scipy_stick_slip(m, k, mu, b, D, x0, v0, T_END, k3=k3,
                                         mu_s=mu_s if mu_s is not None else mu)
        x_sp, _ = evaluate(segs, rest, TS)
        np.testing.assert_allclose(xs[i], x_sp, rtol=0, atol=1e-8, err_msg=str(CASES[i]))


def test_gradient_through_the_diffrax_engine():
    """d x(t) / d (mu, D) by reverse mode through diffrax: central finite differences of the
    same engine (dampax's engine's gradients: test_reference.py); forward mode gives the
    same."""
    def x_at(p, engine, adjoint="recursive"):
        osc = Oscillator(m=1.0, k=25.0, mu=p[0], b=0.05, D=p[1])
        sol = solve_reference(osc, 0.7, 0.4, t_end=3.0, engine=engine, adjoint=adjoint,
                              **OPTIONS)
        return sol.x(jnp.asarray(2.3))

    p = jnp.asarray([0.02, 0.15])
    g = np.asarray(jax.jit(jax.grad(lambda q: x_at(q, "diffrax")))(p))
    f = jax.jit(lambda q: x_at(q, "diffrax"))
    eps = 1e-6
    fd = [(float(f(p + eps * e)) - float(f(p - eps * e))) / (2 * eps) for e in np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)
    # forward mode (diffrax's ForwardMode): the same derivatives
    g_fwd = np.asarray(jax.jit(jax.jacfwd(lambda q: x_at(q, "diffrax", "forward")))(p))
    np.testing.assert_allclose(g_fwd, g, rtol=1e-8, atol=1e-10)


def test_error_map_with_the_diffrax_reference():
    """The same map with either engine as the reference: errors within 1e-8 A0, reference
    halt times within 1e-9 periods (both 1.7e-10 here); the map says which engine."""
    kw = dict(d0_ratio=[0.0, 0.03], d2_ratio=[0.0, 0.2], phi0=[0.4, 2.5], periods=4,
              samples_per_period=16, progress=False)
    ours, theirs = dp.error_map(**kw), dp.error_map(**kw, engine="diffrax")
    assert theirs.attrs["reference_engine"] == "diffrax" and "diffrax" in \
        theirs.attrs["reference_description"]
    for name, tol in (("max_error", 1e-8), ("rms_error", 1e-8), ("reference_halt_time", 1e-9)):
        a, b = ours[name].values, theirs[name].values
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        np.testing.assert_allclose(b, a, rtol=0, atol=tol, err_msg=name)


@pytest.mark.parametrize("call", [
    lambda: dp.solve(Oscillator(m=1, k=1, mu=0.1), 1.0, 0.0, method="reference",
                     engine="scipy"),
    lambda: dp.error_map(d0_ratio=0.1, d2_ratio=0.1, phi0=0.0, engine="scipy",
                         progress=False)])
def test_an_unknown_engine_is_named(call):
    with pytest.raises(ValueError, match="engine must be one of"):
        call()
