"""Cubic stiffness k3 (issue 14): m x'' = -k x - k3 x^3 - mu m g sgn(x') - b x' - D x'|x'|.

The reference against scipy with events (helpers.scipy_stick_slip with k3) and the domain (a
softening spring that lets the block escape, models without k3).
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from helpers import evaluate, scipy_stick_slip

import dampax as dp
from dampax._solution import RESULTS

M, K, A = 1.0, 30.0, 0.2
W0 = math.sqrt(K / M)
T20 = 20 * 2 * math.pi / W0  # 20 undamped periods


def k3_of(ratio):
    """k3 for k3 A^2 / k = ratio."""
    return ratio * K / A**2


# --- the oscillator and the domain -------------------------------------------------------------


def test_k3_field_and_validation():
    osc = dp.Oscillator(m=M, k=K, k3=-50.0)
    assert float(osc.k3) == -50.0
    assert "k3=-50.0" in repr(osc)
    assert "k3" not in repr(dp.Oscillator(m=M, k=K))  # the linear spring's repr is unchanged
    for bad in (math.nan, math.inf):
        with pytest.raises(ValueError, match="k3"):
            dp.Oscillator(k3=bad)
    # energy k x^2/2 + k3 x^4/4 + m v^2/2
    assert float(osc.energy(0.1, 0.3)) == pytest.approx(15 * 0.01 - 12.5 * 1e-4 + 0.045)


@pytest.mark.parametrize("method", ["reference"])
def test_softening_spring_that_lets_go(method):
    """k3 < 0: the potential's maximum at sqrt(k/|k3|) = 0.3 m, barrier k^2/(4 |k3|)."""
    osc = dp.Oscillator(m=M, k=K, k3=-K / 0.09)
    kw = {"t_end": 2.0} if method == "reference" else {}
    for x0, v0 in ((0.31, 0.0), (0.3, 0.0), (0.0, 1.17)):  # beyond, on, energy above barrier
        with pytest.raises(ValueError, match="k3, x0, v0"):
            dp.solve(osc, x0, v0, method=method, **kw)
    if method == "ansatz":  # under jit: NaN and the reason
        sol = jax.jit(lambda o, x: dp.solve(o, x, 0.0, method=method))(osc, 0.31)
        assert not bool(sol.valid) and sol.result == RESULTS.unconfined
        assert np.isnan(float(sol.x(0.5)))
    # below the barrier: fine (the reference up to the barrier; harmonic balance has no
    # matched amplitude that close to it, A w(A) has a maximum)
    dp.solve(osc, 0.0, 1.15 if method == "reference" else 0.9, method=method, **kw)


@pytest.mark.parametrize("options", [dict(method="rizcallah"), dict(method="coulomb_exact"),
                                     dict(method="ansatz", tail="coulomb"),
                                     dict(method="ansatz", phase="undamped")])
def test_models_without_k3_say_so(options):
    osc = dp.Oscillator(m=M, k=K, mu=0.05, k3=100.0)
    with pytest.raises(ValueError, match="k3: this model has no cubic stiffness"):
        dp.solve(osc, 0.2, 0.0, **options)
    if options["method"] == "rizcallah":  # under jit: NaN and the reason
        sol = jax.jit(lambda o: dp.solve(o, 0.2, 0.0, **options))(osc)
        assert not bool(sol.valid) and np.isnan(float(sol.x(0.3)))
        assert sol.result == RESULTS.no_cubic
    # a start at rest inside the band stays there whatever the spring
    assert float(dp.solve(osc, 0.001, 0.0, **options).halt_time) == 0.0


# --- the reference -----------------------------------------------------------------------------


@pytest.mark.parametrize("case", [
    dict(mu=0.03, b=0.2, D=0.5, k3=400.0, x0=0.2, v0=0.0),  # hardening, every damping
    dict(mu=0.02, D=1.0, k3=-200.0, x0=0.15, v0=0.4),  # softening
    dict(b=0.3, k3=-250.0, x0=0.3, v0=0.0),  # softening, k3 x0^2/k = -0.75, no friction
])
def test_reference_against_scipy(case):
    case = dict(case)
    x0, v0 = case.pop("x0"), case.pop("v0")
    osc = dp.Oscillator(m=M, k=K, **case)
    ref = dp.solve(osc, x0, v0, method="reference", t_end=8.0)
    segs, turning, rest = scipy_stick_slip(M, K, case.get("mu", 0.0), case.get("b", 0.0),
                                           case.get("D", 0.0), x0, v0, 8.0, k3=case["k3"])
    t = np.linspace(0.0, 8.0, 801)
    x_sp, v_sp = evaluate(segs, rest, t)
    np.testing.assert_allclose(ref.x(t), x_sp, atol=1e-9 * A)
    np.testing.assert_allclose(ref.v(t), v_sp, atol=1e-8 * A * W0)
    t_tp, x_tp = dp.turning_points(ref, len(turning))
    np.testing.assert_allclose(t_tp, [p[0] for p in turning], atol=1e-9)
    np.testing.assert_allclose(x_tp, [p[1] for p in turning], atol=1e-9 * A)
    if rest is None:
        assert float(ref.halt_time) == math.inf
    else:
        assert float(ref.halt_time) == pytest.approx(rest[0], abs=1e-9)
        assert float(ref.halt_position) == pytest.approx(rest[1], abs=1e-10)
    if "mu" not in case and "D" not in case:  # only viscous: E(t) - E(0) = -int b v^2 dt
        E = np.asarray(ref.energy(t))
        assert np.all(np.diff(E) <= 1e-12) and E[0] == pytest.approx(
            0.5 * K * x0**2 + 0.25 * case["k3"] * x0**4)


def test_sticking_with_the_cubic_force():
    """The block holds where |k x + k3 x^3| <= mu m g, not |x| <= xc: a softening spring pulls
    less, so a start at rest just outside xc sticks; a hardening one just inside moves."""
    mu = 0.05
    xc = mu * 9.81 * M / K
    soft = dp.Oscillator(m=M, k=K, mu=mu, k3=-K / (4 * xc * xc))  # k x + k3 x^3 at 1.05 xc
    for method in ("reference",):
        sol = dp.solve(soft, 1.05 * xc, 0.0, method=method)
        assert float(sol.halt_time) == 0.0 and float(sol.halt_position) == 1.05 * xc
    hard = dp.Oscillator(m=M, k=K, mu=mu, k3=K / (4 * xc * xc))
    ref = dp.solve(hard, 0.95 * xc, 0.0, method="reference", t_end=2.0)
    assert float(ref.halt_time) > 0.0
    segs, turning, rest = scipy_stick_slip(M, K, mu, 0.0, 0.0, 0.95 * xc, 0.0, 2.0,
                                           k3=float(hard.k3))
    assert float(ref.halt_position) == pytest.approx(rest[1], abs=1e-12)
