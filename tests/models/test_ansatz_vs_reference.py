"""The analytic models against the reference integrator (issue 3), and stick-slip at rest.

The reference's own checks (exact Coulomb, scipy DOP853, finite differences) are in
test_reference.py.
"""

import numpy as np
import pytest
from helpers import W0, ratios_to_constants

import dampax as dp

T_END = 12.0


def ref(mu, b, D, x0, v0, **kw):
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D)
    return dp.solve(osc, x0, v0, method="reference", t_end=kw.pop("t_end", T_END), **kw)


def test_start_at_rest_inside_and_outside_band():
    mu = 0.3  # xc = 0.098 m
    inside = ref(mu, 0.0, 0.0, 0.05, 0.0)
    assert float(inside.halt_time) == 0.0 and float(inside.halt_position) == 0.05
    np.testing.assert_array_equal(inside.x(np.linspace(0, 3, 5)), 0.05)
    outside = ref(mu, 0.0, 0.0, -0.2, 0.0)  # moves towards the centre: x increases
    assert float(outside.x(0.1)) > -0.2
    xc = mu * 9.81 / 30.0
    # one swing to -x0 + 2 sgn(x0) xc = 0.0038 m, inside the band: it sticks there
    assert float(outside.halt_position) == pytest.approx(0.2 - 2 * xc, abs=2e-11)
    assert float(outside.halt_time) == pytest.approx(np.pi / W0, rel=1e-10)


@pytest.mark.parametrize("ratios, tail", [((0.0, 0.1), None), ((0.03, 0.0), "coulomb"),
                                          ((0.05, 0.0), "coulomb")])
def test_ansatz_within_one_percent_of_reference_in_excellent_cases(ratios, tail):
    # the paper's "excellent" cases from rest at A0: quadratic d2 A0/w0 = 0.1 and the improved
    # Coulomb solution (eq. 41). The paper judges by the envelope: every turning point and the
    # rest position lie within 1 % of A0 of the reference. (The max-norm error is larger, 1.7 %
    # and 4.4 % of A0, from the shifted zero crossings; the error maps quantify that.)
    mu, b, D = ratios_to_constants(ratios[0], 0.0, ratios[1])
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D)
    ansatz = dp.solve(osc, 0.2, 0.0, tail=tail)
    reference = dp.solve(osc, 0.2, 0.0, method="reference", t_end=T_END)
    ta, xa = (np.asarray(a) for a in dp.turning_points(ansatz, 20))
    tr, xr = (np.asarray(a) for a in dp.turning_points(reference, 20))
    np.testing.assert_array_equal(np.isfinite(ta), np.isfinite(tr))
    finite = np.isfinite(ta)
    assert np.max(np.abs(xa[finite] - xr[finite])) < 0.01 * 0.2
    if tail:
        assert abs(float(ansatz.halt_position) - float(reference.halt_position)) < 0.01 * 0.2
    ts = np.linspace(0.0, T_END, 3000)
    err = np.abs(np.asarray(ansatz.x(ts)) - np.asarray(reference.x(ts))) / 0.2
    assert np.sqrt(np.mean(err**2)) < 0.035 and np.max(err) < 0.07
