"""The numbers in the fit's messages say what the sentence claims (issue 36, item 5)."""

from __future__ import annotations

import re

import pytest

from dampax._fit._text import lower_cost, time_span


@pytest.mark.parametrize("new, old", [(0.032391, 0.0323914), (1.0, 2.0), (5e-9, 5.0000001e-9),
                                      (2333.0, 2333.0000004)])
def test_a_lower_cost_prints_a_lower_number(new, old):
    text = lower_cost(new, old)
    a, b = (float(v) for v in re.match(r"(\S+) < (\S+),", text).groups())
    assert a < b and a == pytest.approx(new, rel=1e-3) and b == pytest.approx(old, rel=1e-3)


@pytest.mark.parametrize("lo, hi", [(2333.1, 2333.4), (0.5, 12.0), (1e-3, 1.0001e-3)])
def test_a_time_span_prints_two_different_ends(lo, hi):
    a, b = (float(v) for v in re.match(r"(\S+)-(\S+) s", time_span(lo, hi)).groups())
    assert a < b and a == pytest.approx(lo, rel=1e-4) and b == pytest.approx(hi, rel=1e-4)


def test_a_held_k3_is_reported_as_fixed():
    """issue 36: dp.fit(..., k3=...) names the held k3 in params, fixed, the report and JSON."""
    import json

    import numpy as np

    import dampax as dp

    ts = np.linspace(0.0, 12.0, 1500)
    osc = dp.Oscillator(m=1.0, k=4.0, D=0.5, k3=2.0)
    sol = dp.solve(osc, 0.3, 0.0, method="reference", t_end=12.0, ts=ts)
    x = np.asarray(sol.x(ts)) + 0.002 * np.random.default_rng(0).standard_normal(ts.size)
    res = dp.fit(ts, x, oscillator=dp.Oscillator(m=1.0, k=4.0), free=("D",), k3=2.0,
                 model="ansatz")
    assert res.params["k3"] == 2.0 and res.fixed["k3"] == 2.0
    assert json.loads(json.dumps(res.to_dict(), default=str))["fixed"]["k3"] == 2.0
    assert any(line.split()[:3] == ["k3:", "2", "(fixed)"] for line in res.report().splitlines())


def test_residual_structure_finds_a_swing_and_skips_a_curve_that_is_not_finite():
    """The residual test of the fit's verdict (_checks.residual_structure): white noise passes,
    a swing at w0 in two periods of the window is found there, and residuals that are not
    finite everywhere (a held refit of a k3 or mu_s search whose model diverged) give no test
    (p NaN, its fit fails elsewhere), not numpy's LinAlgError, which was counted a refusal of
    the whole fit (3 draws of benchmarks/fit_calibration.py)."""
    import numpy as np

    from dampax._fit._checks import residual_structure

    rng = np.random.default_rng(1)
    t = np.arange(4000) * 0.01
    w0 = 2.0 * np.pi
    r = rng.standard_normal(t.size)
    assert residual_structure(t, r, w0)["p"] > 0.01
    bump = np.where((t > 20) & (t < 22), 1.5 * np.cos(w0 * t), 0.0)
    found = residual_structure(t, r + bump, w0)
    assert found["p"] < 1e-6 and 19.5 < found["worst"][0] < 22.5
    r[100] = np.nan
    assert np.isnan(residual_structure(t, r, w0)["p"])
