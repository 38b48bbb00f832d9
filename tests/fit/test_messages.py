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
