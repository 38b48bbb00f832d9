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
